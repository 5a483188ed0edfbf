"""Speed of the learned view encoder per input size and precision, and how far bfloat16 moves embeddings.

    python bench/bench_learned_encoder.py --store STORE [--sizes 224,280,336] [--layers 11,12] [--views 64]

Embeds ``--views`` stored views of ``STORE`` (batch 32, after a warm-up) and one ROI-sized image with each
precision (float32, bfloat16) at each size; prints ms per view, ms for one ROI, the opening time (the cached
TorchScript copy once traced) and the smallest cosine between a view's bfloat16 and float32 embedding, for
each depth (``--layers``: the block pooled, 12 = the whole network; the offline profile pools block 11).
bfloat16 is only fast on CPUs with AMX tiles or AVX512-BF16 (``bf16_pays``); elsewhere it is emulated.
"""

from __future__ import annotations

import argparse
import io
import sys
import time
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))


def main() -> int:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--store", required=True)
    p.add_argument("--sizes", default="224,280,336")
    p.add_argument("--views", type=int, default=64)
    p.add_argument("--layers", default="11,12", help="blocks pooled (12: the whole network)")
    args = p.parse_args()
    import torch
    from PIL import Image

    from pipeline.models.focus_encoder import LearnedViewEncoder
    from pipeline.models.precision import bf16_pays
    from pipeline.store import Store

    store = Store.open(args.store)
    t = store.read_latest("views", columns=["image"])
    store.close()
    images = [Image.open(io.BytesIO(b)).convert("RGB") for b in t.column("image").to_pylist()[: args.views]]
    print(
        f"torch {torch.__version__}, {torch.get_num_threads()} threads, bf16 pays here: {bf16_pays(torch.device('cpu'))}"
    )
    print("| size | block | precision | open s | ms / view (batch 32) | ms / one ROI | min cosine to float32 |")
    print("|---|---|---|---|---|---|---|")
    runs = [(int(s), int(k)) for s in args.sizes.split(",") for k in args.layers.split(",")]
    for size, layer in runs:
        ref = None
        for precision in ("fp32", "bf16"):
            t0 = time.perf_counter()
            enc = LearnedViewEncoder(size=size, precision=precision, layer=layer, batch_size=32)
            opened = time.perf_counter() - t0
            enc.encode_image(images[:4])
            t0 = time.perf_counter()
            emb = enc.encode_image(images)
            per_view = (time.perf_counter() - t0) / len(images)
            t0 = time.perf_counter()
            enc.encode_roi(images[:1])
            one = time.perf_counter() - t0
            ref = emb if ref is None else ref
            cos = float((emb * ref).sum(axis=1).min())
            print(
                f"| {size} | {layer} | {precision} | {opened:.2f} | {per_view * 1000:.1f} | {one * 1000:.0f} | {cos:.5f} |",
                flush=True,
            )
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
