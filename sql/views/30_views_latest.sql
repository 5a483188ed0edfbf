-- views_latest: the latest row of every (mesh_id, view_index, fingerprint) of the views table, any
-- fingerprint, any mesh status (what Store.read_latest returns).
CREATE OR REPLACE VIEW views_latest AS
SELECT
    CAST(mesh_id AS VARCHAR) AS mesh_id,
    CAST(view_index AS SMALLINT) AS view_index,
    CAST(azimuth_deg AS FLOAT) AS azimuth_deg,
    CAST(elevation_deg AS FLOAT) AS elevation_deg,
    CAST(camera_pose AS DOUBLE[16]) AS camera_pose,
    CAST(yfov_deg AS FLOAT) AS yfov_deg,
    CAST(width AS INTEGER) AS width,
    CAST(height AS INTEGER) AS height,
    CAST(image AS BLOB) AS image,
    CAST(fingerprint AS VARCHAR) AS fingerprint,
    CAST(run_id AS VARCHAR) AS run_id
FROM views_all
QUALIFY row_number() OVER (PARTITION BY mesh_id, view_index, fingerprint ORDER BY run_id DESC) = 1;

COMMENT ON VIEW views_latest IS 'latest row per (mesh_id, view_index, fingerprint) of the rendered views';
COMMENT ON COLUMN views_latest.mesh_id IS 'the rendered mesh';
COMMENT ON COLUMN views_latest.view_index IS '0-based view number';
COMMENT ON COLUMN views_latest.azimuth_deg IS 'camera azimuth in degrees';
COMMENT ON COLUMN views_latest.elevation_deg IS 'camera elevation in degrees';
COMMENT ON COLUMN views_latest.camera_pose IS 'camera-to-world 4x4, OpenGL convention, row-major';
COMMENT ON COLUMN views_latest.yfov_deg IS 'vertical field of view in degrees';
COMMENT ON COLUMN views_latest.width IS 'image width in pixels';
COMMENT ON COLUMN views_latest.height IS 'image height in pixels';
COMMENT ON COLUMN views_latest.image IS 'PNG bytes';
COMMENT ON COLUMN views_latest.fingerprint IS 'render config fingerprint';
COMMENT ON COLUMN views_latest.run_id IS 'run that wrote this row';
