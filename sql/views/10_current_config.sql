-- current_config: the configuration of the latest successful onboarding run (the latest row of runs_all
-- with status 'ok'; interrupted, failed and refused runs never become current, as for queries).
-- "Current" everywhere else means "what this config writes": its fingerprints, models and view count.
CREATE OR REPLACE VIEW current_config AS
SELECT
    CAST(run_id AS VARCHAR) AS run_id,
    CAST(profile AS VARCHAR) AS profile,
    CAST(engine AS VARCHAR) AS engine,
    CAST(json_extract_string(config_json, '$.render.cameras') AS VARCHAR) AS cameras,
    CAST(
        CASE
            WHEN json_extract_string(config_json, '$.render.cameras') = 'cap3d' THEN 8
            ELSE CAST(json_extract(config_json, '$.render.views_per_ring') AS INTEGER)
                * json_array_length(json_extract(config_json, '$.render.elevations_deg'))
        END AS INTEGER
    ) AS expected_views,
    CAST(
        CASE
            WHEN json_extract_string(config_json, '$.render.cameras') = 'cap3d' THEN 8
            ELSE CAST(json_extract(config_json, '$.render.views_per_ring') AS INTEGER)
                * json_array_length(json_extract(config_json, '$.render.elevations_deg'))
        END
        + CASE WHEN coalesce(CAST(json_extract(config_json, '$.render.extra_bg_view') AS BOOLEAN), false) THEN 1 ELSE 0 END
        AS INTEGER
    ) AS expected_rendered_views,
    CAST(config_json AS JSON) AS config
FROM runs_all
WHERE status = 'ok'
ORDER BY run_id DESC
LIMIT 1;

COMMENT ON VIEW current_config IS 'the configuration of the latest successful onboarding run';
COMMENT ON COLUMN current_config.run_id IS 'the run whose configuration is current';
COMMENT ON COLUMN current_config.profile IS 'model profile of that run (offline | paper)';
COMMENT ON COLUMN current_config.engine IS 'executor of that run (local | ray)';
COMMENT ON COLUMN current_config.cameras IS 'camera layout (oscar | cap3d)';
COMMENT ON COLUMN current_config.expected_views IS 'captioned views every mesh should have under this config (the camera layout)';
COMMENT ON COLUMN current_config.expected_rendered_views IS 'rendered views every mesh should have: the layout plus the extra background view (--extra-bg-view), which has image embeddings and local features but no caption';
COMMENT ON COLUMN current_config.config IS 'the full configuration as JSON (models, render options, fingerprints)';
