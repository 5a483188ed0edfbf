-- text_embeddings: the caption embeddings the current config uses: latest rows at the current embed_text
-- fingerprint, of active meshes only.
CREATE OR REPLACE VIEW text_embeddings AS
SELECT
    CAST(e.mesh_id AS VARCHAR) AS mesh_id,
    CAST(e.view_index AS SMALLINT) AS view_index,
    CAST(e.encoder_id AS VARCHAR) AS encoder_id,
    CAST(e.dim AS INTEGER) AS dim,
    CAST(e.embedding AS FLOAT[]) AS embedding,
    CAST(e.fingerprint AS VARCHAR) AS fingerprint,
    CAST(e.source_fingerprint AS VARCHAR) AS source_fingerprint,
    CAST(e.run_id AS VARCHAR) AS run_id
FROM text_embeddings_latest AS e
JOIN current_fingerprints AS f ON f.stage = 'embed_text' AND f.fingerprint = e.fingerprint
WHERE e.mesh_id IN (SELECT mesh_id FROM meshes);

COMMENT ON VIEW text_embeddings IS 'current caption embeddings of active meshes';
COMMENT ON COLUMN text_embeddings.mesh_id IS 'the embedded mesh';
COMMENT ON COLUMN text_embeddings.view_index IS 'the view whose caption was embedded';
COMMENT ON COLUMN text_embeddings.encoder_id IS 'text encoder (backend:model)';
COMMENT ON COLUMN text_embeddings.dim IS 'vector width';
COMMENT ON COLUMN text_embeddings.embedding IS 'L2-normalised vector';
COMMENT ON COLUMN text_embeddings.fingerprint IS 'embed_text fingerprint (the current one)';
COMMENT ON COLUMN text_embeddings.source_fingerprint IS 'fingerprint of the embedded caption';
COMMENT ON COLUMN text_embeddings.run_id IS 'run that wrote this row';
