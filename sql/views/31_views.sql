-- views: the rendered views the current config uses: latest rows at the current render fingerprint, of
-- active meshes only.
CREATE OR REPLACE VIEW views AS
SELECT
    CAST(v.mesh_id AS VARCHAR) AS mesh_id,
    CAST(v.view_index AS SMALLINT) AS view_index,
    CAST(v.azimuth_deg AS FLOAT) AS azimuth_deg,
    CAST(v.elevation_deg AS FLOAT) AS elevation_deg,
    CAST(v.camera_pose AS DOUBLE[16]) AS camera_pose,
    CAST(v.width AS INTEGER) AS width,
    CAST(v.height AS INTEGER) AS height,
    CAST(octet_length(v.image) AS BIGINT) AS image_bytes,
    CAST(v.image AS BLOB) AS image,
    CAST(v.fingerprint AS VARCHAR) AS fingerprint,
    CAST(v.run_id AS VARCHAR) AS run_id
FROM views_latest AS v
JOIN current_fingerprints AS f ON f.stage = 'render' AND f.fingerprint = v.fingerprint
WHERE v.mesh_id IN (SELECT mesh_id FROM meshes);

COMMENT ON VIEW views IS 'current views of active meshes (latest rows at the current render fingerprint)';
COMMENT ON COLUMN views.mesh_id IS 'the rendered mesh';
COMMENT ON COLUMN views.view_index IS '0-based view number';
COMMENT ON COLUMN views.azimuth_deg IS 'camera azimuth in degrees';
COMMENT ON COLUMN views.elevation_deg IS 'camera elevation in degrees';
COMMENT ON COLUMN views.camera_pose IS 'camera-to-world 4x4, OpenGL convention, row-major';
COMMENT ON COLUMN views.width IS 'image width in pixels';
COMMENT ON COLUMN views.height IS 'image height in pixels';
COMMENT ON COLUMN views.image_bytes IS 'size of the PNG in bytes';
COMMENT ON COLUMN views.image IS 'PNG bytes';
COMMENT ON COLUMN views.fingerprint IS 'render config fingerprint (the current one)';
COMMENT ON COLUMN views.run_id IS 'run that wrote this row';
