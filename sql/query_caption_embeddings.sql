-- Query path: the stage-1 search table, built once per store state and cached next to the store.
-- One row per (active mesh, caption) at the onboarding run's text-embedding fingerprint; when a caption
-- was embedded by several runs (e.g. --force), the latest run wins. The dedupe works on the keys only
-- and the rows stay unsorted: carrying or sorting 2 KB vectors is what makes a cold open slow.
-- Parameters: $fingerprint (VARCHAR) the embed_text fingerprint of the latest successful run.
-- Inputs: query_meshes (active meshes with mesh_idx, from query_active_meshes.sql),
--         query_caption_source (the text_embeddings dataset of the store's text encoder).
WITH latest AS (
    SELECT mesh_id, view_index, max(run_id) AS run_id
    FROM query_caption_source
    WHERE fingerprint = $fingerprint
    GROUP BY mesh_id, view_index
)
SELECT
    CAST(m.mesh_idx AS INTEGER) AS mesh_idx,         -- index into query_meshes
    CAST(e.view_index AS SMALLINT) AS view_index,    -- which view's caption
    e.embedding                                      -- FLOAT[dim], L2-normalised at onboarding
FROM query_caption_source AS e
JOIN latest AS l ON l.mesh_id = e.mesh_id AND l.view_index = e.view_index AND l.run_id = e.run_id
JOIN query_meshes AS m ON m.mesh_id = e.mesh_id
WHERE e.fingerprint = $fingerprint;
