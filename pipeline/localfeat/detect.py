"""Detect keypoints and descriptors on an object-on-gray image (a rendered view or a query ROI).

The object is cropped to its box and resized so that its longer side is ``work_side`` pixels: views and ROIs
are then compared at one nominal scale, and keypoint coordinates live in that working frame. Detection is
restricted to the object (its mask, slightly dilated so silhouette corners count).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from PIL import Image

from pipeline.localfeat.config import FeatureConfig

_MASK_DILATE_PX = 3


@dataclass(frozen=True)
class Features:
    """Keypoints (n, 2) float32 in working-frame pixels and descriptors (n, d) uint8."""

    xy: np.ndarray
    desc: np.ndarray

    def __len__(self) -> int:
        return int(self.xy.shape[0])


def _empty(dim: int) -> Features:
    return Features(np.zeros((0, 2), np.float32), np.zeros((0, dim), np.uint8))


def descriptor_dim(detector: str) -> int:
    return {"sift": 128, "orb": 32}.get(detector, 0)


def _make(detector: str, n: int):
    import cv2

    if detector == "sift":
        return cv2.SIFT_create(nfeatures=int(n))
    if detector == "orb":
        return cv2.ORB_create(nfeatures=int(n), edgeThreshold=15, patchSize=15)
    raise ValueError(f"no detector {detector!r}")


def detect(
    image: Image.Image,
    cfg: FeatureConfig,
    mask: np.ndarray | None = None,
    max_keypoints: int | None = None,
) -> Features:
    """Keypoints of the object in ``image``; ``mask`` (bool, image size) defaults to the non-gray pixels."""
    import cv2

    from pipeline.models.offline_imageops import bounding_box, clean_mask, foreground_mask, to_rgb

    dim = descriptor_dim(cfg.detector)
    image = to_rgb(image)
    if mask is None:
        mask = clean_mask(foreground_mask(image))
    box = bounding_box(mask)
    if box is None:
        return _empty(dim)
    x0, y0, x1, y1 = box
    scale = cfg.work_side / max(x1 - x0, y1 - y0)
    size = (max(1, round((x1 - x0) * scale)), max(1, round((y1 - y0) * scale)))
    gray = np.asarray(image.convert("L").resize(size, Image.BILINEAR, box=box), dtype=np.uint8)
    m = Image.fromarray(mask.astype(np.uint8) * 255).resize(size, Image.NEAREST, box=box)
    m = cv2.dilate(np.asarray(m), np.ones((2 * _MASK_DILATE_PX + 1,) * 2, np.uint8))
    n = int(max_keypoints or cfg.max_keypoints)
    kps, desc = _make(cfg.detector, n).detectAndCompute(gray, m)
    if desc is None or not kps:
        return _empty(dim)
    order = np.argsort([-k.response for k in kps], kind="stable")[:n]
    xy = np.asarray([kps[i].pt for i in order], np.float32).reshape(-1, 2)
    d = np.clip(np.rint(desc[order]), 0, 255).astype(np.uint8)  # SIFT values are integers in 0..255
    return Features(xy, d)


def to_row(f: Features) -> dict:
    """Columns of a ``view_features`` row (keypoints flattened x0, y0, x1, y1, ...; descriptors as bytes)."""
    return {
        "n_keypoints": len(f),
        "keypoints": f.xy.reshape(-1).astype(np.float32).tolist(),
        "descriptor_dim": int(f.desc.shape[1]) if f.desc.ndim == 2 else 0,
        "descriptors": np.ascontiguousarray(f.desc, np.uint8).tobytes(),
    }


def from_row(n: int, keypoints, dim: int, descriptors: bytes) -> Features:
    """Inverse of :func:`to_row`."""
    xy = np.asarray(keypoints, np.float32).reshape(int(n), 2)
    desc = (
        np.frombuffer(descriptors or b"", np.uint8).reshape(int(n), int(dim))
        if n
        else np.zeros((0, dim), np.uint8)
    )
    return Features(xy, desc)
