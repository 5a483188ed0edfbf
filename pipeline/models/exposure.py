"""Exposure normalisation of an object on a plain background, before a learned encoder sees it.

Photos of an object and renders of its mesh differ most in brightness: the five PoseCNN photos' objects have
a median foreground luminance of 114 (of 255), the renderer's views 72 and its synthetic queries 64-68
(docs/results.md, section 7.4). :func:`normalise_exposure` scales the foreground's RGB (every pixel off the
background colour) so that its median luminance lands on one fixed target, applied alike to the stored views
and to the query ROI: the learned cosine then compares objects at one exposure, whatever the camera or the
renderer's lights did. Where the image holds almost no foreground it is returned unchanged.

Hand-written on OpenCV's array operations because it is a scale on a mask the renderer and the ROI step
already define (the background colour); OpenCV and scikit-image offer histogram matching and gamma, which
either need a reference image per object or change the tone curve rather than the exposure. About 4 ms for
a 512 px view (10 ms in plain NumPy; docs/performance.md, "Exposure").
"""

from __future__ import annotations

import cv2
import numpy as np
from PIL import Image

#: Rec. 601 luma weights (sRGB values, as PIL's ``L`` mode)
LUMA = np.array([0.299, 0.587, 0.114], np.float32)
#: a pixel is foreground when its R + G + B differ from the background colour's by more than this
FOREGROUND_TOLERANCE = 6
#: fewer foreground pixels than this: the image is returned as it is
MIN_FOREGROUND = 16
_SUM3 = np.ones((1, 3), np.float32)


def foreground_mask(a: np.ndarray, fill: tuple[int, int, int]) -> np.ndarray:
    """Boolean HxW mask of the pixels of uint8 RGB array ``a`` whose R + G + B differ from ``fill``'s by more
    than :data:`FOREGROUND_TOLERANCE` (the object, as the exposure step sees it)."""
    # R + G + B of |pixel - fill|, saturated at 255 by OpenCV: the same test against the small tolerance
    off = cv2.transform(cv2.absdiff(a, np.full_like(a, fill)), _SUM3)
    return off > FOREGROUND_TOLERANCE


def luminance(pixels: np.ndarray) -> np.ndarray:
    """Rec. 601 luma (float32) of an ...x3 array of RGB values.

    Element-wise multiplies and adds rather than a matrix product: a BLAS product's kernel (and so its last
    bit) differs between CPUs, and a median one bit either side of a level can move the scaled levels by one
    wherever the scale lands on an exact boundary; these ufuncs round the same everywhere."""
    p = pixels.astype(np.float32, copy=False)
    return p[..., 0] * LUMA[0] + p[..., 1] * LUMA[1] + p[..., 2] * LUMA[2]


def _foreground(a: np.ndarray, fill: tuple[int, int, int]) -> tuple[np.ndarray, float] | None:
    """The foreground mask of RGB array ``a`` and its median luminance; ``None`` with too little of it."""
    fg = foreground_mask(a, fill)
    if int(np.count_nonzero(fg)) < MIN_FOREGROUND:
        return None
    return fg, float(np.median(luminance(a[fg])))


def foreground_luminance(image: Image.Image, fill: tuple[int, int, int]) -> float | None:
    """The median luminance (0-255) of ``image``'s pixels off ``fill``; ``None`` when there are almost none."""
    found = _foreground(np.ascontiguousarray(np.asarray(image.convert("RGB"))), fill)
    return None if found is None else found[1]


def normalise_exposure(image: Image.Image, target: float, fill: tuple[int, int, int]) -> Image.Image:
    """``image`` (RGB) with its foreground (pixels off ``fill``) scaled so that their median luminance is
    ``target`` (0-255), clipped to the 8-bit range; the background stays ``fill``."""
    a = np.ascontiguousarray(np.asarray(image.convert("RGB")))
    found = _foreground(a, fill)
    if found is None:
        return image
    fg, median = found
    # the scale as a lookup table over the 256 levels (float32, as scaling the pixels would compute it)
    scale = float(target) / max(median, 1.0)
    lut = np.clip(np.arange(256, dtype=np.float32) * scale, 0.0, 255.0).astype(np.uint8)
    out = a.copy()
    cv2.copyTo(cv2.LUT(a, lut), fg.astype(np.uint8), out)
    return Image.fromarray(out)
