"""Backgrounds for synthetic queries: solid colours, linear gradients, smooth colour noise, real-photo crops."""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np

BACKGROUND_KINDS = ("solid", "gradient", "noise", "photo")


def make_background(
    kind: str, width: int, height: int, rng: np.random.Generator, photos: list[Path] | None = None
) -> np.ndarray:
    """An HxWx3 uint8 background of ``kind`` drawn with ``rng``."""
    if kind == "solid":
        return np.broadcast_to(_colour(rng), (height, width, 3)).astype(np.uint8)
    if kind == "gradient":
        return _gradient(width, height, rng)
    if kind == "noise":
        return _noise(width, height, rng)
    if kind == "photo":
        if not photos:
            raise ValueError("photo backgrounds need at least one image (--photo-dir)")
        return _photo_crop(photos[int(rng.integers(len(photos)))], width, height, rng)
    raise ValueError(f"unknown background kind {kind!r}; choose from {', '.join(BACKGROUND_KINDS)}")


def _colour(rng: np.random.Generator) -> np.ndarray:
    return rng.integers(0, 256, size=3).astype(np.float64)


def _gradient(width: int, height: int, rng: np.random.Generator) -> np.ndarray:
    a, b = _colour(rng), _colour(rng)
    angle = rng.uniform(0, 2 * math.pi)
    ys, xs = np.mgrid[0:height, 0:width].astype(np.float64)
    t = xs * math.cos(angle) + ys * math.sin(angle)
    t = (t - t.min()) / max(np.ptp(t), 1e-9)
    return (a * (1 - t[..., None]) + b * t[..., None]).round().astype(np.uint8)


def _noise(width: int, height: int, rng: np.random.Generator) -> np.ndarray:
    from PIL import Image

    cells = int(rng.integers(4, 16))
    coarse = rng.integers(0, 256, size=(cells, max(2, cells * width // height), 3)).astype(np.uint8)
    smooth = np.asarray(Image.fromarray(coarse).resize((width, height), Image.BICUBIC), dtype=np.float64)
    grain = rng.normal(0.0, rng.uniform(2.0, 14.0), size=(height, width, 1))
    return np.clip(smooth + grain, 0, 255).astype(np.uint8)


def _photo_crop(path: Path, width: int, height: int, rng: np.random.Generator) -> np.ndarray:
    from PIL import Image

    with Image.open(path) as im:
        im = im.convert("RGB")
        w, h = im.size
        # the largest crop with the target aspect, scaled by 0.5..1, at a random place; random mirror
        aspect = width / height
        cw, ch = (w, w / aspect) if w / h < aspect else (h * aspect, h)
        s = rng.uniform(0.5, 1.0)
        cw, ch = cw * s, ch * s
        x0, y0 = rng.uniform(0, w - cw), rng.uniform(0, h - ch)
        crop = im.resize((width, height), Image.BILINEAR, box=(x0, y0, x0 + cw, y0 + ch))
        if rng.random() < 0.5:
            crop = crop.transpose(Image.FLIP_LEFT_RIGHT)
        return np.asarray(crop, dtype=np.uint8)
