-- Audit errors_by_stage: the failures that still stand (errors_open), grouped by stage and reason, most
-- widespread first, with an example file to look at.
SELECT
    CAST(e.stage AS VARCHAR) AS stage,
    CAST(e.error_type AS VARCHAR) AS error_type,
    CAST(e.reason AS VARCHAR) AS reason,
    CAST(count(*) AS BIGINT) AS n_errors,
    CAST(count(DISTINCT coalesce(e.mesh_id, e.source_path)) AS BIGINT) AS n_files,
    CAST(min(e.source_path) AS VARCHAR) AS example_path,
    CAST(max(e.at) AS TIMESTAMPTZ) AS last_at
FROM errors_open AS e
GROUP BY e.stage, e.error_type, e.reason
ORDER BY n_files DESC, stage, reason;
