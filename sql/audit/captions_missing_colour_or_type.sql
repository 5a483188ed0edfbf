-- Audit captions_missing_colour_or_type: current captions that name no colour or no object type (the
-- words of the colour_words and object_type_words views, whole words, plurals allowed). Such a caption
-- cannot match a prompt like "the yellow mustard bottle" on what matters. Returns one row per offending
-- caption with what it lacks.
WITH checked AS (
    SELECT
        c.*,
        EXISTS (
            SELECT 1 FROM colour_words AS w
            WHERE regexp_matches(lower(coalesce(c.caption, '')), '\b' || w.word || '(s|es)?\b')
        ) AS has_colour,
        EXISTS (
            SELECT 1 FROM object_type_words AS w
            WHERE regexp_matches(lower(coalesce(c.caption, '')), '\b' || w.word || '(s|es)?\b')
        ) AS has_object_type
    FROM captions AS c
)
SELECT
    CAST(k.mesh_id AS VARCHAR) AS mesh_id,
    CAST(m.name AS VARCHAR) AS name,
    CAST(k.view_index AS SMALLINT) AS view_index,
    CAST(k.caption AS VARCHAR) AS caption,
    CAST(k.has_colour AS BOOLEAN) AS has_colour,
    CAST(k.has_object_type AS BOOLEAN) AS has_object_type,
    CAST(
        CASE
            WHEN NOT k.has_colour AND NOT k.has_object_type THEN 'no colour and no object type'
            WHEN NOT k.has_colour THEN 'no colour'
            ELSE 'no object type'
        END AS VARCHAR
    ) AS problem,
    CAST(k.run_id AS VARCHAR) AS run_id
FROM checked AS k
JOIN mesh_names AS m ON m.mesh_id = k.mesh_id
WHERE NOT k.has_colour OR NOT k.has_object_type
ORDER BY problem, mesh_id, view_index;
