-- Audit stale_rows: rows written under an older config: latest rows of views, captions and embeddings
-- whose fingerprint is not the current one of their table (or whose encoder the current config no longer
-- uses). Returns one row per (table, mesh, fingerprint) with its row count; has_current says the mesh
-- also has current rows in that table (the stale ones are then safe to drop), mesh_active whether the
-- mesh is still in the library.
WITH latest AS (
    SELECT 'views' AS table_name, mesh_id, CAST(NULL AS VARCHAR) AS model_id, fingerprint, run_id
    FROM views_latest
    UNION ALL
    SELECT 'captions', mesh_id, captioner_id, fingerprint, run_id FROM captions_latest
    UNION ALL
    SELECT 'text_embeddings', mesh_id, encoder_id, fingerprint, run_id FROM text_embeddings_latest
    UNION ALL
    SELECT 'image_embeddings', mesh_id, encoder_id, fingerprint, run_id FROM image_embeddings_latest
),
current_rows AS (
    SELECT l.table_name, l.mesh_id
    FROM latest AS l
    JOIN current_fingerprints AS f ON f.table_name = l.table_name AND f.fingerprint = l.fingerprint
    GROUP BY l.table_name, l.mesh_id
)
SELECT
    CAST(l.table_name AS VARCHAR) AS table_name,
    CAST(l.mesh_id AS VARCHAR) AS mesh_id,
    CAST(any_value(l.model_id) AS VARCHAR) AS model_id,
    CAST(l.fingerprint AS VARCHAR) AS fingerprint,
    CAST(count(*) AS BIGINT) AS n_rows,
    CAST(max(l.run_id) AS VARCHAR) AS last_run_id,
    CAST(bool_or(cr.mesh_id IS NOT NULL) AS BOOLEAN) AS has_current,
    CAST(l.mesh_id IN (SELECT mesh_id FROM meshes) AS BOOLEAN) AS mesh_active
FROM latest AS l
LEFT JOIN current_rows AS cr ON cr.table_name = l.table_name AND cr.mesh_id = l.mesh_id
WHERE NOT EXISTS (
    SELECT 1 FROM current_fingerprints AS f
    WHERE f.table_name = l.table_name AND f.fingerprint = l.fingerprint
)
GROUP BY l.table_name, l.mesh_id, l.fingerprint
ORDER BY table_name, mesh_id, fingerprint;
