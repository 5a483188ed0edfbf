-- Query path: the stage-2 view table (every active mesh's view embeddings), loaded once per Retriever.
-- One row per (active mesh, view) at the onboarding run's view-embedding fingerprint; when a view
-- was embedded by several runs (e.g. --force), the latest run wins. The dedupe works on the keys only
-- and the rows stay unsorted: carrying or sorting 2 KB vectors is what makes a cold open slow.
-- Parameters: $fingerprint (VARCHAR) the embed_image:view_encoder fingerprint of the latest successful run.
-- Inputs: query_meshes (active meshes with mesh_idx, from query_active_meshes.sql),
--         query_view_source (the image_embeddings dataset of the store's view encoder).
WITH latest AS (
    SELECT mesh_id, view_index, max(run_id) AS run_id
    FROM query_view_source
    WHERE fingerprint = $fingerprint
    GROUP BY mesh_id, view_index
)
SELECT
    CAST(m.mesh_idx AS INTEGER) AS mesh_idx,         -- index into query_meshes
    CAST(e.view_index AS SMALLINT) AS view_index,    -- rendered view number (0..K-1)
    e.embedding                                      -- FLOAT[dim], L2-normalised at onboarding
FROM query_view_source AS e
JOIN latest AS l ON l.mesh_id = e.mesh_id AND l.view_index = e.view_index AND l.run_id = e.run_id
JOIN query_meshes AS m ON m.mesh_id = e.mesh_id
WHERE e.fingerprint = $fingerprint;
