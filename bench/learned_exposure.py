"""Exposure normalisation before the learned encoder, replayed on feature dumps.

    python bench/learned_exposure.py --store STORE --train SYNTH_DUMP [--train DIR ...] --test PHOTO_DUMP \
        [--confirm FRESH_SYNTH_DUMP] [--targets 40,60,80,110,150]

The dumps are ``bench/learned_features.py``'s, with ``bench/learned_layers.py``'s ``layers_224.npz`` (block
11's CLS at 224 px on the images as rendered or photographed: the cue shipped before). For the store's views
and each dump's ROIs, every image's foreground is scaled to a median luminance of each target
(:func:`pipeline.models.exposure.normalise_exposure`, the product's ``exposure`` option) and embedded by the
shipped block (224 px); cached per dump as ``exposure_<target>.npz``. Each target's cue replaces the learned
cosine of the shipped cue set (``raw4``), refitted as ``bench/learned_ltr.py`` fits (synthetic dumps only, 5
folds by object, the photos never fitted on).

Printed: the median foreground luminance of the views and of each dump's ROIs; each cue alone on every dump; each fusion held out; the paired held-out synthetic top-1 gain over
``raw4`` without normalisation. With ``--confirm`` (a synthetic dump used for nothing else) every target is
also fitted on all training dumps and ranked there, and the gain is pooled over the training dumps' held-out
ranks and the fresh set's: the rule of ``bench/learned_layers.py`` (a gain whose 95 % interval, over
objects, lies above zero) on all the synthetic evidence. ``--descriptor 110`` also replays the offline
descriptor on images normalised the same way, beside the learned cue at that target (cached as
``descriptor_110.npz``). Results: docs/results.md, section 7.4.
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
from learned_fusion import bootstrap, cosine_per_model, ranks_of  # noqa: E402
from learned_layers import dump_layers, layer_scores  # noqa: E402
from learned_view_cues import in_raw4, rates, refit, replay_parser  # noqa: E402

TARGETS = (40, 60, 80, 110, 150)


def cls_tokens(images: list[Image.Image], net, bf16: bool, batch: int = 16) -> np.ndarray:
    """The final layer norm's CLS token of ``net`` (cut after the shipped block) at 224 px."""
    import torch

    from pipeline.models.focus_encoder import pixel_batch
    from pipeline.query.settings import GRAY

    out = []
    for i in range(0, len(images), batch):
        x = torch.from_numpy(pixel_batch(images[i : i + batch], 224, tuple(GRAY)))
        with torch.no_grad(), torch.autocast("cpu", dtype=torch.bfloat16, enabled=bf16):
            out.append(net(pixel_values=x).last_hidden_state[:, 0].float().numpy())
    return np.concatenate(out)


def shipped_net():
    """(the network cut after the shipped block, whether it runs in bfloat16 as the product's encoder
    would with precision ``auto``)."""
    import torch

    from pipeline.models.focus_encoder import first_blocks
    from pipeline.models.focus_weights import focus_backbone_dir, load_backbone
    from pipeline.models.precision import bf16_pays

    return first_blocks(load_backbone(focus_backbone_dir()), ltr.shipped_block()), bf16_pays(
        torch.device("cpu")
    )


def embed_normalised(images: list[Image.Image], net, bf16: bool, target: float) -> np.ndarray:
    """CLS vectors of ``images`` with their foreground normalised to ``target`` first (the exposure step)."""
    from pipeline.models.exposure import normalise_exposure
    from pipeline.query.settings import GRAY

    return cls_tokens([normalise_exposure(im, target, tuple(GRAY)) for im in images], net, bf16)


def dump_exposure(store: str, dumps: list[Path], targets: list[float]) -> None:
    """Writes ``exposure_<target>.npz`` (``views``, ``rois``, ``view_mesh``) into every dump lacking it."""
    todo = [t for t in targets if not all((d / f"exposure_{t:g}.npz").exists() for d in dumps)]
    if not todo:
        return
    net, bf16 = shipped_net()
    meshes = json.loads((dumps[0] / "meshes.json").read_text())
    keys, views = view_images(store, meshes)
    for t in todo:
        t0 = time.perf_counter()
        V = embed_normalised(views, net, bf16, t)
        print(f"exposure {t:g}: {len(views)} views in {time.perf_counter() - t0:.1f} s", flush=True)
        for d in dumps:
            R = embed_normalised(dump_rois(d), net, bf16, t)
            np.savez(d / f"exposure_{t:g}.npz", views=V, rois=R, view_mesh=np.array([k[0] for k in keys]))


def luminance_stats(store: str, dumps: list[Path]) -> None:
    """Prints the median over images of each image's median foreground luminance: the store's views, and
    each dump's ROIs per kind (the gap the normalisation closes)."""
    from pipeline.models.exposure import foreground_luminance
    from pipeline.query.settings import GRAY

    def med(images) -> str:
        vals = [v for v in (foreground_luminance(im, tuple(GRAY)) for im in images) if v is not None]
        return f"{np.median(vals):.0f} (n={len(vals)})"

    meshes = json.loads((dumps[0] / "meshes.json").read_text())
    print(f"median foreground luminance: the store's views {med(view_images(store, meshes)[1])}")
    for d in dumps:
        recs = json.loads((d / "queries.json").read_text())
        for kind in sorted({r["kind"] for r in recs}):
            rois = dump_rois(d, [r for r in recs if r["kind"] == kind])
            print(f"median foreground luminance: {d.name} ROIs ({kind}) {med(rois)}")


def with_exposure(targets: list[float]):
    """A dump patch: the unnormalised shipped block as ``L["cls"]`` (the baseline) and ``E<target>`` cues."""

    def patch(D, d):
        n = D["desc"].shape[1]
        D["L"]["cls"] = layer_scores(d, ltr.shipped_block(), n)
        print(f"unnormalised alone, {d.name}: {rates(ranks_of(D['L']['cls'], D['exp']), D['kind'])}")
        for t in targets:
            D[f"E{t:g}"] = ltr.exposure_scores(d, t, n)
            print(f"E{t:g} alone, {d.name}: {rates(ranks_of(D[f'E{t:g}'], D['exp']), D['kind'])}")
        return D

    return patch


def dump_descriptor(store: str, dumps: list[Path], target: float) -> None:
    """Writes ``descriptor_<target>.npz`` (the offline descriptor of the normalised views and ROIs: ``views``,
    ``rois``, ``view_mesh``) into every dump lacking it."""
    from pipeline.models.exposure import normalise_exposure
    from pipeline.models.offline_descriptor import ClassicalDescriptor
    from pipeline.query.settings import GRAY

    todo = [d for d in dumps if not (d / f"descriptor_{target:g}.npz").exists()]
    if not todo:
        return
    enc, fill = ClassicalDescriptor(), tuple(GRAY)
    meshes = json.loads((todo[0] / "meshes.json").read_text())
    keys, views = view_images(store, meshes)
    V = enc.encode_image([normalise_exposure(v, target, fill) for v in views])
    for d in todo:
        R = enc.encode_image([normalise_exposure(im, target, fill) for im in dump_rois(d)])
        np.savez(d / f"descriptor_{target:g}.npz", views=V, rois=R, view_mesh=np.array([k[0] for k in keys]))


def confirm(trains: list[str], fresh: str, featsets: dict, patch, base_name: str = "raw4") -> None:
    """Pooled held-out synthetic gain: the training dumps' 5-fold ranks plus the fresh dump's ranks under
    weights fitted on every training dump, paired against ``base_name``, 95 % intervals over objects."""
    T = [patch(ltr.load(Path(d)), Path(d)) for d in trains]
    F = patch(ltr.load(Path(fresh)), Path(fresh))
    groups = np.concatenate([D["label"] for D in T] + [F["label"]])
    ranks = {}
    for name, fn in featsets.items():
        w, wv = ltr.fit_all(T, fn)
        on_fresh = ranks_of(ltr.scores(np.stack(fn(F)), w, ltr.bonus(F), wv), F["exp"])
        print(
            f"{name} on {Path(fresh).name} (fitted on every training dump): {ltr.rates(on_fresh, F['label'])}"
        )
        ranks[name] = np.concatenate([*ltr.cv_ranks(T, fn), on_fresh])
    base = ranks[base_name]
    for name, r in ranks.items():
        if name == base_name:
            continue
        d5 = (r <= 5).astype(float) - (base <= 5).astype(float)
        lo, hi = bootstrap(d5, groups)
        print(
            f"pooled synthetic held out (n={len(r)}), against {base_name}: {name} top-1 {np.mean(r <= 1):.3f} against "
            f"{np.mean(base <= 1):.3f}, gain {ltr.paired_gain(r, base, groups)}; top-5 {np.mean(r <= 5):.3f} "
            f"against {np.mean(base <= 5):.3f}, gain {d5.mean():+.3f} [{lo:+.3f}, {hi:+.3f}]"
        )


def main() -> int:
    p = replay_parser(__doc__)
    p.add_argument("--confirm", help="a fresh synthetic dump (never fitted or chosen on) for the pooled gain")
    p.add_argument("--targets", default=",".join(map(str, TARGETS)), help="median luminances to try")
    p.add_argument(
        "--descriptor", type=float, help="also replay the descriptor on images normalised to this target"
    )
    p.add_argument(
        "--dump-only", action="store_true", help="only write exposure_<target>.npz into every dump lacking it"
    )
    args = p.parse_args()
    targets = [float(x) for x in args.targets.split(",")]
    dumps = [Path(d) for d in (*args.train, args.test, *([args.confirm] if args.confirm else []))]
    if args.dump_only:
        dump_exposure(args.store, dumps, targets)
        return 0
    luminance_stats(args.store, dumps)
    dump_layers(args.store, dumps)  # the unnormalised baseline of a dump learned_layers.py never saw
    dump_exposure(args.store, dumps, targets)
    patch = with_exposure(targets)
    featsets = {"raw4": ltr.FEATSETS["raw4"]} | {f"E{t:g}": in_raw4(f"E{t:g}") for t in targets}
    refit(args.train, args.test, featsets, patch)
    if args.confirm:
        confirm(args.train, args.confirm, featsets, patch)
    if args.descriptor is not None:
        descriptor_replay(args, dumps, patch)
    return 0


def descriptor_replay(args, dumps: list[Path], patch) -> None:
    """``--descriptor T``: the descriptor on images normalised to ``T`` too, beside the learned cue at ``T``."""
    t = args.descriptor
    dump_descriptor(args.store, dumps, t)

    def with_descriptor(D, d):
        D = patch(D, d)
        a = np.load(d / f"descriptor_{t:g}.npz")
        D["descE"] = cosine_per_model(a["rois"], a["views"], a["view_mesh"], D["desc"].shape[1])
        print(
            f"descriptor alone, {d.name}: {rates(ranks_of(D['desc'], D['exp']), D['kind'])}; normalised: "
            f"{rates(ranks_of(D['descE'], D['exp']), D['kind'])}"
        )
        return D

    learned = f"E{t:g}"
    featsets = {
        "raw4": ltr.FEATSETS["raw4"],  # the shipped fusion's cue set, which the refit's report reads
        learned: in_raw4(learned),
        f"{learned}+descE": lambda D: [D[learned], D["descE"], *ltr.FEATSETS["raw4"](D)[2:]],
    }
    refit(args.train, args.test, featsets, with_descriptor, simplest=learned)
    if args.confirm:
        confirm(args.train, args.confirm, featsets, with_descriptor, base_name=learned)


if __name__ == "__main__":
    raise SystemExit(main())
