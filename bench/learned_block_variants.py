"""Variants of the shipped learned cue (block 11's CLS at 224 px), replayed on feature dumps.

    python bench/learned_block_variants.py --store STORE --train SYNTH_DUMP [--train DIR ...] --test PHOTO_DUMP

The dumps are ``bench/learned_features.py``'s, with ``bench/learned_layers.py``'s ``layers_224.npz`` (block
11 at 224 px: the shipped cue). For the store's views and each dump's ROIs the backbone, cut after block 11,
runs at 224, 280 and 336 px; cached per dump as ``block11_<size>.npz``: blocks 10 and 11's CLS tokens and, at
224 px, block 11's patch tokens averaged with each patch's share of pixels off the render gray (foreground
pooling). The variants, each refitted as ``bench/learned_ltr.py`` fits (``raw4`` cue set, synthetic dumps
only, 5 folds by object, the photos never fitted on), in place of the shipped cue or beside it:

* ``L11_280``, ``L11_336``: block 11's CLS at a larger input;
* ``L10+L11_224``, ``L10+L11_280``: blocks 10 and 11's CLS concatenated (each L2-normalised);
* ``FG11_224``: the foreground patch mean instead of the CLS token; ``raw4+FG11``: beside it, as a fifth cue;
* ``avg224+336``: the mean of the 224 and 336 px cosines;
* ``flip``: view and ROI embeddings averaged with their mirror images' (cached as ``block11_224_extra.npz``);
* ``m5``, ``m10``, ``m20``: the ROI framed by 5, 10 or 20 % of its long side of render gray (the
  ``roi_margin`` option; views unchanged).

Printed: each cue alone, each fusion held out, and the paired held-out synthetic top-1 gain over the shipped
``raw4``. The rule of ``bench/learned_layers.py`` decides (a gain with a 95 % interval above zero).
Results: docs/results.md, section 7.3.
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

import learned_ltr as ltr  # noqa: E402
from learned_features import dump_rois, view_images  # noqa: E402
from learned_fg_pooling import foreground_share  # noqa: E402
from learned_fusion import cosine_per_model, l2, ranks_of  # noqa: E402
from learned_layers import layer_scores  # noqa: E402
from learned_view_cues import in_raw4, per_model, rates, refit, replay_parser  # noqa: E402

SIZES = (224, 280, 336)
MARGINS = (5, 10, 20)
BLOCK = 11
VARIANTS = {
    "L11_280": (280, "L11"),
    "L11_336": (336, "L11"),
    "FG11_224": (224, "FG11"),
    "L10+L11_224": (224, "L10+L11"),
    "L10+L11_280": (280, "L10+L11"),
}


def block_tokens(
    images: list[Image.Image], net, size: int, bf16: bool, batch: int = 16
) -> dict[str, np.ndarray]:
    """Blocks 10 and 11's CLS tokens and (at 224 px) block 11's foreground patch mean, after the final norm."""
    import torch

    from pipeline.models.focus_encoder import pixel_batch
    from pipeline.query.settings import GRAY

    out: dict[str, list] = {"L10": [], "L11": [], "FG11": []}
    for i in range(0, len(images), batch):
        part = images[i : i + batch]
        x = torch.from_numpy(pixel_batch(part, size, tuple(GRAY)))
        with torch.no_grad(), torch.autocast("cpu", dtype=torch.bfloat16, enabled=bf16):
            hs = net(pixel_values=x, output_hidden_states=True).hidden_states
            h10 = net.layernorm(hs[10].float()).float().numpy()
            h11 = net.layernorm(hs[11].float()).float().numpy()
        out["L10"].append(h10[:, 0])
        out["L11"].append(h11[:, 0])
        if size == 224:
            shares = [foreground_share(im, tuple(GRAY), size) for im in part]
            out["FG11"].append(
                np.stack(
                    [
                        (t[1:] * w[:, None]).sum(0) / max(w.sum(), 1e-6)
                        for t, w in zip(h11, shares, strict=True)
                    ]
                )
            )
    return {k: np.concatenate(v) for k, v in out.items() if v}


def dump_variants(store: str, dumps: list[Path]) -> None:
    """Writes ``block11_<size>.npz`` (``views_*``, ``rois_*``, ``view_mesh``) into every dump."""
    import torch

    from pipeline.models.focus_encoder import first_blocks
    from pipeline.models.focus_weights import focus_backbone_dir, load_backbone
    from pipeline.models.precision import bf16_pays

    if all((d / f"block11_{s}.npz").exists() for d in dumps for s in SIZES):
        return
    net = first_blocks(load_backbone(focus_backbone_dir()), BLOCK)
    bf16 = bf16_pays(torch.device("cpu"))
    meshes = json.loads((dumps[0] / "meshes.json").read_text())
    keys, views = view_images(store, meshes)
    for size in SIZES:
        t0 = time.perf_counter()
        V = block_tokens(views, net, size, bf16)
        print(f"{size} px: {len(views)} views in {time.perf_counter() - t0:.1f} s", flush=True)
        for d in dumps:
            R = block_tokens(dump_rois(d), net, size, bf16)
            np.savez(
                d / f"block11_{size}.npz",
                view_mesh=np.array([k[0] for k in keys]),
                **{f"views_{k}": v for k, v in V.items()},
                **{f"rois_{k}": v for k, v in R.items()},
            )


def dump_extra(store: str, dumps: list[Path]) -> None:
    """Writes ``block11_224_extra.npz`` (mirrored views and ROIs, framed ROIs: block 11's CLS) into every dump."""
    import torch

    from pipeline.models.focus_encoder import first_blocks, with_margin
    from pipeline.models.focus_weights import focus_backbone_dir, load_backbone
    from pipeline.models.precision import bf16_pays
    from pipeline.query.settings import GRAY

    if all((d / "block11_224_extra.npz").exists() for d in dumps):
        return
    net = first_blocks(load_backbone(focus_backbone_dir()), BLOCK)
    bf16 = bf16_pays(torch.device("cpu"))

    def cls(images):
        return block_tokens(images, net, 224, bf16)["L11"]

    def mirrored(images):
        return [im.transpose(Image.Transpose.FLIP_LEFT_RIGHT) for im in images]

    meshes = json.loads((dumps[0] / "meshes.json").read_text())
    _, views = view_images(store, meshes)
    views_flip = cls(mirrored(views))
    for d in dumps:
        rois = dump_rois(d)
        framed = {f"rois_m{m}": cls([with_margin(im, m / 100, tuple(GRAY)) for im in rois]) for m in MARGINS}
        np.savez(d / "block11_224_extra.npz", views_flip=views_flip, rois_flip=cls(mirrored(rois)), **framed)


def extra_scores(d: Path, n: int) -> dict[str, np.ndarray]:
    """(queries, models) per extra variant: ``flip`` and ``m<percent>``, against the shipped cue's views."""
    a, b = np.load(d / "layers_224.npz"), np.load(d / "block11_224_extra.npz")
    views, rois, vm = l2(a["views"][BLOCK - 1]), l2(a["rois"][BLOCK - 1]), a["view_mesh"]
    both_v, both_r = l2(views + l2(b["views_flip"])), l2(rois + l2(b["rois_flip"]))
    out = {"flip": per_model(both_r @ both_v.T, vm, n)}
    out |= {f"m{m}": per_model(l2(b[f"rois_m{m}"]) @ views.T, vm, n) for m in MARGINS}
    return out


def variant_scores(d: Path, size: int, key: str, n: int) -> np.ndarray:
    """(queries, models): best cosine over a model's views of the variant (``+`` concatenates)."""
    a = np.load(d / f"block11_{size}.npz")
    parts = key.split("+")
    v = np.concatenate([l2(a[f"views_{k}"]) for k in parts], axis=1)
    r = np.concatenate([l2(a[f"rois_{k}"]) for k in parts], axis=1)
    return cosine_per_model(r, v, a["view_mesh"], n)


def main() -> int:
    p = replay_parser(__doc__)
    args = p.parse_args()
    dumps = [Path(d) for d in (*args.train, args.test)]
    dump_variants(args.store, dumps)
    dump_extra(args.store, dumps)
    extras = ("flip", *(f"m{m}" for m in MARGINS))

    def with_variants(D, d):
        n = D["desc"].shape[1]
        D["L"]["cls"] = layer_scores(d, BLOCK, n)  # the shipped cue
        D["L11_336_cos"] = variant_scores(d, 336, "L11", n)
        for name, (size, key) in VARIANTS.items():
            D[name] = variant_scores(d, size, key, n)
            print(f"{name} alone, {d.name}: {rates(ranks_of(D[name], D['exp']), D['kind'])}")
        for name, sc in extra_scores(d, n).items():
            D[name] = sc
            print(f"{name} alone, {d.name}: {rates(ranks_of(sc, D['exp']), D['kind'])}")
        return D

    raw4 = ltr.FEATSETS["raw4"]
    featsets = {"raw4": raw4} | {name: in_raw4(name) for name in (*VARIANTS, *extras)}
    featsets["raw4+FG11"] = lambda D: [*raw4(D), D["FG11_224"]]
    featsets["avg224+336"] = lambda D: [(D["L"]["cls"] + D["L11_336_cos"]) / 2, *raw4(D)[1:]]
    refit(args.train, args.test, featsets, with_variants)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
