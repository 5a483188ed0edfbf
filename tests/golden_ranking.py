"""Golden rankings: every ranking knob of the query path on a store and a query set, as canonical JSON.

Records, per query: the Python API's full ``Retriever.query`` JSON (timings dropped) and, for the ``segm``
(mask) and ``bbox`` (box) ROI of the query, ``Retriever.rank`` over a grid of every mode, fallback unit,
threshold (default, one nothing passes, one everything passes), fallback k, verification (settings, off, on)
and prompt weight, with the view-level ranking; plus the evaluation engine's plain ``Ranked`` records. Floats
are written with ``repr`` (exact), paths of the machine are replaced by tokens, so two full captures on
the same store compare equal only when every ranking, score and JSON field is identical.

What a test keeps (:func:`summary`) must also hold on another CPU, where the same code and store give
floats that differ in the sixth decimal (float32 matrix products summed in another order: seen between an
Intel Xeon with AMX, where the records were made, and an AMD EPYC, 2026-12-06). So each record is kept
as a :func:`fingerprint`: the exact digest of everything but its floats (every id, order, count, string,
field and the place of every float), plus the sums of its floats in chunks of :data:`CHUNK`, compared
with :data:`VALUE_TOL` per float (:func:`mismatches`). A changed ranking, field or count changes the
digest; a score moved by more than ``CHUNK * VALUE_TOL`` moves its chunk's sum past the tolerance.

As a tool (the before/after check of a ranking refactor)::

    python tests/golden_ranking.py --store STORE --queries Q.jsonl --out golden.json [--compare OLD.json]
"""

from __future__ import annotations

import argparse
import hashlib
import json
import sys
from pathlib import Path

import numpy as np

REPO = Path(__file__).resolve().parents[1]

#: the rank() grid per embedding (keyword arguments); ``views=True`` and a full-length ``top`` are added
THRESHOLDS = (None, 1.5, -1.0)  # default tau, nothing passes (fallback), everything passes
FALLBACK_KS = (1, 10)
VERIFY = (None, False, True)
PROMPT_WEIGHTS = (0.0, 1.0)  # on top of the default (None), at the default tau / k / verification
FULL = 1_000_000
#: floats per summed chunk of a fingerprint, and the drift allowed per float (cross-CPU drift: about 3e-6)
CHUNK = 64
VALUE_TOL = 1e-5
#: per-candidate fields of the pose-estimator hand-off (the ``handoff`` step), left out of the records
HANDOFF_FIELDS = ("units_guess", "units_from", "scale_to_metres", "extent_m", "best_view_pose", "intrinsics")


def grid(modes, units) -> list[dict]:
    """Every rank() setting the golden record covers."""
    out = []
    for mode in modes:
        for unit in units:
            for tau in THRESHOLDS:
                for k in FALLBACK_KS:
                    for verify in VERIFY:
                        out.append(
                            {
                                "mode": mode,
                                "fallback_unit": unit,
                                "threshold": tau,
                                "fallback_k": k,
                                "verify": verify,
                            }
                        )
            for w in PROMPT_WEIGHTS:
                out.append({"mode": mode, "fallback_unit": unit, "prompt_weight": w})
    return out


def scrub(obj, tokens: dict[str, str]):
    """``obj`` with machine paths (keys of ``tokens``) replaced by their tokens, numpy turned into lists."""
    if isinstance(obj, dict):
        return {k: scrub(v, tokens) for k, v in obj.items()}
    if isinstance(obj, (list, tuple)):
        return [scrub(v, tokens) for v in obj]
    if isinstance(obj, np.ndarray):
        return scrub(obj.tolist(), tokens)
    if isinstance(obj, np.generic):
        return obj.item()
    if isinstance(obj, str):
        for path, token in tokens.items():
            obj = obj.replace(path, token)
        return obj
    return obj


def result_record(res) -> dict:
    """A QueryResult without timings, plus its view-level ranking (exact arrays)."""
    d = res.to_dict()
    d.pop("timings_ms", None)
    for key in ("accepted", "confidence", "accept_threshold", "acceptance"):  # the open-set verdict: a
        d.pop(key, None)  # calibrated layer on top of the ranking (tests/test_openset.py), not the ranking
    for c in d.get("candidates", []):  # the pose-estimator hand-off: per-candidate facts about the mesh
        for key in HANDOFF_FIELDS:  # (tests/test_handoff.py), not the ranking
            c.pop(key, None)
    d["timing_keys"] = sorted(res.timings)
    vr = res.view_ranking
    if vr is not None:
        d["view_ranking"] = {
            "mesh_idx": np.asarray(vr.mesh_idx).tolist(),
            "view_index": np.asarray(vr.view_index).tolist(),
            "scores": [float(x) for x in np.asarray(vr.scores)],
            "tiebreak": None if vr.tiebreak is None else [float(x) for x in np.asarray(vr.tiebreak)],
        }
    return d


def ranked_record(r) -> dict:
    """The evaluation engine's Ranked record without its timing."""
    d = {k: v for k, v in vars(r).items() if k != "seconds"}
    return {k: (np.asarray(v).tolist() if isinstance(v, np.ndarray) else v) for k, v in d.items()}


def capture(retriever, queries, tokens: dict[str, str], light: bool = False) -> dict:
    """Golden records of ``queries`` (pipeline.evaluate Query objects) on an open ``retriever``; ``light``:
    the ``segm`` ROI's rows that :func:`is_light` keeps only (the suite's check on a large store)."""
    from pipeline.evaluate.engine import Engine, Setting
    from pipeline.query.modes import MODES
    from pipeline.query.stage1 import FALLBACK_UNITS

    engine = Engine(retriever, str(retriever.store.root))
    out: dict = {}
    for q in queries:
        box = tuple(q.box) if q.box else None
        rec: dict = {"query": result_record(retriever.query(q.image, q.prompt, box=box, mask=q.mask))}
        for roi in ("segm",) if light else ("segm", "bbox"):
            if roi == "segm" and not q.mask:
                continue
            emb = engine.embed(q, roi)
            rows = []
            for kw in grid(MODES, FALLBACK_UNITS):
                if not light or is_light({"args": kw}):
                    res = retriever.rank(emb.embedding, top=FULL, views=True, **kw)
                    rows.append({"args": kw, "result": result_record(res)})
            for mode in MODES:
                for unit in FALLBACK_UNITS:
                    for tau in THRESHOLDS:
                        s = Setting(mode=mode, threshold=tau, fallback_k=3, roi=roi, fallback_unit=unit)
                        if not light or is_light({"engine": s.to_json()}):
                            rows.append(
                                {"engine": s.to_json(), "ranked": ranked_record(engine.rank(emb, s, True))}
                            )
            rec[roi] = rows
        out[q.query_id] = rec
    return scrub(out, tokens)


def is_light(row: dict) -> bool:
    """The rows of the light grid: default verification and fallback k, every mode, unit and threshold."""
    if "engine" in row:
        return row["engine"]["threshold"] is None
    a = row["args"]
    return "prompt_weight" in a or (a["verify"] is None and a["fallback_k"] == 10)


def digest(obj) -> str:
    return hashlib.sha256(json.dumps(obj, sort_keys=True).encode()).hexdigest()


def split_floats(obj, out: list[float] | None = None):
    """``obj`` with every finite float replaced by a placeholder, and those floats in order."""
    out = [] if out is None else out
    if isinstance(obj, dict):
        return {k: split_floats(obj[k], out)[0] for k in sorted(obj, key=str)}, out
    if isinstance(obj, (list, tuple)):
        return [split_floats(v, out)[0] for v in obj], out
    if isinstance(obj, float):
        if obj != obj or obj in (float("inf"), float("-inf")):
            return repr(obj), out  # NaN and infinities are part of the skeleton, exactly
        out.append(obj)
        return "<float>", out
    return obj, out


def fingerprint(obj) -> dict:
    """The exact digest of ``obj`` without its floats, and its floats' sums in chunks of :data:`CHUNK`."""
    skeleton, xs = split_floats(obj)
    a = np.asarray(xs, np.float64)
    sums = [round(float(a[i : i + CHUNK].sum()), 6) for i in range(0, len(a), CHUNK)]
    return {"digest": digest(skeleton), "floats": len(xs), "sums": sums}


def summary(golden: dict, light: bool = False) -> dict:
    """What a test file keeps: per query a :func:`fingerprint` of its query JSON and one per ROI of every
    ranking row (``light``: of the light grid's rows only), plus the readable default ranking."""
    out = {}
    for qid, rec in golden.items():
        cands = rec["query"]["candidates"]
        out[qid] = {
            "query": fingerprint(rec["query"]),
            "best": [c["mesh_id"] for c in cands],
            "scores": [c["score"] if c["score"] is not None else c["image_score"] for c in cands],
        }
        for roi in ("segm",) if light else ("segm", "bbox"):
            if roi in rec:
                out[qid][roi] = fingerprint([r for r in rec[roi] if not light or is_light(r)])
    return out


def mismatches(old: dict, new: dict) -> list[str]:
    """Where two summaries of one query differ beyond the cross-CPU drift (empty: they agree)."""
    bad = [f"/{k}: only in {'new' if k in new else 'old'}" for k in sorted(set(old) ^ set(new))]
    for k in sorted(set(old) & set(new)):
        a, b = old[k], new[k]
        if k == "scores":
            if len(a) != len(b) or any(abs(x - y) > VALUE_TOL for x, y in zip(a, b, strict=False)):
                bad.append(f"/scores: {a} != {b}")
        elif isinstance(a, dict) and "sums" in a:
            if a["digest"] != b.get("digest") or a["floats"] != b.get("floats"):
                bad.append(
                    f"/{k}: ranking, field or count changed (digest {a['digest'][:12]} != {b.get('digest', '')[:12]})"
                )
                continue
            tol = CHUNK * VALUE_TOL
            moved = [i for i, (x, y) in enumerate(zip(a["sums"], b["sums"], strict=True)) if abs(x - y) > tol]
            if moved:
                i = moved[0]
                bad.append(
                    f"/{k}: floats moved in {len(moved)} chunk(s), first #{i}: {a['sums'][i]} != {b['sums'][i]}"
                )
        elif a != b:
            bad.append(f"/{k}: {str(a)[:120]} != {str(b)[:120]}")
    return bad


def differences(old: dict, new: dict, limit: int = 20) -> list[str]:
    """Human-readable first differences between two captures."""
    diffs: list[str] = []

    def walk(a, b, where):
        if len(diffs) >= limit:
            return
        if isinstance(a, dict) and isinstance(b, dict):
            for k in sorted(set(a) | set(b), key=str):
                if k not in a or k not in b:
                    diffs.append(f"{where}/{k}: only in {'new' if k in b else 'old'}")
                else:
                    walk(a[k], b[k], f"{where}/{k}")
        elif isinstance(a, list) and isinstance(b, list) and len(a) == len(b):
            for i, (x, y) in enumerate(zip(a, b, strict=True)):
                walk(x, y, f"{where}[{i}]")
        elif a != b and not (a != a and b != b):  # NaN equals NaN here
            diffs.append(f"{where}: {str(a)[:120]} != {str(b)[:120]}")

    walk(old, new, "")
    return diffs


def machine_tokens(store: Path, queries: Path) -> dict[str, str]:
    import os

    tokens = {
        str(store.resolve()): "<store>",
        str(queries.resolve().parent): "<queries>",
        str(REPO): "<repo>",
    }
    shared = os.environ.get("OSCAR_SHARED_DATA")
    if shared:
        tokens[str(Path(shared).resolve())] = "<shared>"
    # The store records where its library was onboarded from (candidates' ``library_root``): a store built
    # from /work/shared/data/ycb and read where shared/ lies elsewhere (CI's clone) must capture the same.
    # A root inside the checkout (the sample library) is already covered by <repo>.
    from pipeline.evaluate.library import read_store_meshes

    roots = sorted({m.library_root for m in read_store_meshes(str(store))} - {""})
    outside = [r for r in roots if not Path(r).resolve().is_relative_to(REPO)]
    for i, root in enumerate(outside):
        tokens[root] = "<library>" if len(outside) == 1 else f"<library{i}>"
    return dict(sorted(tokens.items(), key=lambda kv: -len(kv[0])))  # longest first


def main(argv: list[str]) -> int:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--store", required=True)
    p.add_argument("--queries", required=True, help="a query set (JSONL/CSV, pipeline.evaluate format)")
    p.add_argument("--out", required=True, help="write the full capture here (JSON)")
    p.add_argument("--compare", help="a previous capture: exit 1 when anything differs")
    p.add_argument("--limit", type=int, help="first N queries only")
    p.add_argument("--summary", help="also write the digests a test keeps (tests/golden/*.json) here")
    p.add_argument("--light", action="store_true", help="the summary of the light grid only")
    args = p.parse_args(argv)
    from pipeline.evaluate.datasets import load_queries
    from pipeline.query import Retriever

    queries = load_queries(args.queries)[: args.limit]
    with Retriever.open(args.store, profile="auto") as r:
        golden = capture(r, queries, machine_tokens(Path(args.store), Path(args.queries)))
    Path(args.out).write_text(json.dumps(golden, sort_keys=True))
    if args.summary:
        Path(args.summary).write_text(
            json.dumps(summary(golden, args.light), indent=1, sort_keys=True) + "\n"
        )
    n = sum(len(v.get("segm", [])) + len(v.get("bbox", [])) + 1 for v in golden.values())
    print(f"{len(golden)} queries, {n} rankings -> {args.out} (digest {digest(golden)[:16]})")
    if args.compare:
        old = json.loads(Path(args.compare).read_text())
        diffs = differences(old, golden)
        if diffs:
            print("DIFFERENT:\n  " + "\n  ".join(diffs))
            return 1
        print(f"identical to {args.compare}")
    return 0


if __name__ == "__main__":
    sys.path.insert(0, str(REPO))
    raise SystemExit(main(sys.argv[1:]))
