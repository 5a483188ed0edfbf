-- Query path: the stage-1 search table, built once per store state and cached next to the store.
-- One row per (active mesh, caption) at the onboarding run's text-embedding fingerprint, latest run
-- winning when a caption was embedded twice. Rows are sorted by mesh so the scan groups cheaply.
-- Parameters: $fingerprint (VARCHAR) the embed_text fingerprint of the latest successful run.
-- Inputs: query_meshes (active meshes with mesh_idx, from query_active_meshes.sql),
--         query_caption_source (the text_embeddings dataset of the store's text encoder).
SELECT
    CAST(m.mesh_idx AS INTEGER) AS mesh_idx,         -- index into query_meshes
    CAST(e.view_index AS SMALLINT) AS view_index,    -- which view's caption
    e.embedding                                      -- FLOAT[dim], L2-normalised at onboarding
FROM query_caption_source AS e
JOIN query_meshes AS m ON m.mesh_id = e.mesh_id
WHERE e.fingerprint = $fingerprint
QUALIFY row_number() OVER (PARTITION BY e.mesh_id, e.view_index ORDER BY e.run_id DESC) = 1
ORDER BY mesh_idx, view_index;
