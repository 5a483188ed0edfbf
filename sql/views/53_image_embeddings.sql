-- image_embeddings: the view embeddings the current config uses, one set per image encoder role
-- (view_encoder: DINOv2 or the offline descriptor; clip_image_encoder where the profile has it): latest
-- rows at the role's current fingerprint, of active meshes only.
CREATE OR REPLACE VIEW image_embeddings AS
SELECT
    CAST(split_part(f.stage, ':', 2) AS VARCHAR) AS role,
    CAST(e.mesh_id AS VARCHAR) AS mesh_id,
    CAST(e.view_index AS SMALLINT) AS view_index,
    CAST(e.encoder_id AS VARCHAR) AS encoder_id,
    CAST(e.dim AS INTEGER) AS dim,
    CAST(e.embedding AS FLOAT[]) AS embedding,
    CAST(e.fingerprint AS VARCHAR) AS fingerprint,
    CAST(e.source_fingerprint AS VARCHAR) AS source_fingerprint,
    CAST(e.run_id AS VARCHAR) AS run_id
FROM image_embeddings_latest AS e
JOIN current_fingerprints AS f ON f.stage LIKE 'embed_image:%' AND f.fingerprint = e.fingerprint
WHERE e.mesh_id IN (SELECT mesh_id FROM meshes);

COMMENT ON VIEW image_embeddings IS 'current view embeddings of active meshes, per image encoder role';
COMMENT ON COLUMN image_embeddings.role IS 'view_encoder | clip_image_encoder';
COMMENT ON COLUMN image_embeddings.mesh_id IS 'the embedded mesh';
COMMENT ON COLUMN image_embeddings.view_index IS 'the embedded view';
COMMENT ON COLUMN image_embeddings.encoder_id IS 'image encoder (backend:model)';
COMMENT ON COLUMN image_embeddings.dim IS 'vector width';
COMMENT ON COLUMN image_embeddings.embedding IS 'L2-normalised vector';
COMMENT ON COLUMN image_embeddings.fingerprint IS 'embed_image fingerprint of the role (the current one)';
COMMENT ON COLUMN image_embeddings.source_fingerprint IS 'fingerprint of the embedded view';
COMMENT ON COLUMN image_embeddings.run_id IS 'run that wrote this row';
