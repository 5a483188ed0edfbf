-- meshes: the library as it is now: one row per file that is present and onboarded (status 'active').
-- Vanished, replaced and failed files are left out (see meshes_latest for them).
CREATE OR REPLACE VIEW meshes AS
SELECT
    CAST(mesh_id AS VARCHAR) AS mesh_id,
    CAST(name AS VARCHAR) AS name,
    CAST(source_path AS VARCHAR) AS source_path,
    CAST(library_root AS VARCHAR) AS library_root,
    CAST(format AS VARCHAR) AS format,
    CAST(file_size AS BIGINT) AS file_size,
    CAST(n_vertices AS BIGINT) AS n_vertices,
    CAST(n_faces AS BIGINT) AS n_faces,
    CAST(bounds_min AS DOUBLE[3]) AS bounds_min,
    CAST(bounds_max AS DOUBLE[3]) AS bounds_max,
    CAST(units_guess AS VARCHAR) AS units_guess,
    CAST(seen_at AS TIMESTAMPTZ) AS seen_at,
    CAST(run_id AS VARCHAR) AS run_id
FROM meshes_latest
WHERE status = 'active';

COMMENT ON VIEW meshes IS 'active meshes: one row per present, onboarded file';
COMMENT ON COLUMN meshes.mesh_id IS 'sha256 of the mesh file and every file it references (several files may share one)';
COMMENT ON COLUMN meshes.name IS 'readable model name';
COMMENT ON COLUMN meshes.source_path IS 'path relative to library_root';
COMMENT ON COLUMN meshes.library_root IS 'absolute path of the onboarded library';
COMMENT ON COLUMN meshes.format IS 'obj | ply | glb | gltf | stl | off';
COMMENT ON COLUMN meshes.file_size IS 'bytes of the mesh file';
COMMENT ON COLUMN meshes.n_vertices IS 'vertex count';
COMMENT ON COLUMN meshes.n_faces IS 'face count';
COMMENT ON COLUMN meshes.bounds_min IS 'bounding box minimum in file units';
COMMENT ON COLUMN meshes.bounds_max IS 'bounding box maximum in file units';
COMMENT ON COLUMN meshes.units_guess IS 'm | mm';
COMMENT ON COLUMN meshes.seen_at IS 'when a run last recorded this file';
COMMENT ON COLUMN meshes.run_id IS 'run that wrote this row';
