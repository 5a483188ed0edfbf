-- Audit duplicate_captions: current captions whose text (case and spacing ignored) is shared by several
-- different meshes, so stage 1 cannot tell those meshes apart by caption. Returns one row per caption of
-- such a group; empty captions are left to short_captions.
--   SET VARIABLE audit_min_duplicate_meshes = 2;  -- distinct meshes that make a group offending
WITH normalised AS (
    SELECT
        c.*,
        lower(trim(regexp_replace(c.caption, '\s+', ' ', 'g'))) AS caption_key
    FROM captions AS c
    WHERE trim(coalesce(c.caption, '')) <> ''
),
groups AS (
    SELECT caption_key, count(DISTINCT mesh_id) AS n_meshes
    FROM normalised
    GROUP BY caption_key
    HAVING count(DISTINCT mesh_id) >= coalesce(CAST(getvariable('audit_min_duplicate_meshes') AS INTEGER), 2)
)
SELECT
    CAST(g.caption_key AS VARCHAR) AS caption_key,
    CAST(g.n_meshes AS BIGINT) AS n_meshes,
    CAST(n.mesh_id AS VARCHAR) AS mesh_id,
    CAST(m.name AS VARCHAR) AS name,
    CAST(n.view_index AS SMALLINT) AS view_index,
    CAST(n.caption AS VARCHAR) AS caption,
    CAST(n.run_id AS VARCHAR) AS run_id
FROM groups AS g
JOIN normalised AS n ON n.caption_key = g.caption_key
JOIN mesh_names AS m ON m.mesh_id = n.mesh_id
ORDER BY n_meshes DESC, caption_key, mesh_id, view_index;
