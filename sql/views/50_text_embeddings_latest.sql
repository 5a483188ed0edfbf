-- text_embeddings_latest: the latest row of every (mesh_id, view_index, fingerprint) of the text
-- embeddings of every encoder, any fingerprint, any mesh status. Vectors are variable-length FLOAT[] here
-- (encoders differ in width); text_embeddings__<encoder_slug> keeps one encoder's fixed FLOAT[dim].
CREATE OR REPLACE VIEW text_embeddings_latest AS
SELECT
    CAST(mesh_id AS VARCHAR) AS mesh_id,
    CAST(view_index AS SMALLINT) AS view_index,
    CAST(encoder_id AS VARCHAR) AS encoder_id,
    CAST(dim AS INTEGER) AS dim,
    CAST(embedding AS FLOAT[]) AS embedding,
    CAST(fingerprint AS VARCHAR) AS fingerprint,
    CAST(source_fingerprint AS VARCHAR) AS source_fingerprint,
    CAST(run_id AS VARCHAR) AS run_id
FROM text_embeddings_all
QUALIFY row_number() OVER (PARTITION BY mesh_id, view_index, fingerprint ORDER BY run_id DESC) = 1;

COMMENT ON VIEW text_embeddings_latest IS 'latest row per (mesh_id, view_index, fingerprint) of the text embeddings, all encoders';
COMMENT ON COLUMN text_embeddings_latest.mesh_id IS 'the embedded mesh';
COMMENT ON COLUMN text_embeddings_latest.view_index IS 'the view (or the caption of the view) that was embedded';
COMMENT ON COLUMN text_embeddings_latest.encoder_id IS 'encoder (backend:model)';
COMMENT ON COLUMN text_embeddings_latest.dim IS 'vector width';
COMMENT ON COLUMN text_embeddings_latest.embedding IS 'L2-normalised vector';
COMMENT ON COLUMN text_embeddings_latest.fingerprint IS 'embedding config fingerprint';
COMMENT ON COLUMN text_embeddings_latest.source_fingerprint IS 'fingerprint of the embedded caption row';
COMMENT ON COLUMN text_embeddings_latest.run_id IS 'run that wrote this row';
