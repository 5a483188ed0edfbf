-- Query stage 1, the selection (OSCAR): from each model's score (the max over its captions of the cosine,
-- computed by BLAS in pipeline/query/stage1.py) keep the models scoring at least tau; when none does, fall
-- back to the top fallback_k counted in captions (the paper and reference scripts: the fallback_k best
-- caption rows, kept as their distinct models) or in models (the fallback_k best models).
-- The same semantics as stage1_text_filter.sql (which also computes the inner products, in SQL: the
-- reference the tests compare with); ties are broken by mesh_idx (= mesh_id order).
-- Parameters: $threshold (DOUBLE) tau, or NULL to skip the threshold (always the top fallback_k);
--             $fallback_k (BIGINT) how many captions / models to keep when none passes tau;
--             $fallback_unit (VARCHAR) 'captions' or 'meshes': what fallback_k counts.
-- The top fallback_k captions (by score, then mesh_idx) all belong to the top fallback_k models (by best
-- caption, then mesh_idx), so the caption unit only looks at the captions of those models.
-- Inputs: stage1_mesh_scores(mesh_idx INTEGER, score FLOAT), one row per model with captions;
--         stage1_caption_scores(mesh_idx INTEGER, score FLOAT), one row per caption
--         (both registered per query by pipeline.query.stage1).
WITH passed AS (
    SELECT mesh_idx, score FROM stage1_mesh_scores WHERE score >= CAST($threshold AS FLOAT)  -- in float32
),
fallback_meshes AS (
    SELECT mesh_idx, score
    FROM stage1_mesh_scores
    WHERE NOT EXISTS (SELECT 1 FROM passed)
    ORDER BY score DESC, mesh_idx
    LIMIT $fallback_k
),
top_captions AS (
    SELECT mesh_idx, score
    FROM stage1_caption_scores
    WHERE CAST($fallback_unit AS VARCHAR) = 'captions'
      AND mesh_idx IN (SELECT mesh_idx FROM fallback_meshes)
    ORDER BY score DESC, mesh_idx
    LIMIT $fallback_k
),
fallback AS (
    SELECT mesh_idx, score
    FROM fallback_meshes
    WHERE CAST($fallback_unit AS VARCHAR) = 'meshes' OR mesh_idx IN (SELECT mesh_idx FROM top_captions)
)
SELECT
    CAST(mesh_idx AS INTEGER) AS mesh_idx,  -- index into the query's mesh list
    CAST(score AS FLOAT) AS score,          -- max over the model's captions of the cosine
    FALSE AS used_fallback                  -- passed tau
FROM passed
UNION ALL
SELECT
    CAST(mesh_idx AS INTEGER) AS mesh_idx,
    CAST(score AS FLOAT) AS score,
    TRUE AS used_fallback                   -- kept by the fallback (top fallback_k captions / models)
FROM fallback
ORDER BY score DESC, mesh_idx;
