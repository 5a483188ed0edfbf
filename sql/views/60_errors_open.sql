-- errors_open: the failures that still stand: the latest error per (stage, mesh or file, fingerprint),
-- at a fingerprint of the current config (discovery errors have none), for a file that is still in the
-- library, and not resolved since (a later run produced that stage's rows at that fingerprint, or a
-- discovery error's file is now onboarded).
CREATE OR REPLACE VIEW errors_open AS
WITH latest AS (
    SELECT *
    FROM errors_all
    QUALIFY row_number() OVER (
        PARTITION BY stage, coalesce(mesh_id, source_path), fingerprint ORDER BY "at" DESC, run_id DESC
    ) = 1
),
produced AS (
    SELECT 'render' AS stage, mesh_id, fingerprint FROM views_latest
    UNION ALL
    SELECT 'caption', mesh_id, fingerprint FROM captions_latest
    UNION ALL
    SELECT 'embed_text', mesh_id, fingerprint FROM text_embeddings_latest
    UNION ALL
    SELECT 'embed_image', mesh_id, fingerprint FROM image_embeddings_latest
    UNION ALL
    SELECT 'patches', mesh_id, fingerprint FROM view_patches_all
    UNION ALL
    SELECT 'features', mesh_id, fingerprint FROM view_features_all
)
SELECT
    CAST(e.stage AS VARCHAR) AS stage,
    CAST(e.error_type AS VARCHAR) AS error_type,
    CAST(e.reason AS VARCHAR) AS reason,
    CAST(e.mesh_id AS VARCHAR) AS mesh_id,
    CAST(e.source_path AS VARCHAR) AS source_path,
    CAST(e.fingerprint AS VARCHAR) AS fingerprint,
    CAST(e.at AS TIMESTAMPTZ) AS at,
    CAST(e.run_id AS VARCHAR) AS run_id
FROM latest AS e
WHERE (
        e.fingerprint IS NULL
        OR e.fingerprint IN (SELECT fingerprint FROM current_fingerprints)
    )
    AND (
        e.mesh_id IS NULL
        OR e.mesh_id IN (SELECT mesh_id FROM meshes_latest WHERE status <> 'removed')
    )
    AND NOT EXISTS (
        SELECT 1 FROM produced AS p
        WHERE p.stage = e.stage AND p.mesh_id = e.mesh_id AND p.fingerprint = e.fingerprint
    )
    AND NOT (
        e.stage = 'discover'
        AND e.source_path IN (SELECT source_path FROM meshes WHERE seen_at > e.at)
    );

COMMENT ON VIEW errors_open IS 'failures that still stand under the current config';
COMMENT ON COLUMN errors_open.stage IS 'discover | render | caption | embed_text | embed_image';
COMMENT ON COLUMN errors_open.error_type IS 'exception class, Timeout or WorkerCrash';
COMMENT ON COLUMN errors_open.reason IS 'one-line reason';
COMMENT ON COLUMN errors_open.mesh_id IS 'the failed mesh (NULL for discovery errors)';
COMMENT ON COLUMN errors_open.source_path IS 'the failed file, relative to its library root';
COMMENT ON COLUMN errors_open.fingerprint IS 'fingerprint of the stage config that failed';
COMMENT ON COLUMN errors_open.at IS 'when it last failed';
COMMENT ON COLUMN errors_open.run_id IS 'run in which it last failed';
