"""Stage 2, the rerank: the ROI's view-encoder vector against the candidates' view embeddings (torch).

Views are held once as a dense ``(n_views, dim)`` tensor on the device (CUDA when available) plus a
``(n_meshes, max_views)`` index with -1 for missing views, so scoring C candidates is one gather and one
batched matrix-vector product: score = max over the candidate's views, best view = its argmax. On the CPU
the same arrays are NumPy (no torch import: see :mod:`pipeline.device`).
"""

from __future__ import annotations

import time
from dataclasses import dataclass

import numpy as np
import pyarrow as pa


@dataclass
class Stage2Result:
    scores: np.ndarray  # float32 per requested mesh; -inf when the mesh has no view embeddings
    best_view: np.ndarray  # int16 view_index per requested mesh; -1 when none
    seconds: float
    view_scores: np.ndarray | None = None  # (meshes, max_views) float32 per-view cosine, -inf = no view
    view_ids: np.ndarray | None = None  # (meshes, max_views) int16 view_index, -1 = no view


def pick_device(device: str | None = None) -> str:
    from pipeline.device import resolve_device

    return resolve_device(device)


class ViewReranker:
    """All active meshes' view embeddings, on ``device``."""

    def __init__(self, views: pa.Table, n_meshes: int, device: str | None = None) -> None:
        self.device = pick_device(device)
        self.numpy = self.device == "cpu"
        self.n_meshes = n_meshes
        mesh_idx = (
            views.column("mesh_idx").to_numpy().astype(np.int64) if views.num_rows else np.zeros(0, np.int64)
        )
        view_index = (
            views.column("view_index").to_numpy().astype(np.int16)
            if views.num_rows
            else np.zeros(0, np.int16)
        )
        if views.num_rows:
            flat = views.column("embedding").combine_chunks().flatten().to_numpy(zero_copy_only=False)
            emb = np.asarray(flat, dtype=np.float32).reshape(views.num_rows, -1)
        else:
            emb = np.zeros((0, 1), np.float32)
        self.dim = emb.shape[1]
        counts = np.bincount(mesh_idx, minlength=n_meshes) if len(mesh_idx) else np.zeros(n_meshes, np.int64)
        max_views = int(counts.max()) if n_meshes and len(mesh_idx) else 1
        order = np.argsort(mesh_idx, kind="stable")
        starts = np.zeros(n_meshes + 1, np.int64)
        starts[1:] = np.cumsum(counts)
        slot = np.arange(len(mesh_idx)) - starts[mesh_idx[order]]
        pad = np.full((n_meshes, max(max_views, 1)), -1, np.int64)
        pad[mesh_idx[order], slot] = order
        self.view_index = view_index
        if self.numpy:
            self._pad, self._valid = pad, pad >= 0
            self._emb = np.array(emb, dtype=np.float32)  # a copy: the cache is memory-mapped
            self._view_index_t = view_index.astype(np.int64)
            return
        import torch

        self.device = torch.device(self.device)
        self._pad = torch.from_numpy(pad).to(self.device)
        self._valid = self._pad >= 0
        self._emb = torch.tensor(
            emb, dtype=torch.float32, device=self.device
        )  # copies (the cache is mmapped)
        self._view_index_t = torch.from_numpy(view_index.astype(np.int64)).to(self.device)

    @property
    def has_views(self) -> np.ndarray:
        if self.numpy:
            return self._valid.any(axis=1)
        return self._valid.any(dim=1).cpu().numpy()

    def score(
        self, query: np.ndarray, mesh_idx: np.ndarray | None = None, per_view: bool = False
    ) -> Stage2Result:
        """Scores of ``mesh_idx`` (all meshes when ``None``), in the given order; ``per_view`` also returns
        every view's score (the same matrix the max is taken over: no extra work but the copy)."""
        t0 = time.perf_counter()
        n = self.n_meshes if mesh_idx is None else len(mesh_idx)
        if self._emb.shape[0] == 0 or n == 0:
            empty = np.zeros((n, 0), np.float32) if per_view else None
            return Stage2Result(
                np.full(n, -np.inf, np.float32),
                np.full(n, -1, np.int16),
                0.0,
                empty,
                None if empty is None else empty.astype(np.int16),
            )
        if self.numpy:
            return self._score_numpy(query, mesh_idx, per_view, t0)
        import torch

        q = torch.from_numpy(np.asarray(query, dtype=np.float32).reshape(-1)).to(self.device)
        if q.shape[0] != self.dim:
            raise ValueError(f"query vector has {q.shape[0]} dims, views have {self.dim}")
        with torch.inference_mode():
            if mesh_idx is None:
                pad, valid = self._pad, self._valid
                every_view = self._emb @ q  # every view once, then gathered per mesh
                s = every_view[pad.clamp(min=0)]
            else:
                idx = torch.from_numpy(np.asarray(mesh_idx, dtype=np.int64)).to(self.device)
                pad, valid = self._pad[idx], self._valid[idx]
                s = self._emb[pad.clamp(min=0)] @ q  # (C, V, d) @ (d,) -> (C, V)
            s = s.masked_fill(~valid, float("-inf"))
            best, arg = s.max(dim=1)
            rows = pad.gather(1, arg[:, None])[:, 0]
            view = torch.where(rows >= 0, self._view_index_t[rows.clamp(min=0)], torch.full_like(rows, -1))
            scores = best.float().cpu().numpy()
            views = view.cpu().numpy().astype(np.int16)
            if per_view:
                ids = torch.where(valid, self._view_index_t[pad.clamp(min=0)], torch.full_like(pad, -1))
                all_scores = s.float().cpu().numpy()
                all_ids = ids.cpu().numpy().astype(np.int16)
        if not per_view:
            return Stage2Result(scores, views, time.perf_counter() - t0)
        return Stage2Result(scores, views, time.perf_counter() - t0, all_scores, all_ids)

    def _score_numpy(
        self, query: np.ndarray, mesh_idx: np.ndarray | None, per_view: bool, t0: float
    ) -> Stage2Result:
        """:meth:`score` in NumPy (the CPU path)."""
        q = np.asarray(query, dtype=np.float32).reshape(-1)
        if q.shape[0] != self.dim:
            raise ValueError(f"query vector has {q.shape[0]} dims, views have {self.dim}")
        if mesh_idx is None:
            pad, valid = self._pad, self._valid
            s = (self._emb @ q)[np.maximum(pad, 0)]  # every view once, then gathered per mesh
        else:
            idx = np.asarray(mesh_idx, dtype=np.int64)
            pad, valid = self._pad[idx], self._valid[idx]
            s = self._emb[np.maximum(pad, 0)] @ q  # (C, V, d) @ (d,) -> (C, V)
        s = np.where(valid, s, np.float32(-np.inf)).astype(np.float32)
        arg = s.argmax(axis=1)
        best = s[np.arange(len(s)), arg].astype(np.float32)
        rows = pad[np.arange(len(pad)), arg]
        view = np.where(rows >= 0, self._view_index_t[np.maximum(rows, 0)], -1).astype(np.int16)
        if not per_view:
            return Stage2Result(best, view, time.perf_counter() - t0)
        ids = np.where(valid, self._view_index_t[np.maximum(pad, 0)], -1).astype(np.int16)
        return Stage2Result(best, view, time.perf_counter() - t0, s.copy(), ids)
