-- mesh_names: one row per active mesh_id (a mesh_id can sit at several paths: identical files), with a
-- readable name and path to show next to its views, captions and embeddings.
CREATE OR REPLACE VIEW mesh_names AS
SELECT
    CAST(mesh_id AS VARCHAR) AS mesh_id,
    CAST(min(name) AS VARCHAR) AS name,
    CAST(min(source_path) AS VARCHAR) AS source_path,
    CAST(count(*) AS BIGINT) AS n_paths
FROM meshes
GROUP BY mesh_id;

COMMENT ON VIEW mesh_names IS 'one row per active mesh_id with a readable name';
COMMENT ON COLUMN mesh_names.mesh_id IS 'sha256 of the mesh file and every file it references';
COMMENT ON COLUMN mesh_names.name IS 'readable model name (the smallest one when several files share the mesh)';
COMMENT ON COLUMN mesh_names.source_path IS 'path relative to the library root (the smallest one when several)';
COMMENT ON COLUMN mesh_names.n_paths IS 'number of active files with this content';
