-- Audit missing_outputs: active meshes that lack some of the rows the current config should have written:
-- views, captions, text embeddings, or the embeddings of any image encoder role. Returns one row per
-- (mesh, stage) with fewer rows than current_config.expected_views, and the open error that explains it,
-- if any (no error: the mesh was never processed, e.g. a run was interrupted).
WITH have AS (
    SELECT 'render' AS stage, mesh_id, count(*) AS n FROM views GROUP BY mesh_id
    UNION ALL
    SELECT 'caption', mesh_id, count(*) FROM captions GROUP BY mesh_id
    UNION ALL
    SELECT 'embed_text', mesh_id, count(*) FROM text_embeddings GROUP BY mesh_id
    UNION ALL
    SELECT 'embed_image:' || role, mesh_id, count(*) FROM image_embeddings GROUP BY role, mesh_id
)
SELECT
    CAST(m.mesh_id AS VARCHAR) AS mesh_id,
    CAST(m.name AS VARCHAR) AS name,
    CAST(m.source_path AS VARCHAR) AS source_path,
    CAST(f.stage AS VARCHAR) AS stage,
    CAST(f.table_name AS VARCHAR) AS table_name,
    CAST(f.model_id AS VARCHAR) AS model_id,
    CAST(coalesce(h.n, 0) AS BIGINT) AS n_rows,
    CAST(c.expected_views AS BIGINT) AS expected_rows,
    CAST((
        SELECT any_value(e.reason) FROM errors_open AS e
        WHERE e.mesh_id = m.mesh_id AND e.stage = split_part(f.stage, ':', 1) AND e.fingerprint = f.fingerprint
    ) AS VARCHAR) AS open_error
FROM mesh_names AS m
CROSS JOIN current_fingerprints AS f
CROSS JOIN current_config AS c
LEFT JOIN have AS h ON h.stage = f.stage AND h.mesh_id = m.mesh_id
WHERE coalesce(h.n, 0) < c.expected_views
ORDER BY mesh_id, stage;
