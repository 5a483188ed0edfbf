"""Local features: detection, storage round trip, matching with a RANSAC inlier count."""

from __future__ import annotations

import numpy as np
import pytest
from PIL import Image

from pipeline.localfeat import FeatureConfig, detect, from_row, to_row
from pipeline.localfeat.config import VerifyConfig
from pipeline.localfeat.match import ViewBank, count_inliers, one_to_one

GRAY = 205


def textured(seed: int, size: int = 200) -> Image.Image:
    """A textured square object (random blocks and discs) on the gray background, with a margin."""
    import cv2

    rng = np.random.default_rng(seed)
    img = np.full((size + 80, size + 80, 3), GRAY, np.uint8)
    obj = np.zeros((size, size, 3), np.uint8)
    for _ in range(60):
        x, y = rng.integers(0, size, 2)
        c = tuple(int(v) for v in rng.integers(0, 255, 3))
        if rng.random() < 0.5:
            cv2.rectangle(
                obj, (int(x), int(y)), (int(x + rng.integers(5, 30)), int(y + rng.integers(5, 30))), c, -1
            )
        else:
            cv2.circle(obj, (int(x), int(y)), int(rng.integers(3, 15)), c, -1)
    img[40 : 40 + size, 40 : 40 + size] = obj
    return Image.fromarray(img)


def warped(image: Image.Image, angle: float = 12.0, scale: float = 0.8) -> Image.Image:
    import cv2

    a = np.asarray(image)
    h, w = a.shape[:2]
    m = cv2.getRotationMatrix2D((w / 2, h / 2), angle, scale)
    return Image.fromarray(cv2.warpAffine(a, m, (w, h), borderValue=(GRAY, GRAY, GRAY)))


CFG = FeatureConfig()


def test_detect_finds_keypoints_on_the_object_only():
    f = detect(textured(0), CFG)
    assert 50 <= len(f) <= CFG.max_keypoints
    assert f.desc.dtype == np.uint8 and f.desc.shape == (len(f), 128)
    # coordinates are in the working frame: the object's box scaled to work_side
    assert f.xy.min() >= -1 and f.xy.max() <= CFG.work_side + 1
    blank = detect(Image.new("RGB", (100, 100), (GRAY,) * 3), CFG)
    assert len(blank) == 0


def test_row_round_trip():
    f = detect(textured(1), CFG)
    row = to_row(f)
    assert row["n_keypoints"] == len(f) and len(row["descriptors"]) == len(f) * 128
    g = from_row(row["n_keypoints"], row["keypoints"], row["descriptor_dim"], row["descriptors"])
    assert np.array_equal(g.desc, f.desc) and np.allclose(g.xy, f.xy)


@pytest.mark.parametrize("method", ["homography", "affine"])
def test_inliers_separate_the_same_object_from_another(method):
    vc = VerifyConfig(method=method)
    views = [detect(textured(s), CFG) for s in (0, 1, 2)]
    bank = ViewBank.build(views, "sift", vc.view_keypoints)
    roi = detect(warped(textured(0)), CFG, max_keypoints=vc.roi_keypoints)
    inliers = count_inliers(roi, bank, vc, CFG)
    assert inliers[0] >= 25
    assert inliers[1] <= 8 and inliers[2] <= 8


def test_orb_detector_and_concat():
    cfg = FeatureConfig(detector="orb")
    views = [detect(textured(s), cfg) for s in (0, 1)]
    assert views[0].desc.shape[1] == 32
    vc = VerifyConfig()
    bank = ViewBank.concat([ViewBank.build([v], "orb") for v in views])
    assert bank.desc.shape[0] == 2
    inliers = count_inliers(detect(warped(textured(0)), cfg, max_keypoints=384), bank, vc, cfg)
    assert inliers[0] > inliers[1]


def test_one_to_one_keeps_the_best_match_per_view_keypoint():
    qi = np.array([0, 1, 2, 3])
    ti = np.array([5, 5, 7, 5])
    sim = np.array([0.5, 0.9, 0.8, 0.7])
    assert sorted(qi[one_to_one(qi, ti, sim)].tolist()) == [1, 2]


def test_config_validation():
    with pytest.raises(ValueError, match="unknown local-feature detector"):
        FeatureConfig(detector="surf")
    with pytest.raises(ValueError, match="max_keypoints"):
        FeatureConfig(max_keypoints=2)
    a, b = FeatureConfig().fingerprint("r1"), FeatureConfig(max_keypoints=128).fingerprint("r1")
    assert a != b and a != FeatureConfig().fingerprint("r2")
    vc = VerifyConfig(weight=0.3, inlier_floor=6, inlier_cap=40)
    assert vc.bonus([0, 6, 40, 100]).tolist() == pytest.approx([0, 0, 0.3, 0.3])
