"""Probe queries made from a model's stored views: no new rendering.

A view (the object rendered on uniform gray) becomes a query-like ROI: the object's mask is where the
render is not gray (closed, largest blob); the object is scaled to a random size, pasted on a random
background (solid, gradient or smooth noise), partly occluded half of the time, run through a camera's
degradations (white balance, exposure, gamma, blur, noise, JPEG; :mod:`pipeline.evaluate.degrade`) and cut
out on gray as the query does (:func:`pipeline.query.roi.cut_out`). Every draw comes from a generator
seeded by the mesh id and the view, so the same store makes the same probes.
"""

from __future__ import annotations

import hashlib
from dataclasses import asdict, dataclass
from typing import TYPE_CHECKING

import numpy as np

if TYPE_CHECKING:
    from PIL import Image

#: backgrounds a probe's object is pasted on (no photo crops: a store has no photos)
BACKGROUNDS = ("solid", "gradient", "noise")


@dataclass(frozen=True)
class ProbeConfig:
    """How many probes per model and how they are made (all of it is fingerprinted)."""

    per_mesh: int = 6  # views turned into probes per model (distinct views, at most as many as it has)
    side_px: tuple[int, int] = (120, 300)  # the object's longer side in the probe, pixels
    margin_px: int = 32  # background around the object's box (the canvas the degradations run on)
    occlusion: bool = True  # an occluder half of the time (DegradeConfig.occlusion_prob)
    seed: int = 0
    version: int = 1  # bump when the generator changes what it draws

    def __post_init__(self) -> None:
        if self.per_mesh < 0:
            raise ValueError(f"probes per mesh must be >= 0, got {self.per_mesh}")
        lo, hi = self.side_px
        if not 16 <= lo <= hi:
            raise ValueError(f"probe object side range must satisfy 16 <= lo <= hi, got {lo},{hi}")

    @property
    def enabled(self) -> bool:
        return self.per_mesh > 0

    def describe(self) -> dict:
        return asdict(self)


def rng_for(mesh_id: str, view_index: int, seed: int) -> np.random.Generator:
    """The generator of one probe (stable across runs, machines and batch layouts)."""
    digest = hashlib.blake2b(f"{seed}:{mesh_id}:{view_index}".encode(), digest_size=8).digest()
    return np.random.default_rng(int.from_bytes(digest, "little"))


def chosen_views(mesh_id: str, view_indices: list[int], cfg: ProbeConfig) -> list[int]:
    """The views of a mesh that become probes: ``cfg.per_mesh`` distinct ones, drawn per mesh."""
    ordered = sorted(set(int(v) for v in view_indices))
    rng = rng_for(mesh_id, -1, cfg.seed)
    k = min(cfg.per_mesh, len(ordered))
    return sorted(ordered[i] for i in rng.choice(len(ordered), size=k, replace=False))


def object_mask(view: np.ndarray, background: tuple[int, int, int]) -> np.ndarray | None:
    """Where a render is not its uniform background: closed, the largest blob with its holes filled
    (OpenCV throughout: this runs for every probe); ``None`` when the view is empty."""
    import cv2

    diff = cv2.absdiff(view, np.full_like(view, background))
    fg = (np.maximum(np.maximum(diff[..., 0], diff[..., 1]), diff[..., 2]) > 3).astype(np.uint8)
    fg = cv2.morphologyEx(fg, cv2.MORPH_CLOSE, np.ones((5, 5), np.uint8))
    n, labels, stats, _ = cv2.connectedComponentsWithStats(fg, connectivity=8)
    if n < 2:
        return None
    blob = (labels == 1 + int(np.argmax(stats[1:, cv2.CC_STAT_AREA]))).astype(np.uint8)
    contours, _ = cv2.findContours(blob, cv2.RETR_EXTERNAL, cv2.CHAIN_APPROX_SIMPLE)
    cv2.drawContours(blob, contours, -1, 1, thickness=cv2.FILLED)  # holes filled
    return blob.astype(bool)


def probe_roi(
    view: np.ndarray, mesh_id: str, view_index: int, cfg: ProbeConfig, background: tuple[int, int, int]
) -> Image.Image | None:
    """The ROI image of one probe made from ``view`` (HxWx3 uint8), or ``None`` when the view shows nothing."""
    import cv2
    from PIL import Image

    from pipeline.evaluate.backgrounds import make_background
    from pipeline.evaluate.degrade import DegradeConfig, occlude, photometric
    from pipeline.query.roi import cut_out

    mask = object_mask(view, background)
    if mask is None:
        return None
    rng = rng_for(mesh_id, view_index, cfg.seed)
    ys, xs = np.nonzero(mask)
    y0, y1, x0, x1 = ys.min(), ys.max() + 1, xs.min(), xs.max() + 1
    crop, cm = view[y0:y1, x0:x1], mask[y0:y1, x0:x1]
    scale = float(rng.uniform(*cfg.side_px)) / max(crop.shape[:2])
    w, h = max(8, round(crop.shape[1] * scale)), max(8, round(crop.shape[0] * scale))
    crop = cv2.resize(crop, (w, h), interpolation=cv2.INTER_AREA)
    cm = cv2.resize(cm.astype(np.uint8), (w, h), interpolation=cv2.INTER_NEAREST) > 0
    if not cm.any():
        return None
    m = cfg.margin_px
    kind = BACKGROUNDS[int(rng.integers(len(BACKGROUNDS)))]
    canvas = make_background(kind, w + 2 * m, h + 2 * m, rng).copy()
    full = np.zeros(canvas.shape[:2], bool)
    full[m : m + h, m : m + w] = cm
    canvas[full] = crop[cm]
    d = DegradeConfig()
    visible = full
    if cfg.occlusion and rng.random() < d.occlusion_prob:
        occluded, vis, _ = occlude(canvas, full, rng, d, make_background("noise", *canvas.shape[1::-1], rng))
        if vis.sum() >= 0.35 * full.sum():  # keep at least a third of the object in view
            canvas, visible = occluded, vis
    canvas, _ = photometric(canvas, rng, d)
    roi, _, _ = cut_out(Image.fromarray(canvas), visible, background)
    return roi
