-- captions: the captions the current config uses: latest rows at the current caption fingerprint, of
-- active meshes only.
CREATE OR REPLACE VIEW captions AS
SELECT
    CAST(c.mesh_id AS VARCHAR) AS mesh_id,
    CAST(c.view_index AS SMALLINT) AS view_index,
    CAST(c.captioner_id AS VARCHAR) AS captioner_id,
    CAST(c.prompt_style AS VARCHAR) AS prompt_style,
    CAST(c.caption AS VARCHAR) AS caption,
    CAST(length(coalesce(c.caption, '')) AS BIGINT) AS caption_chars,
    CAST(len(regexp_extract_all(coalesce(c.caption, ''), '[A-Za-z0-9]+')) AS BIGINT) AS caption_words,
    CAST(c.prompt AS VARCHAR) AS prompt,
    CAST(c.fingerprint AS VARCHAR) AS fingerprint,
    CAST(c.view_fingerprint AS VARCHAR) AS view_fingerprint,
    CAST(c.run_id AS VARCHAR) AS run_id
FROM captions_latest AS c
JOIN current_fingerprints AS f ON f.stage = 'caption' AND f.fingerprint = c.fingerprint
WHERE c.mesh_id IN (SELECT mesh_id FROM meshes);

COMMENT ON VIEW captions IS 'current captions of active meshes (latest rows at the current caption fingerprint)';
COMMENT ON COLUMN captions.mesh_id IS 'the captioned mesh';
COMMENT ON COLUMN captions.view_index IS 'the captioned view';
COMMENT ON COLUMN captions.captioner_id IS 'captioner (backend:model)';
COMMENT ON COLUMN captions.prompt_style IS 'blind | comma | caption | attributes';
COMMENT ON COLUMN captions.caption IS 'the caption';
COMMENT ON COLUMN captions.caption_chars IS 'characters in the caption (0 when NULL)';
COMMENT ON COLUMN captions.caption_words IS 'alphanumeric words in the caption';
COMMENT ON COLUMN captions.prompt IS 'prompt text given to the captioner';
COMMENT ON COLUMN captions.fingerprint IS 'caption config fingerprint (the current one)';
COMMENT ON COLUMN captions.view_fingerprint IS 'fingerprint of the view that was captioned';
COMMENT ON COLUMN captions.run_id IS 'run that wrote this row';
