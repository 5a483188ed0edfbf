"""How good is the best view as a pose prior? ``python -m pipeline.evaluate pose_prior --store S --queries Q``.

On synthetic queries rendered at known cameras (:mod:`pipeline.evaluate.synth`), each answer's
``best_view_pose`` rotation is compared with the true object-to-camera rotation (the geodesic angle between
them). Per query it reports the error for the true model's best view (the prior a pose estimator gets once the
right model is picked) and whether retrieval put that model first. Objects are grouped by geometric symmetry
(:func:`symmetry_class`): for a body of revolution the angle about its axis cannot be told from shape, so
its error is also reported modulo that rotation.

The true camera: synth places it on the ray (azimuth, elevation) aimed at the object, rolled by
``roll_deg`` about its optical axis, then slides it sideways (which does not rotate it).
"""

from __future__ import annotations

import json
import math
from pathlib import Path

import numpy as np

from pipeline.mesh import frames
from pipeline.mesh.cameras import look_at_pose
from pipeline.query.errors import QueryError

#: a shape is a body of revolution about an axis when turning it 45 and 90 degrees about that axis moves
#: its vertices by less than this fraction of its width across the axis (scans are not exact: YCB's bowl,
#: plate and most cups move by 0.6-2.2 %, its dice, Rubik's cube and duplo bricks by 3.4 % or more)
RADIAL_TOL = 0.03
#: surface samples of the symmetry test (the turned ones are matched against these)
SURFACE_POINTS = 30000
THRESHOLD_DEG = 30.0


def true_camera_gl(azimuth_deg: float, elevation_deg: float, roll_deg: float) -> np.ndarray:
    """Camera-to-world pose (OpenGL, normalised frame, translation irrelevant) of a synth query."""
    az, el = math.radians(azimuth_deg), math.radians(elevation_deg)
    direction = np.array([math.cos(el) * math.cos(az), math.cos(el) * math.sin(az), math.sin(el)])
    pose = look_at_pose(direction, 3.0)
    r = math.radians(roll_deg)
    roll = np.array([[math.cos(r), -math.sin(r), 0.0], [math.sin(r), math.cos(r), 0.0], [0.0, 0.0, 1.0]])
    pose[:3, :3] = pose[:3, :3] @ roll
    return pose


def _axis_rotation(axis: np.ndarray, angle_deg: float) -> np.ndarray:
    a = np.asarray(axis, np.float64) / np.linalg.norm(axis)
    t = math.radians(angle_deg)
    k = np.array([[0, -a[2], a[1]], [a[2], 0, -a[0]], [-a[1], a[0], 0]])
    return np.eye(3) + math.sin(t) * k + (1 - math.cos(t)) * k @ k


def symmetry_class(mesh) -> tuple[str, np.ndarray | None]:
    """("radial", axis) for a body of revolution, ("spherical", None), or ("none", None), from the shape alone.

    Points are sampled uniformly over the surface (so their centroid lies on any symmetry axis, whatever
    the scan's vertex density); a principal axis through the centroid is a symmetry axis when turning the
    shape 45 and 90 degrees about it moves the points by less than ``RADIAL_TOL`` of the shape's width
    across that axis (mean distance to the nearest unturned point; the width, not the length, so that a
    knife turned about its blade is not taken for a rod). Texture is ignored: a soup can is radial here
    though its label fixes the angle.
    """
    import trimesh
    from scipy.spatial import cKDTree

    dense = np.asarray(trimesh.sample.sample_surface(mesh, SURFACE_POINTS, seed=0)[0], np.float64)
    centre = dense.mean(axis=0)
    p = dense - centre
    tree = cKDTree(p)
    sample = p[:: max(1, len(p) // 2000)]
    _, vecs = np.linalg.eigh(p.T @ p)
    moved = []
    for axis in vecs.T:
        width = 2.0 * float(np.linalg.norm(p - np.outer(p @ axis, axis), axis=1).max())
        turned = [tree.query(sample @ _axis_rotation(axis, a).T)[0].mean() for a in (45.0, 90.0)]
        moved.append(max(turned) / width)
    radial = [m < RADIAL_TOL for m in moved]
    if all(radial):
        return "spherical", None
    if any(radial):
        return "radial", vecs.T[int(np.argmin(moved))]
    return "none", None


def rotation_errors(r_est: np.ndarray, r_true: np.ndarray, sym: str, axis_src: np.ndarray | None) -> tuple:
    """(error, error modulo the shape's symmetry) in degrees between two object-to-camera rotations.

    ``axis_src``: the symmetry axis in the source frame (radial objects); spherical shapes have no
    shape-defined orientation (modulo error 0).
    """
    err = frames.rotation_angle_deg(r_est, r_true)
    if sym == "spherical":
        return err, 0.0
    if sym == "radial" and axis_src is not None:
        best = min(
            frames.rotation_angle_deg(r_est @ _axis_rotation(axis_src, a), r_true)
            for a in np.arange(0, 360, 1.0)
        )
        return err, best
    return err, err


def evaluate(retriever, queries: list, top: int = 5, progress: bool = False) -> list[dict]:
    """One row per query: the true model's best-view error (None when it is not in the top ``top``)."""
    import trimesh

    from pipeline.progress import iterate

    rows, shapes = [], {}
    for q in iterate(queries, "pose prior", unit="query", enabled=progress):
        expected = q.expected[0]
        try:
            mesh = retriever.mesh(expected)
        except QueryError:  # a query of a mesh this store does not hold
            continue
        if expected not in shapes:
            loaded = trimesh.load(str(Path(mesh["library_root"]) / mesh["source_path"]), process=False)
            geoms = loaded.dump() if isinstance(loaded, trimesh.Scene) else [loaded]
            shapes[expected] = symmetry_class(trimesh.util.concatenate(geoms))
        sym, axis = shapes[expected]
        result = retriever.query(q.image, q.prompt, mask=q.mask, top=top)
        names = [c.mesh_id for c in result.candidates]
        row = {
            "query_id": q.query_id,
            "name": mesh["name"],
            "symmetry": sym,
            "top1": names[:1] == [expected],
        }
        row.update(error_deg=None, error_sym_deg=None, best_view=None)
        if expected in names:
            cand = result.candidates[names.index(expected)]
            if cand.best_view_pose is not None:
                m = q.meta
                info = frames.scale_to_metres(cand.units_guess)
                norm = frames.normalisation(
                    mesh["bounds_min"], mesh["bounds_max"], mesh["scale_to_unit"], mesh["format"], "auto"
                )
                gl = true_camera_gl(m["azimuth_deg"], m["elevation_deg"], m["roll_deg"])
                r_true = frames.view_pose(gl, norm, info)[:3, :3]
                r_est = np.asarray(cand.best_view_pose)[:3, :3]
                err, err_sym = rotation_errors(r_est, r_true, sym, axis)
                row.update(error_deg=round(err, 2), error_sym_deg=round(err_sym, 2), best_view=cand.best_view)
        rows.append(row)
    return rows


def oracle_rows(retriever, queries: list) -> dict[str, float]:
    """Per query, the smallest error any stored view of the true model achieves (the layout's floor)."""
    out = {}
    for q in queries:
        expected = q.expected[0]
        try:
            mesh = retriever.mesh(expected)
        except QueryError:
            continue
        m = q.meta
        norm = frames.normalisation(
            mesh["bounds_min"], mesh["bounds_max"], mesh["scale_to_unit"], mesh["format"], "auto"
        )
        u = frames.scale_to_metres(mesh["units_guess"])
        r_true = frames.view_pose(
            true_camera_gl(m["azimuth_deg"], m["elevation_deg"], m["roll_deg"]), norm, u
        )
        errs = [
            frames.rotation_angle_deg(frames.view_pose(v["camera_pose"], norm, u)[:3, :3], r_true[:3, :3])
            for v in retriever.view_poses([expected])
        ]
        if errs:
            out[q.query_id] = min(errs)
    return out


def bootstrap_ci(values: np.ndarray, stat, n: int = 2000, seed: int = 0) -> tuple[float, float]:
    """95 % percentile-bootstrap interval of ``stat`` over ``values`` (queries resampled, seeded)."""
    rng = np.random.default_rng(seed)
    a = np.asarray(values, np.float64)
    draws = [stat(a[rng.integers(0, len(a), len(a))]) for _ in range(n)]
    return float(np.percentile(draws, 2.5)), float(np.percentile(draws, 97.5))


def table(rows: list[dict], oracle: dict[str, float]) -> str:
    """Markdown table: per symmetry class and overall, median error and the share within 30 degrees, with
    95 % bootstrap intervals in brackets."""
    lines = [
        "| subset | queries | true model in top 5 | median error (deg) | within 30 deg | median mod symmetry "
        "| within 30 deg mod sym | median best possible view |",
        "|---|---|---|---|---|---|---|---|",
    ]
    groups = [("all", rows), ("top-1 correct", [r for r in rows if r["top1"]])]
    groups += [
        (f"symmetry: {s}", [r for r in rows if r["symmetry"] == s]) for s in ("none", "radial", "spherical")
    ]
    for label, rs in groups:
        if not rs:
            continue
        found = [r for r in rs if r["error_deg"] is not None]
        e = np.array([r["error_deg"] for r in found])
        es = np.array([r["error_sym_deg"] for r in found])
        orc = np.array([oracle[r["query_id"]] for r in rs if r["query_id"] in oracle])

        def med(a):
            if not len(a):
                return "-"
            lo, hi = bootstrap_ci(a, np.median)
            return f"{np.median(a):.1f} [{lo:.1f}, {hi:.1f}]"

        def share(a):
            if not len(a):
                return "-"
            lo, hi = bootstrap_ci(a, lambda x: 100 * (x <= THRESHOLD_DEG).mean())
            n = int((a <= THRESHOLD_DEG).sum())
            return f"{n}/{len(a)} ({100 * n / len(a):.0f}% [{lo:.0f}, {hi:.0f}])"

        lines.append(
            f"| {label} | {len(rs)} | {len(found)} | {med(e)} | {share(e)} | {med(es)} | {share(es)} | {med(orc)} |"
        )
    return "\n".join(lines)


def main(argv: list[str] | None = None) -> int:
    from pipeline.cli_common import OneLineParser, fail, positive_int

    p = OneLineParser(
        prog="python -m pipeline.evaluate pose_prior",
        description="Rotation error of the best view's pose prior on synthetic queries at known cameras.",
    )
    p.add_argument("--store", required=True, help="store the queries were generated from")
    p.add_argument("--queries", required=True, help="queries.jsonl written by pipeline.evaluate synth")
    p.add_argument("--top", type=positive_int, default=5, help="candidates per answer (default 5)")
    p.add_argument("--limit", type=positive_int, help="only the first N queries")
    p.add_argument("--out", help="write the per-query rows as JSONL here")
    p.add_argument("--rows", help="tabulate the rows an earlier run wrote with --out (no queries are run)")
    p.add_argument("--no-progress", action="store_true")
    args = p.parse_args(argv)
    from pipeline.evaluate.datasets import load_queries
    from pipeline.evaluate.records import QueryFileError
    from pipeline.query import Retriever

    try:
        queries = load_queries(args.queries)[: args.limit]
    except QueryFileError as exc:
        return fail(str(exc))
    if not queries or "roll_deg" not in queries[0].meta:
        return fail(f"{args.queries} has no synthetic queries with camera metadata (pipeline.evaluate.synth)")
    try:
        with Retriever.open(args.store, profile="auto", preload=args.rows is None) as r:
            if args.rows:
                rows = [json.loads(x) for x in Path(args.rows).read_text().splitlines() if x.strip()]
            else:
                rows = evaluate(r, queries, args.top, progress=not args.no_progress)
            oracle = oracle_rows(r, queries)
    except (QueryError, OSError, ValueError) as exc:
        return fail(str(exc))
    if args.out and not args.rows:
        Path(args.out).write_text("".join(json.dumps(x) + "\n" for x in rows))
    print(table(rows, oracle))
    return 0
