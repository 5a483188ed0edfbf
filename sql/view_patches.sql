-- Query path: the stored object patch tokens of some views of one model (the open-set verdict's patch
-- agreement, pipeline/query/patches.py), in one scan. Like view_images.sql, the equalities on the model and
-- the fingerprint reach the Arrow scan, which skips other models' row groups (view_patches is written sorted
-- by model in small row groups, pipeline.store.BLOB_TABLES).
-- Parameters: $mesh_id (VARCHAR); $view_indices (SMALLINT[]); $patches_fingerprint (VARCHAR).
-- Inputs: view_patches_all (pipeline.db.connect).
SELECT
    CAST(view_index AS SMALLINT) AS view_index,
    n_patches,
    dim,
    tokens                                           -- n_patches x dim float16, little-endian
FROM view_patches_all
WHERE fingerprint = $patches_fingerprint AND mesh_id = $mesh_id AND list_contains($view_indices, view_index)
QUALIFY row_number() OVER (PARTITION BY view_index ORDER BY run_id DESC) = 1;
