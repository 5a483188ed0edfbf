"""The harder synthetic set's degradations: deterministic, bounded, and they change what they should."""

from __future__ import annotations

import numpy as np

from pipeline.evaluate.degrade import DegradeConfig, grow_mask, jitter_box, occlude, photometric


def scene():
    rng = np.random.default_rng(0)
    img = rng.integers(0, 255, (120, 160, 3), dtype=np.uint8)
    mask = np.zeros((120, 160), bool)
    mask[30:90, 40:120] = True
    return img, mask


def test_photometric_is_seeded_and_changes_the_image():
    img, _ = scene()
    a, meta = photometric(img, np.random.default_rng(1), DegradeConfig())
    b, _ = photometric(img, np.random.default_rng(1), DegradeConfig())
    assert a.shape == img.shape and a.dtype == np.uint8 and np.array_equal(a, b)
    assert np.abs(a.astype(int) - img).mean() > 3
    assert 35 <= meta["jpeg_quality"] <= 90 and abs(sum(meta["wb_gains"]) - 3) < 1e-2


def test_occluder_hides_part_of_the_object_only():
    img, mask = scene()
    cfg = DegradeConfig(occlusion_cover=(0.3, 0.3))
    out, visible, hidden = occlude(img, mask, np.random.default_rng(3), cfg, texture=np.zeros_like(img))
    assert 0.05 < hidden < 0.9 and not (visible & ~mask).any()
    changed = (out != img).any(axis=2)
    assert changed.any() and not (changed & visible).any()


def test_loose_mask_and_box():
    _, mask = scene()
    assert grow_mask(mask, 3).sum() > mask.sum() and grow_mask(mask, 0) is mask
    shrunk = grow_mask(mask, -2)
    assert shrunk.sum() == 56 * 76 and not (shrunk & ~mask).any()  # 2 px off every side
    assert grow_mask(mask, -40) is mask  # an erosion that would empty the mask keeps it
    x0, y0, x1, y1 = jitter_box((40, 30, 120, 90), mask.shape, np.random.default_rng(0), 0.12)
    assert 0 <= x0 <= 50 and 0 <= y0 <= 40 and 110 <= x1 <= 160 and 80 <= y1 <= 120
