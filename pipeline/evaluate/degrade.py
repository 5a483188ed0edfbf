"""Camera and scene degradations for the harder synthetic set (``synth --hard``).

Applied to a composited query (object over its background) so that what a real photo does to an object
reaches the query: white balance, exposure, blur, sensor noise and JPEG compression, plus a partial
occluder in front of the object and a mask that is a few pixels too large (so background pixels reach the
encoders, as with any real segmenter). Every draw comes from the caller's random generator.
"""

from __future__ import annotations

import io
from dataclasses import dataclass

import numpy as np


@dataclass(frozen=True)
class DegradeConfig:
    """Ranges of each degradation (each drawn uniformly per query)."""

    white_balance: float = 0.25  # per-channel gain within 1 +- this (then renormalised to keep brightness)
    exposure: tuple[float, float] = (0.55, 1.4)  # global gain
    gamma: tuple[float, float] = (0.8, 1.25)
    blur_sigma: tuple[float, float] = (0.0, 1.6)  # Gaussian blur, pixels
    noise_sigma: tuple[float, float] = (2.0, 10.0)  # read noise, 8-bit levels
    shot_noise: tuple[float, float] = (0.0, 0.6)  # signal-dependent noise scale (sqrt(level) * this)
    jpeg_quality: tuple[int, int] = (35, 90)
    occlusion_prob: float = 0.5  # chance of a partial occluder
    occlusion_cover: tuple[float, float] = (0.1, 0.4)  # share of the object's box area it covers
    mask_dilate_px: tuple[int, int] = (0, 4)  # the query mask grows by this many pixels (negative: shrinks)
    box_jitter: float = 0.12  # the query box grows/shifts by up to this share of its size per side


def photometric(image: np.ndarray, rng: np.random.Generator, cfg: DegradeConfig) -> tuple[np.ndarray, dict]:
    """White balance, exposure, gamma, blur, noise and JPEG on an HxWx3 uint8 image."""
    from PIL import Image, ImageFilter

    x = image.astype(np.float32) / 255.0
    gains = 1.0 + rng.uniform(-cfg.white_balance, cfg.white_balance, size=3)
    gains /= gains.mean()
    exposure = float(rng.uniform(*cfg.exposure))
    gamma = float(rng.uniform(*cfg.gamma))
    x = np.clip(x * gains * exposure, 0.0, 1.0) ** gamma
    img = Image.fromarray((x * 255.0).round().astype(np.uint8))
    sigma = float(rng.uniform(*cfg.blur_sigma))
    if sigma > 0.3:
        img = img.filter(ImageFilter.GaussianBlur(sigma))
    y = np.asarray(img, dtype=np.float32)
    read, shot = float(rng.uniform(*cfg.noise_sigma)), float(rng.uniform(*cfg.shot_noise))
    y = y + rng.normal(0.0, 1.0, size=y.shape) * np.sqrt(read**2 + shot**2 * y)
    img = Image.fromarray(np.clip(y, 0, 255).round().astype(np.uint8))
    quality = int(rng.integers(cfg.jpeg_quality[0], cfg.jpeg_quality[1] + 1))
    buf = io.BytesIO()
    img.save(buf, format="JPEG", quality=quality)
    out = np.asarray(Image.open(io.BytesIO(buf.getvalue())).convert("RGB"), dtype=np.uint8)
    meta = {
        "wb_gains": [round(float(g), 3) for g in gains],
        "exposure": round(exposure, 3),
        "gamma": round(gamma, 3),
        "blur_sigma": round(sigma, 3),
        "noise_sigma": round(read, 2),
        "jpeg_quality": quality,
    }
    return out, meta


def occlude(
    image: np.ndarray,
    mask: np.ndarray,
    rng: np.random.Generator,
    cfg: DegradeConfig,
    texture: np.ndarray | None = None,
) -> tuple[np.ndarray, np.ndarray, float]:
    """Paste an occluder (an ellipse or a rectangle, filled with ``texture`` or a flat colour) over part
    of the object, from one side of its box; return the image, the visible mask and the hidden share."""
    ys, xs = np.nonzero(mask)
    x0, x1, y0, y1 = xs.min(), xs.max() + 1, ys.min(), ys.max() + 1
    bw, bh = x1 - x0, y1 - y0
    cover = float(rng.uniform(*cfg.occlusion_cover))
    side = int(rng.integers(4))  # the occluder enters from the left, right, top or bottom of the box
    frac = min(1.0, cover * float(rng.uniform(1.0, 1.6)))
    H, W = mask.shape
    occ = np.zeros((H, W), dtype=bool)
    gy, gx = np.mgrid[0:H, 0:W]
    if side in (0, 1):
        w = max(1, int(bw * frac))
        ox0 = x0 - w // 3 if side == 0 else x1 - w + w // 3
        oy0 = y0 + int(rng.uniform(-0.2, 0.4) * bh)
        region = (gx >= ox0) & (gx < ox0 + w) & (gy >= oy0) & (gy < oy0 + int(bh * rng.uniform(0.6, 1.2)))
    else:
        h = max(1, int(bh * frac))
        oy0 = y0 - h // 3 if side == 2 else y1 - h + h // 3
        ox0 = x0 + int(rng.uniform(-0.2, 0.4) * bw)
        region = (gy >= oy0) & (gy < oy0 + h) & (gx >= ox0) & (gx < ox0 + int(bw * rng.uniform(0.6, 1.2)))
    if rng.random() < 0.5:  # an ellipse inscribed in the region
        ry, rx = np.nonzero(region)
        if len(rx):
            cx, cy = (rx.min() + rx.max()) / 2, (ry.min() + ry.max()) / 2
            ax, ay = max((rx.max() - rx.min()) / 2, 1), max((ry.max() - ry.min()) / 2, 1)
            region &= ((gx - cx) / ax) ** 2 + ((gy - cy) / ay) ** 2 <= 1.0
    occ |= region
    out = image.copy()
    if texture is not None:
        out[occ] = texture[occ]
    else:
        out[occ] = rng.integers(0, 256, size=3).astype(np.uint8)
    visible = mask & ~occ
    hidden = 1.0 - float(visible.sum()) / max(float(mask.sum()), 1.0)
    return out, visible, hidden


def grow_mask(mask: np.ndarray, px: int) -> np.ndarray:
    """``mask`` dilated by ``px`` pixels (a segmenter's typical over-reach), or eroded by ``-px`` (its
    under-reach). An erosion that would empty the mask keeps it as it was."""
    if px == 0:
        return mask
    from scipy import ndimage

    if px > 0:
        return ndimage.binary_dilation(mask, iterations=int(px))
    shrunk = ndimage.binary_erosion(mask, iterations=int(-px))
    return shrunk if shrunk.any() else mask


def jitter_box(box: tuple[float, float, float, float], shape, rng: np.random.Generator, amount: float):
    """A looser, shifted box around ``box`` (as a detector would draw), clipped to the image."""
    x0, y0, x1, y1 = box
    bw, bh = x1 - x0, y1 - y0
    d = rng.uniform(-0.25 * amount, amount, size=4)  # mostly grows, sometimes cuts a little
    H, W = shape
    nx0, ny0 = max(0.0, x0 - d[0] * bw), max(0.0, y0 - d[1] * bh)
    nx1, ny1 = min(float(W), x1 + d[2] * bw), min(float(H), y1 + d[3] * bh)
    return (round(nx0), round(ny0), round(nx1), round(ny1))
