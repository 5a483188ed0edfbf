"""Image operations shared by the offline (weight-free) captioner and descriptor.

Everything works on the object's foreground: pixels that differ from the uniform gray background used for
renders and query ROIs. The object is cropped to its foreground box and resized to a small working square so
that every measurement is independent of the input's size and of how tightly it was cropped.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from PIL import Image, ImageChops
from scipy import ndimage

#: the uniform background of renders and query ROIs
BACKGROUND_RGB = (205, 205, 205)
#: a pixel is foreground when one of its channels differs from the background by more than this
BACKGROUND_TOLERANCE = 12
#: connected foreground pieces smaller than this fraction of the largest piece are noise
MIN_COMPONENT_FRACTION = 0.02

_EIGHT_CONNECTED = np.ones((3, 3), dtype=bool)


def to_rgb(image: Image.Image | np.ndarray) -> Image.Image:
    """Any PIL image (or HxW / HxWx3 / HxWx4 uint8 array) as RGB; transparent pixels become background."""
    if isinstance(image, np.ndarray):
        image = Image.fromarray(np.ascontiguousarray(image))
    if image.mode == "RGB":
        return image
    if image.mode in ("RGBA", "LA", "PA") or (image.mode == "P" and "transparency" in image.info):
        rgba = image.convert("RGBA")
        canvas = Image.new("RGBA", rgba.size, (*BACKGROUND_RGB, 255))
        return Image.alpha_composite(canvas, rgba).convert("RGB")
    return image.convert("RGB")


def foreground_mask(image: Image.Image, tolerance: int = BACKGROUND_TOLERANCE) -> np.ndarray:
    """Boolean HxW mask of pixels that differ from the gray background (PIL ops: ~1 ms at 512x512)."""
    diff = ImageChops.difference(image, Image.new("RGB", image.size, BACKGROUND_RGB))
    r, g, b = diff.split()
    return np.asarray(ImageChops.lighter(ImageChops.lighter(r, g), b)) > tolerance


def clean_mask(mask: np.ndarray) -> np.ndarray:
    """Drop specks: keep the connected pieces that are at least a small fraction of the largest one."""
    labels, n = ndimage.label(mask, structure=_EIGHT_CONNECTED)
    if n <= 1:
        return mask
    sizes = np.bincount(labels.ravel())
    sizes[0] = 0
    keep = sizes >= MIN_COMPONENT_FRACTION * sizes.max()
    keep[0] = False
    return keep[labels]


def bounding_box(mask: np.ndarray) -> tuple[int, int, int, int] | None:
    """(x0, y0, x1, y1), exclusive ends, of the True pixels; None when there are none."""
    rows = np.flatnonzero(mask.any(axis=1))
    if rows.size == 0:
        return None
    cols = np.flatnonzero(mask.any(axis=0))
    return int(cols[0]), int(rows[0]), int(cols[-1]) + 1, int(rows[-1]) + 1


@dataclass(frozen=True)
class ObjectCrop:
    """The object resized into a ``size`` x ``size`` square (centred, padded with background)."""

    rgb: np.ndarray  # float32 HxWx3 in [0, 1], background outside the object
    mask: np.ndarray  # bool HxW: the object's own pixels (holes such as a mug handle stay background)
    filled: np.ndarray  # bool HxW: the silhouette with holes filled (for shape measurements)
    box_aspect: float  # height / width of the object's box in the input image
    box_hw: tuple[int, int]  # (height, width) of the object's box in the input image, in pixels
    found: bool  # False when the input had no foreground (the whole frame was used instead)


def object_crop(
    image: Image.Image | np.ndarray,
    size: int,
    mask: np.ndarray | None = None,
    tolerance: int = BACKGROUND_TOLERANCE,
    whole_frame_if_empty: bool = True,
) -> ObjectCrop | None:
    """Find the object (or use ``mask``), crop it to its box and fit it into a ``size`` square."""
    image = to_rgb(image)
    if mask is None:
        mask = clean_mask(foreground_mask(image, tolerance))
    else:
        mask = np.asarray(mask, dtype=bool)
        if mask.shape != (image.height, image.width):
            raise ValueError(f"mask shape {mask.shape} != image shape {(image.height, image.width)}")
    box = bounding_box(mask)
    found = box is not None
    if not found:
        if not whole_frame_if_empty:
            return None
        box = (0, 0, image.width, image.height)
        mask = np.ones((image.height, image.width), dtype=bool)
    x0, y0, x1, y1 = box
    bw, bh = x1 - x0, y1 - y0
    scale = size / max(bw, bh)
    tw, th = max(1, round(bw * scale)), max(1, round(bh * scale))
    ox, oy = (size - tw) // 2, (size - th) // 2
    patch = np.asarray(image.resize((tw, th), Image.BILINEAR, box=box), dtype=np.float32) / 255.0
    mpatch = Image.fromarray(mask.astype(np.float32)).resize((tw, th), Image.BILINEAR, box=box)
    rgb = np.empty((size, size, 3), dtype=np.float32)
    rgb[:] = np.asarray(BACKGROUND_RGB, dtype=np.float32) / 255.0
    rgb[oy : oy + th, ox : ox + tw] = patch
    m = np.zeros((size, size), dtype=bool)
    m[oy : oy + th, ox : ox + tw] = np.asarray(mpatch) >= 0.5
    if not m.any():  # a sliver thinner than a working pixel: keep its centre line
        m[oy : oy + th, ox : ox + tw] = np.asarray(mpatch) > 0
    filled = ndimage.binary_fill_holes(m)
    return ObjectCrop(rgb, m, filled, bh / bw, (bh, bw), found)


def rgb_to_hsv(rgb: np.ndarray) -> np.ndarray:
    """Float RGB in [0, 1] (..., 3) to HSV with hue in degrees [0, 360), saturation and value in [0, 1]."""
    r, g, b = rgb[..., 0], rgb[..., 1], rgb[..., 2]
    v = rgb.max(axis=-1)
    c = v - rgb.min(axis=-1)
    s = np.where(v > 0, c / np.maximum(v, 1e-12), 0.0)
    cz = np.maximum(c, 1e-12)
    h = np.where(v == r, ((g - b) / cz) % 6.0, np.where(v == g, (b - r) / cz + 2.0, (r - g) / cz + 4.0))
    h = np.where(c > 0, h * 60.0, 0.0)
    return np.stack([h, s, v], axis=-1).astype(np.float32)


_RGB_TO_XYZ = np.array(
    [[0.4124564, 0.3575761, 0.1804375], [0.2126729, 0.7151522, 0.0721750], [0.0193339, 0.1191920, 0.9503041]],
    dtype=np.float32,
)
_WHITE_D65 = np.array([0.95047, 1.0, 1.08883], dtype=np.float32)


def rgb_to_lab(rgb: np.ndarray) -> np.ndarray:
    """Float sRGB in [0, 1] (..., 3) to CIE Lab (D65): L in [0, 100], a and b roughly in [-110, 110]."""
    lin = np.where(rgb <= 0.04045, rgb / 12.92, ((rgb + 0.055) / 1.055) ** 2.4)
    xyz = lin @ _RGB_TO_XYZ.T / _WHITE_D65
    f = np.where(xyz > 0.008856, np.cbrt(xyz), 7.787 * xyz + 16.0 / 116.0)
    lab = np.stack(
        [116.0 * f[..., 1] - 16.0, 500.0 * (f[..., 0] - f[..., 1]), 200.0 * (f[..., 1] - f[..., 2])], -1
    )
    return lab.astype(np.float32)


@dataclass(frozen=True)
class Silhouette:
    """Scale-free measurements of a filled silhouette."""

    aspect: float  # height / width of the silhouette's box
    extent: float  # area / box area
    solidity: float  # area / convex hull area
    circularity: float  # 4 pi area / perimeter^2 (1 for a disc)
    elongation: float  # sqrt of the ratio of the principal second moments (1 for a disc or square)
    bend: float  # sagitta / length of a parabola fitted along the major axis (0 for a straight bar)
    ellipse_iou: float  # IoU with the ellipse of the same second moments
    symmetry: float  # IoU of the silhouette with its left-right mirror image
    corner_fill: float  # mean filled fraction of the four corner patches of the box
    top_width: float  # mean width of the top fifth of rows relative to the median row width
    bottom_width: float  # the same for the bottom fifth
    width_flatness: float  # std / mean of the row widths over the middle 60 % of rows
    radial: np.ndarray  # max centroid distance in 16 angular sectors, divided by their mean
    hu: np.ndarray  # the first four Hu moment invariants


def silhouette(filled: np.ndarray, sectors: int = 16) -> Silhouette | None:
    """Measure a filled silhouette (any size); None when it has fewer than 3 pixels."""
    box = bounding_box(filled)
    if box is None:
        return None
    x0, y0, x1, y1 = box
    m = filled[y0:y1, x0:x1]
    h, w = m.shape
    area = float(m.sum())
    if area < 3:
        return None
    ys, xs = np.nonzero(m)
    ys = ys.astype(np.float64) + 0.5
    xs = xs.astype(np.float64) + 0.5
    cy, cx = ys.mean(), xs.mean()
    dy, dx = ys - cy, xs - cx
    mu20, mu02, mu11 = (dx * dx).mean(), (dy * dy).mean(), (dx * dy).mean()
    cov = np.array([[mu20, mu11], [mu11, mu02]]) + np.eye(2) / 12.0  # + pixel extent
    evals, evecs = np.linalg.eigh(cov)
    elongation = float(np.sqrt(evals[1] / max(evals[0], 1e-12)))
    along = dx * evecs[0, 1] + dy * evecs[1, 1]
    across = dx * evecs[0, 0] + dy * evecs[1, 0]
    length = float(along.max() - along.min())
    if length > 2 and area >= 8:
        curve = float(np.polyfit(along, across, 2)[0])
        bend = abs(curve) * (length / 2) ** 2 / length
    else:
        bend = 0.0
    inv = np.linalg.inv(cov)
    gy, gx = np.mgrid[0:h, 0:w].astype(np.float64) + 0.5
    gy -= cy
    gx -= cx
    inside = (inv[0, 0] * gx * gx + 2 * inv[0, 1] * gx * gy + inv[1, 1] * gy * gy) <= 4.0
    ellipse_iou = float((inside & m).sum() / max((inside | m).sum(), 1))

    padded = np.pad(m.astype(np.float32), 2)
    smooth = ndimage.gaussian_filter(padded, 1.0)
    gyy, gxx = np.gradient(smooth)
    perimeter = float(np.hypot(gxx, gyy).sum())
    circularity = float(min(4 * np.pi * area / max(perimeter, 1e-6) ** 2, 1.0))

    boundary = m & ~ndimage.binary_erosion(m, border_value=0)
    by, bx = np.nonzero(boundary)
    corners = np.concatenate(
        [np.stack([bx + ox, by + oy], 1) for ox in (0.0, 1.0) for oy in (0.0, 1.0)], axis=0
    ).astype(np.float64)
    hull_area = convex_hull_area(corners) or float(h * w)
    solidity = float(min(area / max(hull_area, 1e-6), 1.0))

    symmetry = float((m & m[:, ::-1]).sum() / max((m | m[:, ::-1]).sum(), 1))
    ch, cw = max(1, round(0.15 * h)), max(1, round(0.15 * w))
    corner_fill = float(
        np.mean([m[:ch, :cw].mean(), m[:ch, -cw:].mean(), m[-ch:, :cw].mean(), m[-ch:, -cw:].mean()])
    )
    widths = m.sum(axis=1).astype(np.float64)
    med = max(float(np.median(widths)), 1.0)
    fifth = max(1, h // 5)
    top_width = float(widths[:fifth].mean() / med)
    bottom_width = float(widths[-fifth:].mean() / med)
    middle = widths[int(0.2 * h) : max(int(0.8 * h), int(0.2 * h) + 1)]
    width_flatness = float(middle.std() / max(middle.mean(), 1e-6))

    bdy, bdx = by + 0.5 - cy, bx + 0.5 - cx
    sector = ((np.arctan2(bdy, bdx) + np.pi) / (2 * np.pi) * sectors).astype(np.int64) % sectors
    radial = np.zeros(sectors)
    np.maximum.at(radial, sector, np.hypot(bdy, bdx))
    radial = radial / max(radial.mean(), 1e-6)

    scale = area**2  # eta_pq = mu_pq / area^(1 + (p+q)/2), here p+q in {2, 3}
    n20, n02, n11 = mu20 * area / scale, mu02 * area / scale, mu11 * area / scale
    s3 = area**2.5
    n30, n03 = (dx**3).sum() / s3, (dy**3).sum() / s3
    n21, n12 = (dx * dx * dy).sum() / s3, (dx * dy * dy).sum() / s3
    hu = np.array(
        [
            n20 + n02,
            (n20 - n02) ** 2 + 4 * n11**2,
            (n30 - 3 * n12) ** 2 + (3 * n21 - n03) ** 2,
            (n30 + n12) ** 2 + (n21 + n03) ** 2,
        ]
    )
    return Silhouette(
        aspect=h / w,
        extent=area / (h * w),
        solidity=solidity,
        circularity=circularity,
        elongation=elongation,
        bend=bend,
        ellipse_iou=ellipse_iou,
        symmetry=symmetry,
        corner_fill=corner_fill,
        top_width=top_width,
        bottom_width=bottom_width,
        width_flatness=width_flatness,
        radial=radial,
        hu=hu,
    )


def convex_hull_area(points: np.ndarray) -> float:
    """Area of the convex hull of 2-D ``points`` (0.0 when degenerate): Andrew's monotone chain.

    Replaces ``scipy.spatial.ConvexHull(points).volume``, whose import (all of scipy.spatial) cost a cold
    query more than the hull itself; on pixel-corner coordinates both are exact (tests compare them).
    Only each row's leftmost and rightmost point can be a hull vertex, so those are all it looks at.
    """
    if len(points) < 3:
        return 0.0
    ys, inverse = np.unique(points[:, 1], return_inverse=True)
    lo = np.full(len(ys), np.inf)
    hi = np.full(len(ys), -np.inf)
    np.minimum.at(lo, inverse, points[:, 0])
    np.maximum.at(hi, inverse, points[:, 0])
    pts = sorted({(float(x), float(y)) for x, y in zip(np.r_[lo, hi], np.r_[ys, ys], strict=True)})
    if len(pts) < 3:
        return 0.0

    def half(seq):
        chain: list[tuple[float, float]] = []
        for p in seq:
            while len(chain) >= 2:
                (ax, ay), (bx, by) = chain[-2], chain[-1]
                if (bx - ax) * (p[1] - ay) - (by - ay) * (p[0] - ax) > 0:
                    break
                chain.pop()
            chain.append(p)
        return chain[:-1]

    hull = half(pts) + half(reversed(pts))
    x = np.array([p[0] for p in hull])
    y = np.array([p[1] for p in hull])
    return float(abs(np.dot(x, np.roll(y, -1)) - np.dot(y, np.roll(x, -1))) / 2.0)
