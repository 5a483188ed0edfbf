-- Query path: the rendered views of the answer's candidates (for --explain contact sheets), with their
-- captions where the caption fingerprint matches.
-- Parameters: $mesh_ids (VARCHAR[]) candidate mesh ids; $render_fingerprint (VARCHAR);
--             $caption_fingerprint (VARCHAR).
-- Inputs: views_all, captions_all (pipeline.db.connect).
WITH v AS (
    SELECT mesh_id, view_index, image, azimuth_deg, elevation_deg
    FROM views_all
    WHERE fingerprint = $render_fingerprint AND list_contains($mesh_ids, mesh_id)
    QUALIFY row_number() OVER (PARTITION BY mesh_id, view_index ORDER BY run_id DESC) = 1
),
c AS (
    SELECT mesh_id, view_index, caption
    FROM captions_all
    WHERE fingerprint = $caption_fingerprint AND list_contains($mesh_ids, mesh_id)
    QUALIFY row_number() OVER (PARTITION BY mesh_id, view_index ORDER BY run_id DESC) = 1
)
SELECT
    CAST(v.mesh_id AS VARCHAR) AS mesh_id,
    CAST(v.view_index AS SMALLINT) AS view_index,
    CAST(v.azimuth_deg AS FLOAT) AS azimuth_deg,
    CAST(v.elevation_deg AS FLOAT) AS elevation_deg,
    v.image,                                         -- PNG bytes
    CAST(c.caption AS VARCHAR) AS caption            -- NULL when not captioned at this fingerprint
FROM v
LEFT JOIN c ON c.mesh_id = v.mesh_id AND c.view_index = v.view_index
ORDER BY v.mesh_id, v.view_index;
