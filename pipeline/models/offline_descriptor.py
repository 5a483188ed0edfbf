"""A deterministic, weight-free image descriptor for the ``offline`` profile's stage 2 (views vs ROI).

The object (foreground on the gray background) is cropped to its box and fitted into a square, so the
descriptor does not depend on scale or on how tightly the input was cropped. It concatenates weighted,
individually L2-normalised blocks:

* a soft-binned joint Lab colour histogram of the object's pixels (Hellinger: square-rooted),
* a spatial colour layout (mean Lab colour and coverage of each cell of a 4x4 grid),
* a HOG-like gradient-orientation histogram over a 4x4 grid of cells (square-rooted),
* silhouette shape features: aspect ratio, fill ratio, solidity, elongation, a centroid-distance profile and
  Hu moments, each scalar encoded as a soft one-hot over fixed bins so the cosine behaves like a kernel.
"""

from __future__ import annotations

import numpy as np
from PIL import Image

from pipeline.models.offline_imageops import BACKGROUND_TOLERANCE, object_crop, rgb_to_lab, silhouette
from pipeline.models.protocols import l2_normalise

DEFAULT_MODEL_ID = "oscar-color-gradient-descriptor-v1"

#: side of the square the object is fitted into
SIZE = 64
#: Lab histogram bins (L, a, b) and ranges
LAB_BINS = (5, 7, 7)
LAB_RANGES = ((0.0, 100.0), (-70.0, 70.0), (-70.0, 70.0))
#: spatial layout grid and HOG grid / orientations
LAYOUT_GRID = 4
HOG_GRID = 4
HOG_ORIENTATIONS = 9
#: soft one-hot encodings of the silhouette scalars: (low, high, bins)
_SHAPE_ENCODINGS = {
    "log_aspect": (-1.6, 1.6, 13),
    "extent": (0.2, 1.0, 9),
    "solidity": (0.4, 1.0, 7),
    "log_elongation": (0.0, 1.6, 9),
    "hu1": (-0.85, -0.3, 9),  # log10 of the first Hu moment (disc: -0.80)
}
_RADIAL_SECTORS = 16

#: block weights (each block is unit-norm before weighting)
W_COLOUR = 1.0
W_LAYOUT = 0.7
W_HOG = 0.8
W_SHAPE = 0.6

_COLOUR_DIM = int(np.prod(LAB_BINS))
_LAYOUT_DIM = LAYOUT_GRID * LAYOUT_GRID * 4
_HOG_DIM = HOG_GRID * HOG_GRID * HOG_ORIENTATIONS
_SHAPE_DIM = sum(b for _, _, b in _SHAPE_ENCODINGS.values()) + _RADIAL_SECTORS
DIM = _COLOUR_DIM + _LAYOUT_DIM + _HOG_DIM + _SHAPE_DIM


def _soft_index(values: np.ndarray, low: float, high: float, bins: int) -> tuple[np.ndarray, np.ndarray]:
    """Linear soft-binning: lower bin index and the weight of the upper neighbour, bin centres evenly spaced."""
    pos = (np.clip(values, low, high) - low) / (high - low) * (bins - 1)
    lo = np.minimum(np.floor(pos).astype(np.int64), bins - 2) if bins > 1 else np.zeros(pos.shape, np.int64)
    return lo, pos - lo


def colour_histogram(lab: np.ndarray) -> np.ndarray:
    """Trilinearly soft-binned joint Lab histogram of (N, 3) pixels, normalised to sum 1."""
    hist = np.zeros(_COLOUR_DIM)
    if len(lab) == 0:
        return hist
    idx, frac = zip(*(_soft_index(lab[:, k], *LAB_RANGES[k], LAB_BINS[k]) for k in range(3)), strict=True)
    nb, nc = LAB_BINS[1], LAB_BINS[2]
    for dl in (0, 1):
        wl = frac[0] if dl else 1 - frac[0]
        for da in (0, 1):
            wa = frac[1] if da else 1 - frac[1]
            for db in (0, 1):
                wb = frac[2] if db else 1 - frac[2]
                flat = ((idx[0] + dl) * nb + idx[1] + da) * nc + idx[2] + db
                hist += np.bincount(flat, weights=wl * wa * wb, minlength=_COLOUR_DIM)
    return hist / hist.sum()


def _cell_sums(values: np.ndarray, grid: int) -> np.ndarray:
    """Sum a (S, S, ...) array over a grid x grid partition -> (grid, grid, ...)."""
    s = values.shape[0] // grid
    return values.reshape(grid, s, grid, s, *values.shape[2:]).sum(axis=(1, 3))


def layout(lab: np.ndarray, mask: np.ndarray) -> np.ndarray:
    """Per grid cell: coverage and mean (L-50, a, b)/50 of the object's pixels (zeros where empty)."""
    cover = _cell_sums(mask.astype(np.float64), LAYOUT_GRID)
    centred = (lab - np.array([50.0, 0.0, 0.0])) / 50.0
    sums = _cell_sums(centred * mask[..., None], LAYOUT_GRID)
    means = sums / np.maximum(cover, 1.0)[..., None]
    cell_area = (mask.shape[0] // LAYOUT_GRID) ** 2
    return np.concatenate([means, (cover / cell_area)[..., None]], axis=-1).ravel()


def hog(lightness: np.ndarray) -> np.ndarray:
    """Unsigned gradient-orientation histogram over a grid of cells (soft orientation bins), sum 1."""
    gy, gx = np.gradient(lightness)
    mag = np.hypot(gx, gy)
    ang = np.mod(np.arctan2(gy, gx), np.pi) / np.pi * HOG_ORIENTATIONS - 0.5
    lo = np.floor(ang).astype(np.int64)
    frac = ang - lo
    n = lightness.shape[0]
    cell = n // HOG_GRID
    rows, cols = np.mgrid[0:n, 0:n] // cell
    base = (rows * HOG_GRID + cols) * HOG_ORIENTATIONS
    hist = np.bincount((base + lo % HOG_ORIENTATIONS).ravel(), (mag * (1 - frac)).ravel(), _HOG_DIM)
    hist += np.bincount((base + (lo + 1) % HOG_ORIENTATIONS).ravel(), (mag * frac).ravel(), _HOG_DIM)
    total = hist.sum()
    return hist / total if total > 0 else hist


def _rbf(value: float, low: float, high: float, bins: int) -> np.ndarray:
    centres = np.linspace(low, high, bins)
    width = (high - low) / (bins - 1)
    return np.exp(-0.5 * ((np.clip(value, low, high) - centres) / width) ** 2)


def shape_block(filled: np.ndarray) -> np.ndarray:
    """Soft one-hot encodings of the silhouette scalars plus its centroid-distance profile."""
    s = silhouette(filled, sectors=_RADIAL_SECTORS)
    if s is None:
        return np.zeros(_SHAPE_DIM)
    values = {
        "log_aspect": float(np.log(s.aspect)),
        "extent": s.extent,
        "solidity": s.solidity,
        "log_elongation": float(np.log(s.elongation)),
        "hu1": float(np.log10(max(s.hu[0], 1e-6))),
    }
    parts = [_rbf(values[k], *_SHAPE_ENCODINGS[k]) / np.sqrt(len(values)) for k in _SHAPE_ENCODINGS]
    parts.append(0.5 * s.radial / np.linalg.norm(s.radial))
    return np.concatenate(parts)


def _unit(x: np.ndarray) -> np.ndarray:
    n = np.linalg.norm(x)
    return x / n if n > 0 else x


class ClassicalDescriptor:
    """Colour + layout + gradient + silhouette descriptor of the object on the gray background."""

    dim = DIM

    def __init__(self, model_id: str = DEFAULT_MODEL_ID, tolerance: int = BACKGROUND_TOLERANCE) -> None:
        self.model_id = model_id
        self.tolerance = int(tolerance)

    def encode_image(self, images: list[Image.Image]) -> np.ndarray:
        """(n, DIM) float32, L2-normalised rows."""
        if not images:
            return np.zeros((0, DIM), dtype=np.float32)
        return l2_normalise(np.stack([self.describe(image) for image in images]))

    def describe(self, image: Image.Image, mask: np.ndarray | None = None) -> np.ndarray:
        """One unnormalised descriptor; an image without foreground is described as a whole."""
        crop = object_crop(image, SIZE, mask=mask, tolerance=self.tolerance)
        lab = rgb_to_lab(crop.rgb)
        mask = crop.mask
        blocks = [
            (W_COLOUR, np.sqrt(colour_histogram(lab[mask]))),
            (W_LAYOUT, layout(lab, mask)),
            (W_HOG, np.sqrt(hog(lab[..., 0]))),
            (W_SHAPE, shape_block(crop.filled)),
        ]
        return np.concatenate([w * _unit(b) for w, b in blocks]).astype(np.float32)
