-- encoders: the embeddings per encoder: one row per (table, encoder, fingerprint) with its row and mesh
-- counts, and whether the current config uses it. Old encoders and fingerprints stay listed until
-- `compact` (or a cleanup) drops their rows.
CREATE OR REPLACE VIEW encoders AS
WITH latest AS (
    SELECT 'text_embeddings' AS table_name, mesh_id, encoder_id, dim, fingerprint, run_id
    FROM text_embeddings_latest
    UNION ALL
    SELECT 'image_embeddings' AS table_name, mesh_id, encoder_id, dim, fingerprint, run_id
    FROM image_embeddings_latest
)
SELECT
    CAST(l.table_name AS VARCHAR) AS table_name,
    CAST(l.encoder_id AS VARCHAR) AS encoder_id,
    CAST(any_value(l.dim) AS INTEGER) AS dim,
    CAST(l.fingerprint AS VARCHAR) AS fingerprint,
    CAST(bool_or(f.fingerprint IS NOT NULL) AS BOOLEAN) AS is_current,
    CAST(count(*) AS BIGINT) AS n_rows,
    CAST(count(DISTINCT l.mesh_id) AS BIGINT) AS n_meshes,
    CAST(max(l.run_id) AS VARCHAR) AS last_run_id
FROM latest AS l
LEFT JOIN current_fingerprints AS f ON f.fingerprint = l.fingerprint AND f.table_name = l.table_name
GROUP BY l.table_name, l.encoder_id, l.fingerprint;

COMMENT ON VIEW encoders IS 'embeddings per (table, encoder, fingerprint) with counts';
COMMENT ON COLUMN encoders.table_name IS 'text_embeddings | image_embeddings';
COMMENT ON COLUMN encoders.encoder_id IS 'encoder (backend:model)';
COMMENT ON COLUMN encoders.dim IS 'vector width';
COMMENT ON COLUMN encoders.fingerprint IS 'embedding config fingerprint';
COMMENT ON COLUMN encoders.is_current IS 'the current config writes this fingerprint';
COMMENT ON COLUMN encoders.n_rows IS 'latest rows (one per mesh and view)';
COMMENT ON COLUMN encoders.n_meshes IS 'distinct meshes, active or not';
COMMENT ON COLUMN encoders.last_run_id IS 'most recent run that wrote rows of this fingerprint';
