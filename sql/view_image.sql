-- Query path: one rendered view of one model (the open-set verdict's patch agreement,
-- pipeline/query/patches.py).
-- Parameters: $mesh_id (VARCHAR); $view_index (SMALLINT); $render_fingerprint (VARCHAR).
-- Inputs: views_all (pipeline.db.connect).
SELECT image                                         -- PNG bytes
FROM views_all
WHERE fingerprint = $render_fingerprint AND mesh_id = $mesh_id AND view_index = $view_index
ORDER BY run_id DESC
LIMIT 1;
