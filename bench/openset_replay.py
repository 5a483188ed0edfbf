"""Open-set acceptance variants, replayed on the answers of ``python -m pipeline.evaluate openset``.

    python bench/openset_replay.py --store STORE --examples OPENSET_OUT/examples.jsonl \
        --fresh FRESH_OUT/examples.jsonl [--variant two-stage+verify]

``--examples``: the answers the shipped calibration was fitted on; ``--fresh``: the answers of a query set
used for nothing else (the openset command run on it alone), for confirmation. Both must come from STORE
(the full library). Three variants of the default ranking's acceptance model; the first two use the
selection as it was until section 6.7 (one fold assignment: GroupKFold on the objects as labelled,
:func:`as_before`):

* **Model hubness.** Per model, from the store's learned view vectors: its best-view cosine with every
  other model, the mean of the k best (``hub1``, ``hub3``, ``hub10``), and ``vhub`` (each view's mean
  cosine with its 10 nearest views of other models, averaged over the model's views). Offered as the top-1
  model's ``learned - hub`` beside the shipped features: leave one object out with the product's forward
  selection in each fold (``pipeline.evaluate.openset.cross_validate(select=True)``), with and without
  them, and each one forced in beside the shipped set (that set was selected on all the answers, so those
  lines are optimistic).
* **Selection threshold.** ``min_gain`` (the inner cross-validated rejection a feature must add) at 0.005
  (shipped), 0.02 and 0.04: leave one object out as above, then fitted on every answer and scored on the
  fresh answers, at the operating point and at the threshold that accepts 95 % of their correct answers.
* **Selection votes** (section 6.7, shipped with 5): the selection as before, and the feature set picked
  most often over ``repeats`` = 1, 5 or 9 seeded fold assignments (``select_features(repeats=...)``), leave
  one object out and on the fresh set, with the absent answers rejected at one global threshold accepting
  95, 97 and 98 % of the correct ones.

Printed: absent rejected / correct accepted, pooled and on the photos (``ycb_photos``) per ROI kind.
Results: docs/results.md, sections 6.6 and 6.7.
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

import numpy as np

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))

import pipeline.evaluate.openset as openset  # noqa: E402
import pipeline.query.accept as accept  # noqa: E402
from pipeline.evaluate.openset import (  # noqa: E402
    Example,
    cross_validate,
    fit,
    greedy_selection,
    rates_at,
    select_features,
    usable_features,
)

HUB = ("l_hub1", "l_hub3", "l_hub10", "l_vhub")


def as_before(examples, candidates, target, c=1.0, folds=5, min_gain=openset.MIN_GAIN, repeats=None):
    """The selection until section 6.7: one greedy pass on the objects' own fold assignment."""
    groups = np.array([e.group for e in examples])
    return greedy_selection(examples, candidates, target, groups, c, folds, min_gain)


def selecting_as_before(fn):
    """Runs ``fn`` with :func:`as_before` as the selection ``cross_validate`` calls."""

    def run(*args):
        saved = openset.select_features
        openset.select_features = as_before
        try:
            return fn(*args)
        finally:
            openset.select_features = saved

    return run


TARGET = 0.97  # the openset command's default operating point


def model_hubness(store_path: str) -> dict[str, dict[str, float]]:
    """mesh_id -> {hub1, hub3, hub10, vhub} from the store's learned view vectors."""
    from pipeline.query.library import StoreTables, latest_onboarding
    from pipeline.store import Store

    store = Store(Path(store_path), writable=False)
    tables = StoreTables(store, latest_onboarding(store), use_cache=False)
    views = tables.learned_views
    if views is None:
        raise SystemExit(f"store {store_path} has no learned view embeddings")
    id_of = dict(zip(tables.meshes.column("mesh_idx").to_pylist(), tables.meshes.column("mesh_id").to_pylist(),
                     strict=True))  # fmt: skip
    mesh = np.array(views.column("mesh_idx").to_pylist())
    e = np.array(views.column("embedding").to_pylist(), np.float32)
    e /= np.linalg.norm(e, axis=1, keepdims=True)
    s = e @ e.T
    models = sorted(set(mesh.tolist()))
    best = np.array(
        [[s[np.ix_(mesh == a, mesh == b)].max() if a != b else -1.0 for b in models] for a in models]
    )
    top = -np.sort(-best, axis=1)
    out = {}
    for i, m in enumerate(models):
        own = mesh == m
        vhub = float(np.sort(s[np.ix_(own, ~own)], axis=1)[:, -10:].mean())
        out[id_of[m]] = {"hub1": float(top[i, 0]), "hub3": float(top[i, :3].mean()),
                         "hub10": float(top[i, :10].mean()), "vhub": vhub}  # fmt: skip
    return out


def load(path: str, variant: str, hubs: dict | None = None) -> list[Example]:
    out = []
    for line in Path(path).read_text().splitlines():
        d = json.loads(line)
        if d["variant"] != variant:
            continue
        d.pop("confidence", None), d.pop("accepted", None)
        if hubs is not None:
            h = hubs[d["top1"]]
            for k in HUB:
                d["features"][k] = d["features"]["learned"] - h[k[2:]]
        out.append(Example(**d))
    return out


def pct(d: dict) -> str:
    return f"{100 * d['rate']:.1f}% [{100 * d['lo']:.0f}, {100 * d['hi']:.0f}]"


def report(tag: str, exs: list[Example], picked: dict | None = None) -> None:
    """The out-of-fold (or fresh) rates of ``exs``, pooled and on the photos per ROI kind."""
    r = rates_at(exs)
    line = f"{tag}: pooled {pct(r.absent_rejected)} rejected / {pct(r.correct_accepted)} accepted"
    for roi in ("mask", "box"):
        part = [e for e in exs if e.source == "ycb_photos" and e.roi == roi]
        if part:
            p = rates_at(part)
            line += f"; photos {roi} {100 * p.absent_rejected['rate']:.1f} / {100 * p.correct_accepted['rate']:.1f}"
    if picked:
        line += " | per fold: " + ", ".join(
            f"{k} x{v}" for k, v in sorted(picked.items(), key=lambda t: -t[1])[:3]
        )
    print(line, flush=True)


def hubness(args) -> None:
    accept.FEATURES = (*accept.FEATURES, *HUB)  # the acceptance model checks its features' names
    exs = load(args.examples, args.variant, model_hubness(args.store))
    base = tuple(f for f in usable_features(exs) if f not in HUB)
    report("selection, shipped candidates", exs, cross_validate(exs, base, TARGET, select=True))
    report("selection, + hubness", exs, cross_validate(exs, (*base, *HUB), TARGET, select=True))
    shipped = as_before(exs, base, TARGET)  # the set 6.5 shipped
    cross_validate(exs, shipped, TARGET)
    report(f"the shipped set {','.join(shipped)} in every fold (optimistic)", exs)
    for f in HUB:
        cross_validate(exs, (*shipped, f), TARGET)
        report(f"+ {f} (optimistic)", exs)


def min_gain(args) -> None:
    exs = load(args.examples, args.variant)
    fresh = load(args.fresh, args.variant)
    feats = usable_features(exs)
    for gain in (0.005, 0.02, 0.04):
        picked = cross_validate(exs, feats, TARGET, select=True, min_gain=gain)
        report(f"min_gain {gain}, leave one object out", exs, picked)
        on_fresh(f"min_gain {gain}", exs, as_before(exs, feats, TARGET, min_gain=gain), fresh)


def curve(examples: list[Example], conf: np.ndarray) -> str:
    """Absent answers rejected at the one threshold that accepts 95, 97 and 98 % of the correct ones."""
    right = np.array([e.library == "full" and e.correct for e in examples])
    absent = np.array([e.library == "absent" for e in examples])
    return ", ".join(
        f"{100 * np.mean(conf[absent] < np.quantile(conf[right], 1 - a)):.1f} % at {100 * a:g} %"
        for a in (0.95, 0.97, 0.98)
    )


def on_fresh(name: str, exs: list[Example], chosen: tuple[str, ...], fresh: list[Example]) -> None:
    """Fits ``chosen`` on every answer of ``exs`` and prints its rates on the fresh answers, at its operating
    point and at one threshold (:func:`curve`)."""
    model = fit(exs, chosen, TARGET)
    conf = model.predict(np.array([[e.features[f] for f in chosen] for e in fresh]))
    for e, c in zip(fresh, conf, strict=True):
        e.confidence, e.accepted = float(c), bool(c >= model.threshold)
    report(f"{name}, {','.join(chosen)} fitted on every answer, on the fresh set", fresh)
    print(f"    one threshold on the fresh set: {curve(fresh, conf)}", flush=True)


def votes(args) -> None:
    exs = load(args.examples, args.variant)
    fresh = load(args.fresh, args.variant)
    feats = usable_features(exs)
    for repeats in (None, 1, 5, 9):
        name = "as before" if repeats is None else f"repeats {repeats}"
        if repeats is None:
            picked = selecting_as_before(cross_validate)(exs, feats, TARGET, 1.0, True)
            chosen = as_before(exs, feats, TARGET)
        else:
            picked = cross_validate(exs, feats, TARGET, select=True, repeats=repeats)
            chosen = select_features(exs, feats, TARGET, repeats=repeats)
        report(f"{name}, leave one object out", exs, picked)
        oof = np.array([e.confidence for e in exs])
        print(f"    one threshold on the out-of-fold confidences: {curve(exs, oof)}")
        on_fresh(name, exs, chosen, fresh)


def main() -> int:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--store", required=True)
    p.add_argument("--examples", required=True, help="the calibration answers (examples.jsonl)")
    p.add_argument("--fresh", required=True, help="a fresh set's answers (examples.jsonl), for confirmation")
    p.add_argument("--variant", default="two-stage+verify")
    args = p.parse_args()
    selecting_as_before(min_gain)(args)
    votes(args)
    selecting_as_before(hubness)(args)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
