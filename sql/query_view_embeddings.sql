-- Query path: the stage-2 view table (every active mesh's view embeddings), loaded once per Retriever.
-- Latest run wins when a view was embedded twice.
-- Parameters: $fingerprint (VARCHAR) the embed_image:view_encoder fingerprint of the latest successful run.
-- Inputs: query_meshes (active meshes with mesh_idx), query_view_source (the image_embeddings dataset of
--         the store's view encoder).
SELECT
    CAST(m.mesh_idx AS INTEGER) AS mesh_idx,         -- index into query_meshes
    CAST(e.view_index AS SMALLINT) AS view_index,    -- rendered view number (0..K-1)
    e.embedding                                      -- FLOAT[dim], L2-normalised at onboarding
FROM query_view_source AS e
JOIN query_meshes AS m ON m.mesh_id = e.mesh_id
WHERE e.fingerprint = $fingerprint
QUALIFY row_number() OVER (PARTITION BY e.mesh_id, e.view_index ORDER BY e.run_id DESC) = 1
ORDER BY mesh_idx, view_index;
