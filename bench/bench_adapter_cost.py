"""What a per-store query adapter (docs/results.md, section 10.2) would add to onboarding, measured.

    python bench/bench_adapter_cost.py --store STORE [--per-mesh 3] [--onboard LIBRARY]

Times, on the store's meshes: rendering ``--per-mesh`` synthetic queries per model (``synth --hard
--mask-grow 0,0`` over solid, gradient and noise backgrounds), making their ROIs and embedding them with the
store's learned encoder (the query path's ``make_roi`` and ``encode_roi``), and training the adapter on them
and the stored view vectors (``bench/learned_adapter.py``'s ``train``, lam 0.01, rank 32). With ``--onboard``
the library is also onboarded into a fresh temporary store in the same run, as the reference the other
phases are compared with. Prints a table: seconds, seconds per model, share of the onboarding time.
"""

from __future__ import annotations

import argparse
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))
sys.path.insert(0, str(REPO / "bench"))


def synth_queries(store: str, out: Path, per_mesh: int) -> list:
    from dataclasses import replace

    from pipeline.evaluate.degrade import DegradeConfig
    from pipeline.evaluate.library import read_store_meshes
    from pipeline.evaluate.synth import SynthConfig, generate
    from pipeline.evaluate.synth_cli import store_render_config

    cfg = SynthConfig(
        per_mesh=per_mesh,
        seed=23,
        backgrounds=("solid", "gradient", "noise"),
        degrade=DegradeConfig(mask_dilate_px=(0, 0)),
    )
    cfg = replace(cfg, onboarding=store_render_config(store) or cfg.onboarding)
    return generate(read_store_meshes(store), out, cfg, progress=False)


def roi_vectors(store: str, queries: list) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """(ROI vectors, right model index, stored view vectors, their model index)."""
    from pipeline.query import Retriever

    with Retriever.open(store, profile="offline") as r:
        enc = r.model("learned_encoder")
        at = {m: i for i, m in enumerate(r.mesh_ids)}
        rois = [r.make_roi(q.image, q.prompt, box=q.box, mask=q.mask).image for q in queries]
        R = enc.encode_roi(rois)
        t = np.array([at[q.expected[0]] for q in queries])
        views = r.tables.learned_views
        V = np.array(views.column("embedding").to_pylist(), np.float32)
        vm = np.array(views.column("mesh_idx").to_pylist())
    return R, t, V, vm


def main() -> int:
    import learned_adapter as la
    import torch

    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--store", required=True)
    p.add_argument("--per-mesh", type=int, default=3)
    p.add_argument("--onboard", help="a library folder to onboard into a fresh store, as the reference")
    args = p.parse_args()
    torch.set_num_threads(2)
    rows: list[tuple[str, float]] = []
    with tempfile.TemporaryDirectory() as tmp:
        if args.onboard:
            t0 = time.perf_counter()
            cmd = [
                sys.executable,
                "-m",
                "pipeline.onboard",
                args.onboard,
                "--store",
                f"{tmp}/store",
                "--no-progress",
            ]
            subprocess.run(cmd, check=True, stdout=subprocess.DEVNULL)
            rows.append(("onboarding (reference)", time.perf_counter() - t0))
        t0 = time.perf_counter()
        queries = synth_queries(args.store, Path(tmp) / "synth", args.per_mesh)
        rows.append((f"render {args.per_mesh} synthetic queries per model", time.perf_counter() - t0))
        t0 = time.perf_counter()
        R, t, V, vm = roi_vectors(args.store, queries)
        rows.append(("ROIs and their learned vectors (incl. model load)", time.perf_counter() - t0))
        t0 = time.perf_counter()
        D = {"V": V, "vm": vm}
        V3 = la.views_by_model(D)
        la.train(R, t, np.ones(V3.shape[0], bool), V3, 0.01, 32)
        rows.append(("train the adapter (300 steps, full softmax)", time.perf_counter() - t0))
    n = len(set(vm.tolist()))
    ref = rows[0][1] if args.onboard else None
    print(f"{n} models, {len(queries)} synthetic queries")
    print("| phase | s | s per model | share of onboarding |")
    print("|---|---|---|---|")
    for name, s in rows:
        share = f"{s / ref:.2f}" if ref else "-"
        print(f"| {name} | {s:.1f} | {s / n:.2f} | {share} |")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
