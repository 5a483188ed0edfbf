"""Small mask helpers shared by the box segmenters (:mod:`pipeline.query.roi`, :mod:`pipeline.query.saliency`)."""

from __future__ import annotations

import numpy as np


def largest_blob(fg: np.ndarray) -> np.ndarray | None:
    """The largest connected part of a foreground mask after a small opening, holes filled (None if empty)."""
    from scipy import ndimage

    fg = ndimage.binary_opening(fg, iterations=1)
    labels, n = ndimage.label(fg)
    if n == 0:
        return None
    sizes = ndimage.sum(fg, labels, index=np.arange(1, n + 1))
    return ndimage.binary_fill_holes(labels == (int(np.argmax(sizes)) + 1))


def plausible(full: np.ndarray, box, min_share: float, max_share: float) -> np.ndarray | None:
    """``full`` cut to ``box``, or ``None`` when it covers less than ``min_share`` or more than ``max_share``
    of the box (a sliver, or nothing split from the box)."""
    x0, y0, x1, y1 = box
    inside = np.zeros_like(full)
    inside[y0:y1, x0:x1] = True
    full = full & inside
    share = float(full[y0:y1, x0:x1].mean()) if (x1 > x0 and y1 > y0) else 0.0
    if not min_share <= share <= max_share:
        return None
    return full
