-- Query adapter (pipeline.adapter.table): the models it is fitted on, i.e. the active meshes that have
-- learned view embeddings at the run's fingerprint (the same rows sql/query_view_embeddings.sql joins,
-- without reading a vector). Parameters: $fingerprint (VARCHAR) the embed_image:learned_encoder fingerprint.
-- Inputs: query_meshes (active meshes with mesh_idx), query_view_source (the learned encoder's image_embeddings).
SELECT DISTINCT
    CAST(m.mesh_idx AS INTEGER) AS mesh_idx,
    CAST(m.mesh_id AS VARCHAR) AS mesh_id
FROM query_view_source AS e
JOIN query_meshes AS m ON m.mesh_id = e.mesh_id
WHERE e.fingerprint = $fingerprint
ORDER BY mesh_idx;
