-- captions_latest: the latest row of every (mesh_id, view_index, fingerprint) of the captions table, any
-- fingerprint, any mesh status.
CREATE OR REPLACE VIEW captions_latest AS
SELECT
    CAST(mesh_id AS VARCHAR) AS mesh_id,
    CAST(view_index AS SMALLINT) AS view_index,
    CAST(captioner_id AS VARCHAR) AS captioner_id,
    CAST(prompt_style AS VARCHAR) AS prompt_style,
    CAST(prompt AS VARCHAR) AS prompt,
    CAST(caption AS VARCHAR) AS caption,
    CAST(fingerprint AS VARCHAR) AS fingerprint,
    CAST(view_fingerprint AS VARCHAR) AS view_fingerprint,
    CAST(run_id AS VARCHAR) AS run_id
FROM captions_all
QUALIFY row_number() OVER (PARTITION BY mesh_id, view_index, fingerprint ORDER BY run_id DESC) = 1;

COMMENT ON VIEW captions_latest IS 'latest row per (mesh_id, view_index, fingerprint) of the captions';
COMMENT ON COLUMN captions_latest.mesh_id IS 'the captioned mesh';
COMMENT ON COLUMN captions_latest.view_index IS 'the captioned view';
COMMENT ON COLUMN captions_latest.captioner_id IS 'captioner (backend:model)';
COMMENT ON COLUMN captions_latest.prompt_style IS 'blind | comma | caption | attributes';
COMMENT ON COLUMN captions_latest.prompt IS 'prompt text given to the captioner';
COMMENT ON COLUMN captions_latest.caption IS 'the caption';
COMMENT ON COLUMN captions_latest.fingerprint IS 'caption config fingerprint';
COMMENT ON COLUMN captions_latest.view_fingerprint IS 'fingerprint of the view that was captioned';
COMMENT ON COLUMN captions_latest.run_id IS 'run that wrote this row';
