-- Query path: the models a query can return.
-- A mesh is active when the latest meshes row of one of its (library_root, source_path) is 'active';
-- a mesh_id reachable by several paths is listed once, with its first active path (by root, then path)
-- for display and export. mesh_idx numbers the meshes 0..n-1 in mesh_id order: stage 1 and stage 2
-- address meshes by it.
-- Inputs: meshes_all (pipeline.db.connect). No parameters.
WITH latest AS (
    SELECT
        *,
        row_number() OVER (
            PARTITION BY library_root, source_path, mesh_id ORDER BY run_id DESC, seen_at DESC
        ) AS rn
    FROM meshes_all
),
active AS (
    SELECT * FROM latest WHERE rn = 1 AND status = 'active'
),
one_path AS (
    SELECT
        *,
        row_number() OVER (PARTITION BY mesh_id ORDER BY library_root, source_path) AS path_rank,
        count(*) OVER (PARTITION BY mesh_id) AS n_paths
    FROM active
)
SELECT
    CAST(row_number() OVER (ORDER BY mesh_id) - 1 AS INTEGER) AS mesh_idx,  -- dense 0-based index
    CAST(mesh_id AS VARCHAR) AS mesh_id,                                   -- content hash of the files
    CAST(coalesce(name, source_path) AS VARCHAR) AS name,                  -- display name
    CAST(source_path AS VARCHAR) AS source_path,                           -- relative to library_root
    CAST(library_root AS VARCHAR) AS library_root,
    CAST(format AS VARCHAR) AS format,
    deps,                                                                  -- referenced files (export)
    bounds_min,                                                            -- file units (hand-off)
    bounds_max,
    CAST(units_guess AS VARCHAR) AS units_guess,                           -- 'm' | 'mm' (loader's guess)
    CAST(scale_to_unit AS DOUBLE) AS scale_to_unit,                        -- to the unit sphere (render)
    CAST(n_paths AS INTEGER) AS n_paths                                    -- paths sharing this content
FROM one_path
WHERE path_rank = 1
ORDER BY mesh_id;
