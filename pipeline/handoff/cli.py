"""``python -m pipeline.handoff --store STORE --answers ANSWERS.jsonl --out DIR``: a batch of answers
(``pipeline.query --queries ... --output ANSWERS.jsonl``) to a BOP-style folder for a pose estimator.

``DIR/models/obj_NNNNNN.ply`` (mm) + ``models/models_info.json`` (the BOP toolkit's), ``DIR/objects.json``
(obj_id -> mesh id, name, source path, units and how they were decided, size in metres) and
``DIR/priors.json`` (per query: the photo, its ROI box, and one hypothesis per kept candidate, in BOP's
``cam_R_m2c`` / ``cam_t_m2c`` convention). See docs/handoff.md.
"""

from __future__ import annotations

import json
import sys
from pathlib import Path

import numpy as np

from pipeline.cli_common import OneLineParser, fail, positive_int


def build_parser():
    p = OneLineParser(
        prog="python -m pipeline.handoff",
        description="Turn a batch of answers into BOP models (mm) plus per-query pose priors.",
    )
    p.add_argument("--store", required=True, help="the store the answers came from")
    p.add_argument("--answers", required=True, metavar="ANSWERS.jsonl", help="pipeline.query --output file")
    p.add_argument("--out", required=True, metavar="DIR", help="output folder (created)")
    p.add_argument(
        "--hypotheses",
        type=positive_int,
        default=1,
        metavar="N",
        help="candidates kept per query (default 1)",
    )
    p.add_argument(
        "--camera-k",
        metavar="FX,FY,CX,CY",
        help="the photos' intrinsics: place each hypothesis at the depth its ROI box implies (else: the view's)",
    )
    return p


def parse_k(text: str | None) -> np.ndarray | None:
    if text is None:
        return None
    try:
        fx, fy, cx, cy = (float(v) for v in text.split(","))
    except ValueError:
        raise ValueError(f"--camera-k wants FX,FY,CX,CY (4 numbers), got {text!r}") from None
    if fx <= 0 or fy <= 0:
        raise ValueError(f"--camera-k focal lengths must be positive, got {text!r}")
    return np.array([[fx, 0.0, cx], [0.0, fy, cy], [0.0, 0.0, 1.0]])


def read_answers(path: Path) -> tuple[list[dict], list[dict]]:
    """(answers with candidates, skipped lines with why)."""
    try:
        lines = path.read_text(encoding="utf-8").splitlines()
    except OSError as exc:
        raise ValueError(f"cannot read {path}: {exc.strerror or exc}") from None
    answers, skipped = [], []
    for n, line in enumerate(lines, start=1):
        if not line.strip():
            continue
        try:
            a = json.loads(line)
        except json.JSONDecodeError as exc:
            skipped.append({"line": n, "reason": f"not JSON: {exc.msg}"})
            continue
        if not isinstance(a, dict) or "error" in a or not a.get("candidates"):
            why = a.get("error", "no candidates") if isinstance(a, dict) else "not an object"
            skipped.append({"line": n, "id": a.get("id") if isinstance(a, dict) else None, "reason": why})
            continue
        answers.append(a)
    return answers, skipped


def main(argv: list[str] | None = None) -> int:
    args = build_parser().parse_args(argv)
    from pipeline.query.errors import QueryError
    from pipeline.store import StoreError

    try:
        k = parse_k(args.camera_k)
        answers, skipped = read_answers(Path(args.answers))
        if not answers:
            return fail(f"{args.answers} has no answer with candidates ({len(skipped)} lines skipped)")
        return _run(args, k, answers, skipped)
    except (QueryError, StoreError, ValueError) as exc:
        return fail(str(exc))


def _run(args, k, answers: list[dict], skipped: list[dict]) -> int:
    from pipeline.handoff.priors import hypothesis
    from pipeline.query.api import Retriever
    from pipeline.query.export import write_bop_models
    from pipeline.query.handoff import metric_info

    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    obj_ids: dict[str, int] = {}
    for a in answers:
        for c in a["candidates"][: args.hypotheses]:
            obj_ids.setdefault(c["mesh_id"], len(obj_ids) + 1)
    with Retriever.open(args.store, profile="auto", preload=False) as r:
        meshes = {m: r.mesh(m) for m in obj_ids}
    write_bop_models([(obj_ids[m], rec) for m, rec in meshes.items()], out)
    objects = {}
    for m, rec in meshes.items():
        objects[str(obj_ids[m])] = {
            "mesh_id": m,
            "name": rec.get("name"),
            "library_root": rec.get("library_root"),
            "source_path": rec.get("source_path"),
            **metric_info(rec),
        }
    priors, n_hyp = [], 0
    for a in answers:
        q = a.get("query") or {}
        box = (q.get("roi") or {}).get("box")
        hyps = []
        for c in a["candidates"][: args.hypotheses]:
            if c.get("best_view_pose") is None:
                continue
            rec = meshes[c["mesh_id"]]
            centre_m = (
                (np.asarray(rec["bounds_min"]) + np.asarray(rec["bounds_max"])) / 2.0 * c["scale_to_metres"]
            )
            h = hypothesis(c, centre_m, box if k is not None else None, k)
            hyps.append(
                {
                    "obj_id": obj_ids[c["mesh_id"]],
                    "mesh_id": c["mesh_id"],
                    "rank": c["rank"],
                    "score": c.get("score") if c.get("score") is not None else c.get("image_score"),
                    "best_view": c["best_view"],
                    **h,
                }
            )
        n_hyp += len(hyps)
        entry = {"id": a.get("id"), "image": q.get("image"), "roi_box": box, "hypotheses": hyps}
        if k is not None:
            entry["cam_K"] = [float(v) for v in k.reshape(-1)]
        else:
            first = a["candidates"][0].get("intrinsics") or {}
            entry["view_K"] = sum(first.get("K", []), [])  # the view's K: the rotation prior's camera
        priors.append(entry)
    (out / "objects.json").write_text(json.dumps(objects, indent=2) + "\n")
    (out / "priors.json").write_text(json.dumps({"priors": priors, "skipped": skipped}, indent=2) + "\n")
    print(
        f"{len(objects)} models -> {out / 'models'}; {n_hyp} hypotheses for {len(priors)} queries -> "
        f"{out / 'priors.json'}" + (f"; {len(skipped)} answer lines skipped" if skipped else ""),
        file=sys.stderr,
    )
    return 0
