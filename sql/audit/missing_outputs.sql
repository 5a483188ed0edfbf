-- Audit missing_outputs: active meshes that lack some of the rows the current config (the latest successful
-- run's) should have written: views, captions, text embeddings, the embeddings of any image encoder role,
-- the learned encoder's patch tokens, or local features. Returns one row per (mesh, stage) with fewer rows than that render config makes for
-- the stage (current_config.expected_views captioned views; expected_rendered_views with the extra
-- background view, for render, image embeddings, patch tokens and features), and the open error that explains it, if
-- any (no error: the mesh was never processed, e.g. a run was interrupted). The probe stage (query
-- adapter) makes up to --probes rows per mesh, fewer where a chosen view shows nothing: at least one is
-- expected.
WITH per_view AS (  -- stages whose every-run rows are counted at the current fingerprint, by distinct view
    SELECT 'probe' AS stage, mesh_id, view_index, fingerprint FROM probe_embeddings_all
    UNION ALL
    SELECT 'patches', mesh_id, view_index, fingerprint FROM view_patches_all
    UNION ALL
    SELECT 'features', mesh_id, view_index, fingerprint FROM view_features_all
),
have AS (
    SELECT 'render' AS stage, mesh_id, count(*) AS n FROM views GROUP BY mesh_id
    UNION ALL
    SELECT 'caption', mesh_id, count(*) FROM captions GROUP BY mesh_id
    UNION ALL
    SELECT 'embed_text', mesh_id, count(*) FROM text_embeddings GROUP BY mesh_id
    UNION ALL
    SELECT 'embed_image:' || role, mesh_id, count(*) FROM image_embeddings GROUP BY role, mesh_id
    UNION ALL
    SELECT r.stage, r.mesh_id, count(DISTINCT r.view_index)
    FROM per_view AS r
    JOIN current_fingerprints AS f ON f.stage = r.stage AND f.fingerprint = r.fingerprint
    WHERE r.mesh_id IN (SELECT mesh_id FROM meshes)
    GROUP BY r.stage, r.mesh_id
),
expected AS (
    SELECT
        f.*,
        CASE
            WHEN f.stage IN ('caption', 'embed_text') THEN c.expected_views
            WHEN f.stage = 'probe' THEN 1
            ELSE c.expected_rendered_views
        END AS n_expected
    FROM current_fingerprints AS f
    CROSS JOIN current_config AS c
)
SELECT
    CAST(m.mesh_id AS VARCHAR) AS mesh_id,
    CAST(m.name AS VARCHAR) AS name,
    CAST(m.source_path AS VARCHAR) AS source_path,
    CAST(f.stage AS VARCHAR) AS stage,
    CAST(f.table_name AS VARCHAR) AS table_name,
    CAST(f.model_id AS VARCHAR) AS model_id,
    CAST(coalesce(h.n, 0) AS BIGINT) AS n_rows,
    CAST(f.n_expected AS BIGINT) AS expected_rows,
    CAST((
        SELECT any_value(e.reason) FROM errors_open AS e
        WHERE e.mesh_id = m.mesh_id AND e.stage = split_part(f.stage, ':', 1) AND e.fingerprint = f.fingerprint
    ) AS VARCHAR) AS open_error
FROM mesh_names AS m
CROSS JOIN expected AS f
LEFT JOIN have AS h ON h.stage = f.stage AND h.mesh_id = m.mesh_id
WHERE coalesce(h.n, 0) < f.n_expected
ORDER BY mesh_id, stage;
