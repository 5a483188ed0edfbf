-- Query path: some rendered views of one model (the open-set verdict's patch agreement,
-- pipeline/query/patches.py), in one scan: the views of a model share a Parquet row group, whose image
-- column is read once (one query per view read it once per view). The equalities on the model and the
-- fingerprint reach the Arrow scan, which skips the row groups of other models: the views table is written
-- sorted by model in small row groups (pipeline.store.VIEW_ROW_GROUP_ROWS).
-- Parameters: $mesh_id (VARCHAR); $view_indices (SMALLINT[]); $render_fingerprint (VARCHAR).
-- Inputs: views_all (pipeline.db.connect).
SELECT
    CAST(view_index AS SMALLINT) AS view_index,
    image                                            -- PNG bytes
FROM views_all
WHERE fingerprint = $render_fingerprint AND mesh_id = $mesh_id AND list_contains($view_indices, view_index)
QUALIFY row_number() OVER (PARTITION BY view_index ORDER BY run_id DESC) = 1;
