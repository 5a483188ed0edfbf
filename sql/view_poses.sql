-- Query path: the camera of each rendered view of some meshes (the pose-estimator hand-off), without
-- the PNG bytes.
-- Parameters: $mesh_ids (VARCHAR[]) mesh ids; $render_fingerprint (VARCHAR) the onboarding run's.
-- Inputs: views_all (pipeline.db.connect).
SELECT
    CAST(mesh_id AS VARCHAR) AS mesh_id,
    CAST(view_index AS SMALLINT) AS view_index,
    camera_pose,                                     -- camera-to-world, OpenGL axes, row-major 4x4
    CAST(yfov_deg AS DOUBLE) AS yfov_deg,
    CAST(width AS INTEGER) AS width,
    CAST(height AS INTEGER) AS height
FROM views_all
WHERE fingerprint = $render_fingerprint AND list_contains($mesh_ids, mesh_id)
QUALIFY row_number() OVER (PARTITION BY mesh_id, view_index ORDER BY run_id DESC) = 1
ORDER BY mesh_id, view_index;
