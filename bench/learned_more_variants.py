"""Four more variants around the shipped learned cue (block 11's CLS on exposure-normalised images),
replayed on feature dumps.

    python bench/learned_more_variants.py --store STORE --train SYNTH_DUMP [--train DIR ...] \
        --test PHOTO_DUMP --confirm FRESH_SYNTH_DUMP [--variants rotations,white_balance,erosion,rings]

The dumps are ``bench/learned_features.py``'s with ``bench/learned_exposure.py``'s ``exposure_110.npz`` (the
shipped cue, ``E110``); STORE is the store the dumps were made from (its meshes are re-rendered for
``rings``). Variants, each printed as the cue alone (top-1 / top-5 per dump and ROI kind):

* ``rotations``: the ROI also turned by 90, 180 and 270 degrees in the image plane (gray corners), the
  model's score the max over the turns (all four, or 0 / 90 / 270), their mean, or the max with the turned
  ones 0.02 behind; the synthetic queries are rolled (``pipeline.evaluate.synth``), the photos' objects lie
  in any direction.
* ``white_balance``: the ROI's foreground multiplied by the photo's grey-world (p = 1) or shades-of-grey
  (p = 6) channel gains, estimated on the whole photo, at strength 0.5 or 1, before the exposure step; the
  harder synthetic sets carry a random white balance (``pipeline.evaluate.degrade``).
* ``erosion``: the ROI's foreground (off the render gray) eroded by 1, 2 or 3 px, or by 1 % or 2 % of the
  ROI's long side, before the exposure step (the harder synthetic sets grow their query masks by 0-4 px,
  ``pipeline.evaluate.degrade``; the photos' masks are the dataset's labels).
* ``erosion_fused`` (not in the default list): the ROI eroded by 1 px in place of the shipped cue, refitted
  into the fusion and confirmed like ``rings`` (section 10 confirms on an exact-mask set, ``synth --mask-grow
  0,0``).
* ``rings``: one more elevation ring of 4 views (30, -45 or 75 degrees; rendered and embedded here, cached
  as ``rings.npz`` beside the first training dump), the model's score the max over its 12 stored views and
  the ring's. Also refitted into the shipped cue set as ``bench/learned_ltr.py`` fits (synthetic dumps
  only, 5 folds by object), with the pooled held-out gain over ``E110`` on every synthetic dump
  (``bench/learned_exposure.py``'s ``--confirm`` rule).

Results: docs/results.md, section 7.5.
"""

from __future__ import annotations

import json
import sys
import time
from pathlib import Path

import numpy as np
from PIL import Image

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))
sys.path.insert(0, str(REPO / "bench"))

import learned_exposure as exposure_bench  # noqa: E402
import learned_ltr as ltr  # noqa: E402
from learned_exposure import confirm, shipped_net  # noqa: E402
from learned_features import dump_rois  # noqa: E402
from learned_fusion import cosine_per_model, ranks_of  # noqa: E402
from learned_view_cues import in_raw4, rates, refit, replay_parser  # noqa: E402

TARGET = 110  # the shipped exposure target
RINGS = {"e30": 30.0, "em45": -45.0, "e75": 75.0}


def embed_normalised(images: list[Image.Image], net, bf16: bool) -> np.ndarray:
    """The shipped cue's vectors of ``images``: exposure step at :data:`TARGET`, then the network."""
    return exposure_bench.embed_normalised(images, net, bf16, TARGET)


def loaded(d: Path):
    """(records, expected mesh positions, ROI kinds, the shipped cue's arrays) of dump ``d``."""
    recs = json.loads((d / "queries.json").read_text())
    return (
        recs,
        [r["expected"] for r in recs],
        np.array([r["kind"] for r in recs]),
        np.load(d / f"exposure_{TARGET}.npz"),
    )


def rotations(dumps: list[Path], net, bf16: bool) -> None:
    from pipeline.query.settings import GRAY

    for d in dumps:
        recs, exp, kind, E = loaded(d)
        path = d / "rotations_110.npz"
        if not path.exists():
            rois = dump_rois(d, recs)
            turned = {
                a: [im.rotate(a, expand=True, fillcolor=tuple(GRAY)) for im in rois] for a in (90, 180, 270)
            }
            np.savez(path, **{f"r{a}": embed_normalised(ims, net, bf16) for a, ims in turned.items()})
        R = np.load(path)
        n = int(E["view_mesh"].max()) + 1
        s0 = cosine_per_model(E["rois"], E["views"], E["view_mesh"], n)
        s = {a: cosine_per_model(R[f"r{a}"], E["views"], E["view_mesh"], n) for a in (90, 180, 270)}
        side = np.maximum(s[90], s[270])
        for name, score in (
            ("as shipped", s0),
            ("max 0/90/270", np.maximum(s0, side)),
            ("max of four", np.maximum.reduce([s0, *s.values()])),
            ("mean 0/90/270", (s0 + s[90] + s[270]) / 3),
            ("max, turned 0.02 behind", np.maximum(s0, side - 0.02)),
        ):
            print(f"rotations, {d.name}, {name}: {rates(ranks_of(score, exp), kind)}", flush=True)


def channel_gains(path: str, p: float) -> np.ndarray:
    """Shades-of-grey gains (p = 1: grey world) of the whole photo at ``path``, mean gain 1."""
    a = np.asarray(Image.open(path).convert("RGB"), np.float32).reshape(-1, 3) / 255.0
    m = (a**p).mean(0) ** (1.0 / p)
    return m.mean() / np.maximum(m, 1e-3)


def balanced(im: Image.Image, gains: np.ndarray) -> Image.Image:
    """``im`` with its foreground (off the render gray) multiplied by ``gains``, clipped to 8 bits."""
    from pipeline.models.exposure import foreground_mask
    from pipeline.query.settings import GRAY

    rgb = np.ascontiguousarray(np.asarray(im.convert("RGB")))
    fg = foreground_mask(rgb, tuple(GRAY))
    a = rgb.astype(np.float32)
    a[fg] = np.clip(a[fg] * gains, 0, 255)
    return Image.fromarray(a.round().astype(np.uint8))


def white_balance(dumps: list[Path], net, bf16: bool) -> None:
    settings = [(p, k) for p in (1.0, 6.0) for k in (0.5, 1.0)]
    for d in dumps:
        recs, exp, kind, E = loaded(d)
        path = d / "white_balance_110.npz"
        if not path.exists():
            rois = dump_rois(d, recs)
            gains = {(r["image"], p): None for r in recs for p, _ in settings}
            gains = {key: channel_gains(*key) for key in gains}
            out = {}
            for p, k in settings:
                ims = [balanced(im, gains[(r["image"], p)] ** k) for r, im in zip(recs, rois, strict=True)]
                out[f"p{p:g}_k{k:g}"] = embed_normalised(ims, net, bf16)
            np.savez(path, **out)
        W = np.load(path)
        n = int(E["view_mesh"].max()) + 1
        print(
            f"white balance, {d.name}, as shipped: "
            f"{rates(ranks_of(cosine_per_model(E['rois'], E['views'], E['view_mesh'], n), exp), kind)}"
        )
        for key in W.files:
            score = cosine_per_model(W[key], E["views"], E["view_mesh"], n)
            print(f"white balance, {d.name}, {key}: {rates(ranks_of(score, exp), kind)}", flush=True)


def eroded(im: Image.Image, px: int) -> Image.Image:
    """``im`` with its foreground (off the render gray) eroded by ``px`` pixels (unchanged when that would
    leave less than 30 % of it)."""
    import cv2

    from pipeline.models.exposure import foreground_mask
    from pipeline.query.settings import GRAY

    a = np.ascontiguousarray(np.asarray(im.convert("RGB"))).copy()
    fg = foreground_mask(a, tuple(GRAY)).astype(np.uint8)
    kept = cv2.erode(fg, np.ones((2 * px + 1, 2 * px + 1), np.uint8))
    if kept.sum() < 0.3 * fg.sum():
        return im
    a[(fg > 0) & (kept == 0)] = GRAY
    return Image.fromarray(a)


def erosion(dumps: list[Path], net, bf16: bool) -> None:
    for d in dumps:
        recs, exp, kind, E = loaded(d)
        rois = dump_rois(d, recs)
        n = int(E["view_mesh"].max()) + 1
        plain = cosine_per_model(E["rois"], E["views"], E["view_mesh"], n)
        print(f"erosion, {d.name}, as shipped: {rates(ranks_of(plain, exp), kind)}")
        for px, share in ((1, 0.0), (2, 0.0), (3, 0.0), (0, 0.01), (0, 0.02)):
            name = f"{px} px" if px else f"{100 * share:g} % of the side"
            sizes = [px or max(1, round(share * max(im.size))) for im in rois]
            x = embed_normalised([eroded(im, k) for im, k in zip(rois, sizes, strict=True)], net, bf16)
            score = cosine_per_model(x, E["views"], E["view_mesh"], n)
            print(f"erosion, {d.name}, {name}: {rates(ranks_of(score, exp), kind)}", flush=True)


def erosion_fused(args, dumps: list[Path], net, bf16: bool, px: int = 1) -> None:
    """The ROI eroded by ``px`` px in place of the shipped cue, refitted into the fusion like ``rings``
    (cached per dump as ``erode<px>_110.npz``)."""
    for d in dumps:
        path = d / f"erode{px}_{TARGET}.npz"
        if not path.exists():
            recs = json.loads((d / "queries.json").read_text())
            np.savez(path, rois=embed_normalised([eroded(im, px) for im in dump_rois(d, recs)], net, bf16))

    def patch(D, d):
        n = D["desc"].shape[1]
        E = np.load(d / f"exposure_{TARGET}.npz")
        D["E110"] = ltr.exposure_scores(d, TARGET, n)
        D[f"ER{px}"] = cosine_per_model(
            np.load(d / f"erode{px}_{TARGET}.npz")["rois"], E["views"], E["view_mesh"], n
        )
        return D

    featsets = {"raw4": ltr.FEATSETS["raw4"], "E110": in_raw4("E110"), f"ER{px}": in_raw4(f"ER{px}")}
    refit(args.train, args.test, featsets, patch, simplest="E110")
    confirm(args.train, args.confirm, featsets, patch, base_name="E110")


def render_rings(store: str, meshes: list[str], out: Path) -> None:
    """Renders every model on each ring of :data:`RINGS` (4 views) and writes their shipped-cue vectors."""
    from pipeline.mesh.load import load_mesh
    from pipeline.mesh.render import Renderer
    from pipeline.mesh.settings import RenderConfig
    from pipeline.models.focus_encoder import LearnedViewEncoder
    from pipeline.profiles import PROFILES
    from pipeline.store import Store

    if out.exists():
        return
    enc = LearnedViewEncoder(**PROFILES["offline"].learned_encoder.options)
    s = Store.open(store)
    rows = s.read_latest("meshes").to_pylist()
    s.close()
    path = {r["mesh_id"]: (f"{r['library_root']}/{r['source_path']}", r["format"]) for r in rows}
    arrays = {}
    for name, elevation in RINGS.items():
        renderer = Renderer(RenderConfig(elevations_deg=(elevation,), views_per_ring=4))
        t0 = time.perf_counter()
        embs, vm = [], []
        for j, m in enumerate(meshes):
            views = renderer.render(load_mesh(*path[m], max_faces=10**7))
            embs.append(enc.encode_image([Image.fromarray(v.image) for v in views]))
            vm += [j] * len(views)
        renderer.close()
        print(f"ring {name}: {len(vm)} views rendered and embedded in {time.perf_counter() - t0:.1f} s")
        arrays[name], arrays[f"{name}_mesh"] = np.concatenate(embs), np.array(vm)
    np.savez(out, **arrays)


def rings(args, dumps: list[Path]) -> None:
    cache = dumps[0] / "rings.npz"
    render_rings(args.store, json.loads((dumps[0] / "meshes.json").read_text()), cache)
    R = np.load(cache)

    def patch(D, d):
        n = D["desc"].shape[1]
        E = np.load(d / f"exposure_{TARGET}.npz")
        D["E110"] = ltr.exposure_scores(d, TARGET, n)
        for name in RINGS:
            D[f"+{name}"] = np.maximum(D["E110"], cosine_per_model(E["rois"], R[name], R[f"{name}_mesh"], n))
        return D

    for d in dumps:
        D = patch(ltr.load(d), d)
        for key in ("E110", *(f"+{name}" for name in RINGS)):
            print(f"rings, {d.name}, {key} alone: {rates(ranks_of(D[key], D['exp']), D['kind'])}", flush=True)
    featsets = {"raw4": ltr.FEATSETS["raw4"], "E110": in_raw4("E110")}
    featsets |= {f"+{name}": in_raw4(f"+{name}") for name in RINGS}
    refit(args.train, args.test, featsets, patch, simplest="E110")
    confirm(args.train, args.confirm, featsets, patch, base_name="E110")


def main() -> int:
    p = replay_parser(__doc__)
    p.add_argument("--confirm", required=True, help="a fresh synthetic dump (never fitted or chosen on)")
    p.add_argument("--variants", default="rotations,white_balance,erosion,rings")
    args = p.parse_args()
    dumps = [Path(d) for d in (*args.train, args.test, args.confirm)]
    variants = args.variants.split(",")
    if {"rotations", "white_balance", "erosion", "erosion_fused"} & set(variants):
        net, bf16 = shipped_net()
        if "rotations" in variants:
            rotations(dumps, net, bf16)
        if "white_balance" in variants:
            white_balance(dumps, net, bf16)
        if "erosion" in variants:
            erosion(dumps, net, bf16)
        if "erosion_fused" in variants:
            erosion_fused(args, dumps, net, bf16)
    if "rings" in variants:
        rings(args, dumps)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
