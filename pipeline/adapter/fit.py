"""Fit the query adapter: a low-rank linear map of the ROI's learned vector, ``A = I + U W``.

Trained by a softmax over the models' best-view cosines (the probe's own model against the others,
temperature :data:`FitConfig.temperature`), with Adam and a penalty ``lam * |U W|^2`` that keeps it near the
identity. The stored views are not touched (no re-embedding), so the map only moves the query side. Up to
``full_max_models`` models every model competes in every step; past it each probe competes with its own
``negatives`` closest models by the plain cosine (found once, in chunks), so a step costs the same at any
library size. Mini-batches of ``batch`` probes; every draw is seeded. Choice of rank and ``lam``:
docs/results.md, section 10.2 (left-out synthetic sets, never the photos).

Why hand-written: a few dozen lines of PyTorch (already a dependency for the encoders); no library offers a
listwise, max-over-views metric fit of this shape.
"""

from __future__ import annotations

from dataclasses import asdict, dataclass

import numpy as np


@dataclass(frozen=True)
class FitConfig:
    rank: int = 32
    lam: float = 0.01
    steps: int = 300
    lr: float = 3e-3
    temperature: float = 0.03
    batch: int = 512  # probes per step
    full_max_models: int = 1024  # past this, sampled negatives
    negatives: int = 63  # closest other models per probe (sampled-negative mode)
    seed: int = 0

    def __post_init__(self) -> None:
        if self.rank < 1 or self.steps < 1 or self.batch < 1 or self.negatives < 1:
            raise ValueError("adapter rank, steps, batch and negatives must be >= 1")
        if self.lam < 0 or self.lr <= 0 or self.temperature <= 0:
            raise ValueError("adapter lam must be >= 0, lr and temperature > 0")

    def describe(self) -> dict:
        return asdict(self)


def views_by_model(views: np.ndarray, view_model: np.ndarray, n_models: int):
    """(models, most views, dim) float32 tensor of L2-normalised views, and its (models, most views) mask of
    real views (models with fewer views are padded)."""
    import torch

    counts = np.bincount(view_model, minlength=n_models)
    most = max(int(counts.max()), 1)
    order = np.argsort(view_model, kind="stable")
    slot = np.arange(len(order)) - np.repeat(np.cumsum(counts) - counts, counts)
    V3 = np.zeros((n_models, most, views.shape[1]), np.float32)
    mask = np.zeros((n_models, most), bool)
    V3[view_model[order], slot] = views[order]
    mask[view_model[order], slot] = True
    return torch.as_tensor(V3), torch.as_tensor(mask)


def best_view_scores(q, V3, mask, models=None):
    """Each query's best-view cosine with each model (``models``: (b, m) indices per query, else all)."""
    import torch

    if models is None:
        s = torch.einsum("bd,nvd->bnv", q, V3)
        return s.masked_fill(~mask[None], -2.0).max(-1).values
    s = torch.einsum("bd,bmvd->bmv", q, V3[models])
    return s.masked_fill(~mask[models], -2.0).max(-1).values


def hard_negatives(probes: np.ndarray, target: np.ndarray, V3, mask, k: int, chunk: int = 256) -> np.ndarray:
    """(probes, k + 1) model indices: the probe's own model first, then its ``k`` closest other models by the
    plain best-view cosine."""
    import torch

    out = np.empty((len(probes), k + 1), np.int64)
    with torch.no_grad():
        for a in range(0, len(probes), chunk):
            s = best_view_scores(torch.as_tensor(probes[a : a + chunk]), V3, mask)
            t = torch.as_tensor(target[a : a + chunk])
            s[torch.arange(len(t)), t] = -9.0
            out[a : a + chunk, 0] = target[a : a + chunk]
            out[a : a + chunk, 1:] = torch.topk(s, k, dim=1).indices.numpy()
    return out


def fit_adapter(
    probes: np.ndarray, target: np.ndarray, views: np.ndarray, view_model: np.ndarray, cfg: FitConfig
) -> np.ndarray:
    """The (dim, dim) float32 map ``I + U W`` fitted on L2-normalised ``probes`` whose model is ``target``
    (indices into the models of ``view_model``, which numbers the L2-normalised ``views`` by model)."""
    import torch

    probes = np.ascontiguousarray(probes, np.float32)
    target = np.asarray(target, np.int64)
    n_models = int(max(view_model.max(), target.max())) + 1
    dim = probes.shape[1]
    if len(probes) == 0 or n_models < 2:
        raise ValueError("an adapter needs probes of at least two models")
    V3, mask = views_by_model(np.asarray(views, np.float32), np.asarray(view_model, np.int64), n_models)
    sampled = n_models > cfg.full_max_models
    cands = hard_negatives(probes, target, V3, mask, min(cfg.negatives, n_models - 1)) if sampled else None
    g = torch.Generator().manual_seed(cfg.seed)
    rng = np.random.default_rng(cfg.seed)
    U = torch.zeros(dim, cfg.rank, requires_grad=True)
    W = (0.01 * torch.randn(cfg.rank, dim, generator=g)).requires_grad_()
    opt = torch.optim.Adam([U, W], lr=cfg.lr)
    P, T = torch.as_tensor(probes), torch.as_tensor(target)
    eye = torch.eye(dim)
    order = rng.permutation(len(probes))
    at = 0
    for _ in range(cfg.steps):
        if len(probes) <= cfg.batch:
            idx = np.arange(len(probes))
        else:
            if at + cfg.batch > len(order):
                order, at = rng.permutation(len(probes)), 0
            idx, at = order[at : at + cfg.batch], at + cfg.batch
        q = torch.nn.functional.normalize(P[idx] @ (eye + U @ W), dim=1)
        if sampled:
            s = best_view_scores(q, V3, mask, torch.as_tensor(cands[idx]))
            labels = torch.zeros(len(idx), dtype=torch.int64)  # the own model is column 0
        else:
            s = best_view_scores(q, V3, mask)
            labels = T[idx]
        loss = torch.nn.functional.cross_entropy(s / cfg.temperature, labels) + cfg.lam * (U @ W).pow(2).sum()
        opt.zero_grad()
        loss.backward()
        opt.step()
    return (eye + U @ W).detach().numpy().astype(np.float32)


def apply_adapter(vector: np.ndarray, matrix: np.ndarray) -> np.ndarray:
    """The adapted, L2-normalised ROI vector(s)."""
    v = np.asarray(vector, np.float32) @ matrix
    norm = np.linalg.norm(v, axis=-1, keepdims=True)
    return (v / np.maximum(norm, 1e-12)).astype(np.float32)
