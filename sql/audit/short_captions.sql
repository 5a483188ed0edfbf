-- Audit short_captions: current captions that are empty or too short to describe an object.
-- Returns one row per offending caption. Thresholds are DuckDB variables with defaults:
--   SET VARIABLE audit_min_caption_chars = 20;  -- fewer characters (after trimming) is too short
--   SET VARIABLE audit_min_caption_words = 3;   -- fewer alphanumeric words is too short
SELECT
    CAST(c.mesh_id AS VARCHAR) AS mesh_id,
    CAST(m.name AS VARCHAR) AS name,
    CAST(m.source_path AS VARCHAR) AS source_path,
    CAST(c.view_index AS SMALLINT) AS view_index,
    CAST(c.caption AS VARCHAR) AS caption,
    CAST(length(trim(coalesce(c.caption, ''))) AS BIGINT) AS caption_chars,
    CAST(c.caption_words AS BIGINT) AS caption_words,
    CAST(
        CASE
            WHEN trim(coalesce(c.caption, '')) = '' THEN 'empty'
            WHEN length(trim(c.caption)) < coalesce(CAST(getvariable('audit_min_caption_chars') AS INTEGER), 20)
                THEN 'too few characters'
            ELSE 'too few words'
        END AS VARCHAR
    ) AS problem,
    CAST(c.captioner_id AS VARCHAR) AS captioner_id,
    CAST(c.run_id AS VARCHAR) AS run_id
FROM captions AS c
JOIN mesh_names AS m ON m.mesh_id = c.mesh_id
WHERE
    trim(coalesce(c.caption, '')) = ''
    OR length(trim(c.caption)) < coalesce(CAST(getvariable('audit_min_caption_chars') AS INTEGER), 20)
    OR c.caption_words < coalesce(CAST(getvariable('audit_min_caption_words') AS INTEGER), 3)
ORDER BY caption_chars, mesh_id, view_index;
