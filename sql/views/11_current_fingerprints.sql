-- current_fingerprints: one row per stage of the current config: the fingerprint its rows carry, the table
-- they live in and the model that wrote them. Rows with any other fingerprint are stale.
CREATE OR REPLACE VIEW current_fingerprints AS
SELECT
    CAST(j.key AS VARCHAR) AS stage,
    CAST(
        CASE
            WHEN j.key = 'render' THEN 'views'
            WHEN j.key = 'caption' THEN 'captions'
            WHEN j.key = 'embed_text' THEN 'text_embeddings'
            WHEN j.key = 'features' THEN 'view_features'
            WHEN j.key = 'probe' THEN 'probe_embeddings'
            WHEN j.key = 'patches' THEN 'view_patches'
            ELSE 'image_embeddings'
        END AS VARCHAR
    ) AS table_name,
    CAST(
        CASE
            WHEN j.key = 'caption' THEN json_extract_string(c.config, '$.models.captioner')
            WHEN j.key = 'embed_text' THEN json_extract_string(c.config, '$.models.text_encoder')
            WHEN j.key IN ('probe', 'patches') THEN json_extract_string(c.config, '$.models.learned_encoder')
            WHEN j.key LIKE 'embed_image:%' THEN json_extract_string(c.config, '$.models.' || split_part(j.key, ':', 2))
        END AS VARCHAR
    ) AS model_id,
    CAST(json_extract_string(j.value, '$') AS VARCHAR) AS fingerprint
FROM current_config AS c, json_each(c.config, '$.fingerprints') AS j;

COMMENT ON VIEW current_fingerprints IS 'fingerprint, table and model of every stage of the current config';
COMMENT ON COLUMN current_fingerprints.stage IS 'render | caption | embed_text | embed_image:<role> | probe | patches | features';
COMMENT ON COLUMN current_fingerprints.table_name IS 'table the stage writes';
COMMENT ON COLUMN current_fingerprints.model_id IS 'captioner or encoder id (backend:model); NULL for render';
COMMENT ON COLUMN current_fingerprints.fingerprint IS 'fingerprint of the stage config and model, chained through its inputs';
