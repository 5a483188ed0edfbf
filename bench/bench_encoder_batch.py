"""Speed of onboarding's learned view pass per encoder batch size, alternated in one process.

    python bench/bench_encoder_batch.py --store STORE [--batches 8,16,32] [--views 96] [--repeats 4]

Reads ``--views`` stored views of ``STORE`` and runs the offline profile's learned encoder on them the way
the ``embed_image`` step does (``encode_image_patches``: embeddings and object patch tokens from one
forward pass), with each batch size in turn, ``--repeats`` rounds alternating the sizes after a warm-up.
Prints the median ms per view of each size, its ratio to the first, and the largest difference of its
embeddings from the first size's (batching must not change what is stored). Threads: torch's default
(every core), as onboarding runs.
"""

from __future__ import annotations

import argparse
import io
import statistics
import sys
import time
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))


def main() -> int:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--store", required=True)
    p.add_argument("--batches", default="8,16,32")
    p.add_argument("--views", type=int, default=96)
    p.add_argument("--repeats", type=int, default=4)
    args = p.parse_args()
    import numpy as np
    import torch
    from PIL import Image

    from pipeline.models.registry import create_model
    from pipeline.profiles import get_profile
    from pipeline.store import Store

    store = Store.open(args.store)
    t = store.read_latest("views", columns=["image"])
    store.close()
    images = [Image.open(io.BytesIO(b)).convert("RGB") for b in t.column("image").to_pylist()[: args.views]]
    enc = create_model("learned_encoder", get_profile("offline").learned_encoder)
    sizes = [int(b) for b in args.batches.split(",")]
    print(f"torch {torch.__version__}, {torch.get_num_threads()} threads, {len(images)} views, {enc.model_id}")
    enc.encode_image_patches(images[:8])  # warm-up
    times: dict[int, list[float]] = {b: [] for b in sizes}
    out: dict[int, np.ndarray] = {}
    for _ in range(args.repeats):
        for b in sizes:
            enc.batch_size = b
            t0 = time.perf_counter()
            emb, _patches = enc.encode_image_patches(images)
            times[b].append((time.perf_counter() - t0) / len(images))
            out[b] = emb
    first = statistics.median(times[sizes[0]])
    print(f"| batch | ms / view, median of {args.repeats} | ratio to batch {sizes[0]} | max abs diff of embeddings |")
    print("|---|---|---|---|")
    for b in sizes:
        med = statistics.median(times[b])
        diff = float(np.abs(out[b] - out[sizes[0]]).max())
        print(f"| {b} | {med * 1000:.1f} | {med / first:.2f} | {diff:.1e} |", flush=True)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
