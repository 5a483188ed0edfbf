-- meshes_latest: the latest row of every (library_root, source_path, mesh_id), whatever its status.
-- Same rule as Store.read_latest: the row of the highest run_id wins.
CREATE OR REPLACE VIEW meshes_latest AS
SELECT
    CAST(mesh_id AS VARCHAR) AS mesh_id,
    CAST(source_path AS VARCHAR) AS source_path,
    CAST(library_root AS VARCHAR) AS library_root,
    CAST(name AS VARCHAR) AS name,
    CAST(format AS VARCHAR) AS format,
    CAST(file_size AS BIGINT) AS file_size,
    CAST(mtime_ns AS BIGINT) AS mtime_ns,
    CAST(deps AS STRUCT(path VARCHAR, size BIGINT, mtime_ns BIGINT)[]) AS deps,
    CAST(n_vertices AS BIGINT) AS n_vertices,
    CAST(n_faces AS BIGINT) AS n_faces,
    CAST(bounds_min AS DOUBLE[3]) AS bounds_min,
    CAST(bounds_max AS DOUBLE[3]) AS bounds_max,
    CAST(units_guess AS VARCHAR) AS units_guess,
    CAST(scale_to_unit AS DOUBLE) AS scale_to_unit,
    CAST(status AS VARCHAR) AS status,
    CAST(seen_at AS TIMESTAMPTZ) AS seen_at,
    CAST(run_id AS VARCHAR) AS run_id
FROM meshes_all
QUALIFY row_number() OVER (
    PARTITION BY library_root, source_path, mesh_id ORDER BY run_id DESC, seen_at DESC
) = 1;

COMMENT ON VIEW meshes_latest IS 'latest row per (library_root, source_path, mesh_id), any status';
COMMENT ON COLUMN meshes_latest.mesh_id IS 'sha256 of the mesh file and every file it references';
COMMENT ON COLUMN meshes_latest.source_path IS 'path of the file relative to library_root';
COMMENT ON COLUMN meshes_latest.library_root IS 'absolute path of the onboarded library';
COMMENT ON COLUMN meshes_latest.name IS 'readable model name (parent folder for generic file names, else the stem)';
COMMENT ON COLUMN meshes_latest.format IS 'obj | ply | glb | gltf | stl | off';
COMMENT ON COLUMN meshes_latest.file_size IS 'bytes of the mesh file';
COMMENT ON COLUMN meshes_latest.mtime_ns IS 'modification time of the mesh file (ns since the epoch)';
COMMENT ON COLUMN meshes_latest.deps IS 'referenced files (.mtl, textures) with size and mtime';
COMMENT ON COLUMN meshes_latest.n_vertices IS 'vertex count (NULL until rendered)';
COMMENT ON COLUMN meshes_latest.n_faces IS 'face count (NULL until rendered)';
COMMENT ON COLUMN meshes_latest.bounds_min IS 'bounding box minimum in file units';
COMMENT ON COLUMN meshes_latest.bounds_max IS 'bounding box maximum in file units';
COMMENT ON COLUMN meshes_latest.units_guess IS 'm | mm';
COMMENT ON COLUMN meshes_latest.scale_to_unit IS 'factor that maps the mesh to a unit bounding sphere';
COMMENT ON COLUMN meshes_latest.status IS 'active | removed (file vanished or changed) | failed (could not be rendered)';
COMMENT ON COLUMN meshes_latest.seen_at IS 'when the run that wrote this row saw the file';
COMMENT ON COLUMN meshes_latest.run_id IS 'run that wrote this row';
