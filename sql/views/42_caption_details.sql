-- caption_details: every current caption next to its view (camera, image) and its mesh (name, path), the
-- table to read when auditing captions by eye.
CREATE OR REPLACE VIEW caption_details AS
SELECT
    CAST(c.mesh_id AS VARCHAR) AS mesh_id,
    CAST(m.name AS VARCHAR) AS name,
    CAST(m.source_path AS VARCHAR) AS source_path,
    CAST(c.view_index AS SMALLINT) AS view_index,
    CAST(v.azimuth_deg AS FLOAT) AS azimuth_deg,
    CAST(v.elevation_deg AS FLOAT) AS elevation_deg,
    CAST(c.captioner_id AS VARCHAR) AS captioner_id,
    CAST(c.prompt_style AS VARCHAR) AS prompt_style,
    CAST(c.caption AS VARCHAR) AS caption,
    CAST(c.caption_chars AS BIGINT) AS caption_chars,
    CAST(c.caption_words AS BIGINT) AS caption_words,
    CAST(v.image AS BLOB) AS image,
    CAST(c.run_id AS VARCHAR) AS run_id
FROM captions AS c
JOIN mesh_names AS m ON m.mesh_id = c.mesh_id
LEFT JOIN views_latest AS v
    ON v.mesh_id = c.mesh_id AND v.view_index = c.view_index AND v.fingerprint = c.view_fingerprint;

COMMENT ON VIEW caption_details IS 'current captions joined with their view and mesh';
COMMENT ON COLUMN caption_details.mesh_id IS 'the captioned mesh';
COMMENT ON COLUMN caption_details.name IS 'readable model name';
COMMENT ON COLUMN caption_details.source_path IS 'path relative to the library root';
COMMENT ON COLUMN caption_details.view_index IS 'the captioned view';
COMMENT ON COLUMN caption_details.azimuth_deg IS 'camera azimuth of the view in degrees';
COMMENT ON COLUMN caption_details.elevation_deg IS 'camera elevation of the view in degrees';
COMMENT ON COLUMN caption_details.captioner_id IS 'captioner (backend:model)';
COMMENT ON COLUMN caption_details.prompt_style IS 'blind | comma | caption | attributes';
COMMENT ON COLUMN caption_details.caption IS 'the caption';
COMMENT ON COLUMN caption_details.caption_chars IS 'characters in the caption';
COMMENT ON COLUMN caption_details.caption_words IS 'alphanumeric words in the caption';
COMMENT ON COLUMN caption_details.image IS 'PNG bytes of the captioned view (NULL if the view is gone)';
COMMENT ON COLUMN caption_details.run_id IS 'run that wrote the caption';
