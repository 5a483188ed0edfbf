-- Query stage 1, the text filter (OSCAR): score every model by its best-matching caption and keep the
-- models scoring at least tau; when none does, fall back to the top fallback_k counted in captions
-- (the paper and reference scripts: the fallback_k best caption rows, kept as their distinct models) or
-- in models (the fallback_k best models).
-- Embeddings are L2-normalised at onboarding, so the inner product is the cosine similarity. Each vector
-- is stored as 8 equal slices (e0..e7) and the inner product is the sum of the 8 slice products: the same
-- number up to float rounding, about a third less CPU than one long product (pipeline/query/stage1.py).
-- Ties are broken by mesh_idx (= mesh_id order), so results are deterministic.
-- Parameters: $q0 .. $q7 (FLOAT[]) the query vector in caption-embedding space, cut like the rows;
--             $threshold (DOUBLE) tau, or NULL to skip the threshold (always the top fallback_k);
--             $fallback_k (BIGINT) how many captions / models to keep when none passes tau;
--             $fallback_unit (VARCHAR) 'captions' or 'meshes': what fallback_k counts.
-- The top fallback_k captions (by score, then mesh_idx) all belong to the top fallback_k models (by best
-- caption, then mesh_idx), so the caption unit only re-scores the captions of those models.
-- Inputs: stage1_captions(mesh_idx INTEGER, e0 .. e7 FLOAT[dim/8]), one row per caption
--         (registered by pipeline.query.stage1; built by query_caption_embeddings.sql).
WITH scores AS MATERIALIZED (
    SELECT
        mesh_idx,
        max(
            list_dot_product(e0, CAST($q0 AS FLOAT[])) + list_dot_product(e1, CAST($q1 AS FLOAT[]))
            + list_dot_product(e2, CAST($q2 AS FLOAT[])) + list_dot_product(e3, CAST($q3 AS FLOAT[]))
            + list_dot_product(e4, CAST($q4 AS FLOAT[])) + list_dot_product(e5, CAST($q5 AS FLOAT[]))
            + list_dot_product(e6, CAST($q6 AS FLOAT[])) + list_dot_product(e7, CAST($q7 AS FLOAT[]))
        ) AS score
    FROM stage1_captions
    GROUP BY mesh_idx
),
passed AS (
    SELECT mesh_idx, score FROM scores WHERE score >= CAST($threshold AS FLOAT)  -- compared in float32
),
fallback_meshes AS (
    SELECT mesh_idx, score
    FROM scores
    WHERE NOT EXISTS (SELECT 1 FROM passed)
    ORDER BY score DESC, mesh_idx
    LIMIT $fallback_k
),
top_captions AS (
    SELECT
        mesh_idx,
        list_dot_product(e0, CAST($q0 AS FLOAT[])) + list_dot_product(e1, CAST($q1 AS FLOAT[]))
        + list_dot_product(e2, CAST($q2 AS FLOAT[])) + list_dot_product(e3, CAST($q3 AS FLOAT[]))
        + list_dot_product(e4, CAST($q4 AS FLOAT[])) + list_dot_product(e5, CAST($q5 AS FLOAT[]))
        + list_dot_product(e6, CAST($q6 AS FLOAT[])) + list_dot_product(e7, CAST($q7 AS FLOAT[])) AS score
    FROM stage1_captions
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
