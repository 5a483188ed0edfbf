"""Refit the open-set calibration on more answers, leave one object out, and score it on a held-out set.

    python bench/openset_refit.py --train EXAMPLES.jsonl [--train ...] --held-out EXAMPLES.jsonl \
        [--held-out ...] [--masks-only] [--weigh-together ycb_photos,bbq_sauce] [--target 0.97] \
        [--features score,text_score,score_z ...] [--select] [--variant two-stage+verify]

``--train``: answers written by ``python -m pipeline.evaluate openset`` (its ``examples.jsonl``) or by
``bench/openset_examples.py``; ``--held-out``: answers of query sets that no fit or choice here sees. For
each ``--features`` set (and with ``--select``, the product's voting forward selection repeated in each
fold, :func:`pipeline.evaluate.openset.cross_validate`): the leave-one-object-out rates on the training
answers, pooled and per query file and ROI kind, then the model fitted on all of them at its operating
point (``--target`` of the correct answers accepted, each query file weighing the same) scored on every
held-out file, beside the shipped calibration (``pipeline/query/calibration/offline.json``). Printed:
absent answers rejected / correct answers accepted. ``--install N`` writes the N-th run's model (1-based,
in the order printed) into that file for ``--variant`` alone, with its provenance under ``fit.refits``;
the other variants stay as they are. Results: docs/results.md, sections 11 and 12.
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

import numpy as np

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))


def load(paths: list[str], variant: str, masks_only: bool, together: set[str]) -> list:
    """The examples of ``variant`` in ``paths`` (only mask ROIs with ``masks_only``); the sources in
    ``together`` share one weight group."""
    from pipeline.evaluate.openset import load_examples

    return load_examples(paths, variant, ("mask",) if masks_only else None, together)


def pct(d: dict) -> str:
    return "  -  " if d["rate"] is None else f"{100 * d['rate']:5.1f}"


def line(name: str, part: list, accepted=None) -> str:
    from pipeline.evaluate.openset import rates_at

    r = rates_at(part, accepted)
    n_abs = sum(e.library == "absent" for e in part)
    n_ok = sum(e.library == "full" and e.correct for e in part)
    return f"  {name:30s} {pct(r.absent_rejected)} % rejected ({n_abs}) / {pct(r.correct_accepted)} % accepted ({n_ok})"


def held_out_lines(model, held: dict[str, list]) -> list[str]:
    out = []
    for name, part in held.items():
        x = np.array([[e.features[f] for f in model.features] for e in part], np.float64)
        ok = dict(zip([id(e) for e in part], model.predict(x) >= model.threshold, strict=True))
        out.append(line(f"held out: {name}", part, lambda e, ok=ok: bool(ok[id(e)])))
    return out


def main() -> int:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--train", action="extend", nargs="+", required=True, help="one or more answer files")
    p.add_argument("--held-out", action="extend", nargs="+", default=[], help="one or more answer files")
    p.add_argument("--masks-only", action="store_true")
    p.add_argument("--weigh-together", default="ycb_photos,bbq_sauce")
    p.add_argument("--target", type=float, default=0.97)
    p.add_argument("--features", action="append", default=[], help="a comma-separated feature set")
    p.add_argument("--select", action="store_true", help="also the product's per-fold feature selection")
    p.add_argument("--variant", default="two-stage+verify")
    p.add_argument("--install", type=int, default=0, help="write the N-th run's model into the shipped file")
    args = p.parse_args()

    from pipeline.evaluate.openset import cross_validate, fit, select_features, usable_features
    from pipeline.query.accept import load_calibration

    together = {s for s in args.weigh_together.split(",") if s}
    train = load(args.train, args.variant, args.masks_only, together)
    held = {Path(h).stem: load([h], args.variant, True, set()) for h in args.held_out}
    shipped = load_calibration("offline").variants[args.variant]
    print(f"shipped {','.join(shipped.features)} (threshold {shipped.threshold})")
    print("\n".join(held_out_lines(shipped, held)))
    runs = [(tuple(f.split(",")), False) for f in args.features]
    if args.select:
        runs.append((usable_features(train), True))
    fitted = []
    for feats, select in runs:
        picked = cross_validate(train, feats, args.target, select=select)
        chosen = select_features(train, feats, args.target) if select else feats
        model = fit(train, chosen, args.target)
        title = "selection" if select else ",".join(feats)
        print(f"\n{title}: out of fold, {len(train)} answers" + (f" (per fold: {picked})" if select else ""))
        print(line("pooled", train))
        for src, roi in sorted({(e.source, e.roi) for e in train}):
            print(line(f"{src} / {roi}", [e for e in train if (e.source, e.roi) == (src, roi)]))
        print(f"  fitted on all: {','.join(chosen)} (threshold {model.threshold})")
        print("\n".join(held_out_lines(model, held)))
        fitted.append((model, rates_of(train)))
    if args.install:
        path = install(fitted[args.install - 1], args, len(train))
        print(f"\ninstalled run {args.install} for {args.variant} into {path}")
    return 0


def rates_of(examples: list) -> dict:
    """The out-of-fold rates of ``examples`` as the calibration's provenance records them."""
    from dataclasses import asdict

    from pipeline.evaluate.openset import rates_at

    return asdict(rates_at(examples))


def install(fitted: tuple, args, n: int):
    """Replace ``args.variant``'s model in the shipped calibration by ``fitted`` (model, out-of-fold
    rates), recording how it was made."""
    import dataclasses
    import datetime

    from pipeline.query.accept import load_calibration, shipped_path

    model, oof = fitted
    cal = load_calibration("offline")
    refits = dict(cal.fit.get("refits") or {})
    refits[args.variant] = {
        "command": "python bench/openset_refit.py " + " ".join(sys.argv[1:]),
        "date": datetime.datetime.now(datetime.timezone.utc).strftime("%Y-%m-%dT%H:%M:%SZ"),
        "train": list(args.train),
        "held_out": list(args.held_out),
        "masks_only": bool(args.masks_only),
        "target": args.target,
        "answers": n,
        "cv": "leave one object out",
        "out_of_fold": oof,
    }
    new = dataclasses.replace(
        cal, variants={**cal.variants, args.variant: model}, fit={**cal.fit, "refits": refits}
    )
    return new.write(shipped_path("offline"))


if __name__ == "__main__":
    raise SystemExit(main())
