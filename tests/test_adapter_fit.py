"""The query adapter's fit (pipeline/adapter/fit.py) on a synthetic metric problem: ROIs are a fixed
distortion of their model's views, which a plain cosine confuses and a fitted map undoes."""

from __future__ import annotations

import numpy as np
import pytest

from pipeline.adapter.fit import FitConfig, apply_adapter, fit_adapter, views_by_model


def unit(x):
    return x / np.linalg.norm(x, axis=-1, keepdims=True)


def problem(n_models=24, n_views=4, dim=16, per_model=6, seed=0):
    """Views, and probes made by a fixed linear distortion of a random view of their model plus noise."""
    rng = np.random.default_rng(seed)
    views = unit(rng.normal(size=(n_models * n_views, dim))).astype(np.float32)
    view_model = np.repeat(np.arange(n_models), n_views)
    distort = np.eye(dim) + 1.5 * rng.normal(size=(dim, dim)) / np.sqrt(dim)
    target = np.repeat(np.arange(n_models), per_model)
    src = views[target * n_views + rng.integers(n_views, size=len(target))]
    probes = unit(src @ distort + 0.05 * rng.normal(size=src.shape)).astype(np.float32)
    return views, view_model, probes, target


def top1(probes, target, views, view_model, matrix=None):
    q = probes if matrix is None else apply_adapter(probes, matrix)
    s = q @ views.T
    n = view_model.max() + 1
    best = np.stack([s[:, view_model == m].max(axis=1) for m in range(n)], axis=1)
    return float(np.mean(best.argmax(axis=1) == target))


@pytest.mark.parametrize(
    "cfg",
    [FitConfig(rank=8, steps=150), FitConfig(rank=8, steps=150, full_max_models=4, negatives=6, batch=64)],
)
def test_fit_undoes_a_distortion_on_probes_it_never_saw(cfg):
    views, view_model, probes, target = problem()
    train = np.arange(len(target)) % 6 < 4  # four probes per model to fit, two held out
    matrix = fit_adapter(probes[train], target[train], views, view_model, cfg)
    assert matrix.shape == (16, 16) and matrix.dtype == np.float32
    before = top1(probes[~train], target[~train], views, view_model)
    after = top1(probes[~train], target[~train], views, view_model, matrix)
    assert before < 0.6 and after >= before + 0.25, (before, after)


def test_fit_is_seeded():
    views, view_model, probes, target = problem(n_models=8)
    cfg = FitConfig(rank=4, steps=20)
    a = fit_adapter(probes, target, views, view_model, cfg)
    b = fit_adapter(probes, target, views, view_model, cfg)
    c = fit_adapter(probes, target, views, view_model, FitConfig(rank=4, steps=20, seed=1))
    np.testing.assert_array_equal(a, b)
    assert not np.allclose(a, c)


def test_models_with_fewer_views_are_padded_not_confused():
    views = unit(np.array([[1, 0, 0], [0, 1, 0], [0, 0, 1]], np.float32))
    V3, mask = views_by_model(views, np.array([0, 0, 1]), 2)
    assert V3.shape == (2, 2, 3) and mask.tolist() == [[True, True], [True, False]]


def test_apply_adapter_normalises():
    v = apply_adapter(np.array([[3.0, 4.0]], np.float32), np.eye(2, dtype=np.float32) * 2)
    np.testing.assert_allclose(v, [[0.6, 0.8]], rtol=1e-6)


def test_bad_inputs_are_refused():
    with pytest.raises(ValueError, match="at least two models"):
        fit_adapter(
            np.ones((1, 3), np.float32),
            np.array([0]),
            np.eye(3, dtype=np.float32)[:1],
            np.array([0]),
            FitConfig(),
        )
    with pytest.raises(ValueError, match="rank"):
        FitConfig(rank=0)
    with pytest.raises(ValueError, match="lam"):
        FitConfig(lam=-1)
