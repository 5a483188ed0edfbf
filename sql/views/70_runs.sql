-- runs: one row per onboarding run, newest first, with its status, duration, per-stage seconds, what the
-- removal guard saw (active files before the run, how many vanished, the limit, whether it stopped the run),
-- and the Ray nodes it lost and the meshes it redid (from the cluster entry of config_json).
CREATE OR REPLACE VIEW runs AS
SELECT
    CAST(run_id AS VARCHAR) AS run_id,
    CAST(engine AS VARCHAR) AS engine,
    CAST(profile AS VARCHAR) AS profile,
    CAST(library_root AS VARCHAR) AS library_root,
    CAST(status AS VARCHAR) AS status,
    CAST(started_at AS TIMESTAMPTZ) AS started_at,
    CAST(finished_at AS TIMESTAMPTZ) AS finished_at,
    CAST(epoch(finished_at) - epoch(started_at) AS DOUBLE) AS seconds,
    CAST(n_files AS BIGINT) AS n_files,
    CAST(n_added AS BIGINT) AS n_added,
    CAST(n_removed AS BIGINT) AS n_removed,
    CAST(n_skipped AS BIGINT) AS n_skipped,
    CAST(n_failed AS BIGINT) AS n_failed,
    CAST(stage_seconds_json AS JSON) AS stage_seconds,
    CAST(json_extract(config_json, '$.removal_guard') AS JSON) AS removal_guard,
    CAST(json_extract(config_json, '$.cluster.lost_nodes') AS VARCHAR[]) AS lost_nodes,
    CAST(json_extract(config_json, '$.cluster.meshes_redone') AS BIGINT) AS n_redone
FROM runs_all
ORDER BY run_id DESC;

COMMENT ON VIEW runs IS 'onboarding runs, newest first';
COMMENT ON COLUMN runs.run_id IS 'sortable run id (UTC start time + random suffix)';
COMMENT ON COLUMN runs.engine IS 'local | ray';
COMMENT ON COLUMN runs.profile IS 'offline | paper';
COMMENT ON COLUMN runs.library_root IS 'the onboarded library';
COMMENT ON COLUMN runs.status IS 'ok | interrupted (SIGINT/SIGTERM; finished work kept) | failed (an error) | refused (the removal guard stopped it before any commit); only ok runs decide what is current';
COMMENT ON COLUMN runs.started_at IS 'start time';
COMMENT ON COLUMN runs.finished_at IS 'end time';
COMMENT ON COLUMN runs.seconds IS 'wall-clock duration';
COMMENT ON COLUMN runs.n_files IS 'mesh files found';
COMMENT ON COLUMN runs.n_added IS 'new or changed files';
COMMENT ON COLUMN runs.n_removed IS 'vanished or replaced files';
COMMENT ON COLUMN runs.n_skipped IS 'meshes with nothing left to do';
COMMENT ON COLUMN runs.n_failed IS 'meshes or files that failed in this run';
COMMENT ON COLUMN runs.stage_seconds IS 'seconds per stage as JSON';
COMMENT ON COLUMN runs.removal_guard IS 'the removal guard: active files before the run, vanished, share, max_removed, allow_removal, tripped';
COMMENT ON COLUMN runs.lost_nodes IS 'Ray nodes lost during the run, as IP (node id prefix); empty for none, NULL before this was recorded';
COMMENT ON COLUMN runs.n_redone IS 'meshes re-submitted after their batch was lost with a node or worker (not failed)';
