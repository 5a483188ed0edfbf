-- error_summary: errors by stage: every error row ever written, how many still stand (errors_open), and
-- when the stage last failed.
CREATE OR REPLACE VIEW error_summary AS
WITH open AS (
    SELECT stage, count(*) AS n_open, count(DISTINCT coalesce(mesh_id, source_path)) AS n_open_files
    FROM errors_open
    GROUP BY stage
)
SELECT
    CAST(e.stage AS VARCHAR) AS stage,
    CAST(count(*) AS BIGINT) AS n_errors,
    CAST(count(DISTINCT coalesce(e.mesh_id, e.source_path)) AS BIGINT) AS n_files,
    CAST(coalesce(any_value(o.n_open), 0) AS BIGINT) AS n_open,
    CAST(coalesce(any_value(o.n_open_files), 0) AS BIGINT) AS n_open_files,
    CAST(min(e.at) AS TIMESTAMPTZ) AS first_at,
    CAST(max(e.at) AS TIMESTAMPTZ) AS last_at
FROM errors_all AS e
LEFT JOIN open AS o ON o.stage = e.stage
GROUP BY e.stage;

COMMENT ON VIEW error_summary IS 'errors by stage, all time and still open';
COMMENT ON COLUMN error_summary.stage IS 'discover | render | caption | embed_text | embed_image';
COMMENT ON COLUMN error_summary.n_errors IS 'error rows ever written';
COMMENT ON COLUMN error_summary.n_files IS 'distinct meshes (or files, for discovery) that ever failed';
COMMENT ON COLUMN error_summary.n_open IS 'errors that still stand (see errors_open)';
COMMENT ON COLUMN error_summary.n_open_files IS 'distinct meshes or files with an open error';
COMMENT ON COLUMN error_summary.first_at IS 'first failure';
COMMENT ON COLUMN error_summary.last_at IS 'latest failure';
