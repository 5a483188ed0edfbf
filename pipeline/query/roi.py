"""The region of interest: the prompted object cut out of the photo, pasted on uniform gray, cropped.

Where the object comes from, in order: a given mask; a given box (segmented by the profile's segmenter
when it has one, else used as is); the profile's detector (best box for the prompt), then the segmenter.
``roi_mode="bbox"`` is the paper's ablation: the raw box crop, no segmentation.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass, field

import numpy as np
from PIL import Image

from pipeline.query.errors import QueryError
from pipeline.query.images import Photo, box_to_working
from pipeline.query.masks import largest_blob, plausible
from pipeline.query.saliency import saliency_grabcut_segment, saliency_segment
from pipeline.query.settings import GRAY, ROI_MODES

IntBox = tuple[int, int, int, int]


@dataclass
class Roi:
    """The query object: ``image`` is what the encoders see; ``mask``/``box`` are in the photo's pixels."""

    image: Image.Image  # RGB: the object on gray, cropped to its box (or the raw box crop in bbox mode)
    mask: np.ndarray  # bool, photo size (original pixels)
    box: tuple[float, float, float, float]  # x0, y0, x1, y1 in original pixels
    source: str  # "box" | "mask" | "detector"
    roi_mode: str = "segm"
    crop_mask: np.ndarray | None = None  # bool, ``image`` size: which ROI pixels are the object
    detector_score: float | None = None
    notes: list[str] = field(default_factory=list)
    photo_source: str = ""  # the photo's path (or "<PIL image>")
    photo_size: tuple[int, int] = (0, 0)  # the photo's (width, height) as given

    def describe(self) -> dict:
        return {
            "box": [round(float(v), 2) for v in self.box],
            "source": self.source,
            "roi_mode": self.roi_mode,
            "size": list(self.image.size),
            "mask_pixels": int(self.mask.sum()),
            "detector_score": self.detector_score,
            "notes": list(self.notes),
        }


def mask_box(mask: np.ndarray) -> IntBox | None:
    """Tight integer box (x0, y0, x1 exclusive, y1 exclusive) of a boolean mask."""
    ys = np.flatnonzero(mask.any(axis=1))
    xs = np.flatnonzero(mask.any(axis=0))
    if ys.size == 0:
        return None
    return int(xs[0]), int(ys[0]), int(xs[-1]) + 1, int(ys[-1]) + 1


def box_mask(shape: tuple[int, int], box: IntBox) -> np.ndarray:
    m = np.zeros(shape, dtype=bool)
    x0, y0, x1, y1 = box
    m[y0:y1, x0:x1] = True
    return m


def border_segment(image: Image.Image, box: IntBox, min_share: float = 0.02, max_share: float = 0.97):
    """Segmenter-free object mask inside ``box``: pixels unlike the box's border colour, largest blob.

    Used by profiles without a segmenter (offline). Works when the box has a margin of fairly uniform
    background (renders, table tops, studio shots); returns ``None`` when the result is implausible.
    """

    x0, y0, x1, y1 = box
    crop = np.asarray(image, dtype=np.float32)[y0:y1, x0:x1]
    h, w = crop.shape[:2]
    b = max(1, round(0.03 * min(h, w)))
    if min(h, w) < 3 * b + 2:
        return None
    border = np.concatenate(
        [
            crop[:b].reshape(-1, 3),
            crop[-b:].reshape(-1, 3),
            crop[:, :b].reshape(-1, 3),
            crop[:, -b:].reshape(-1, 3),
        ]
    )
    bg = np.median(border, axis=0)
    spread = np.median(np.linalg.norm(border - bg, axis=1))
    dist = np.linalg.norm(crop - bg, axis=2)
    fg = dist > max(24.0, 3.0 * spread)
    fg = largest_blob(fg)
    if fg is None:
        return None
    share = float(fg.mean())
    if not min_share <= share <= max_share:
        return None
    full = np.zeros(image.size[::-1], dtype=bool)
    full[y0:y1, x0:x1] = fg
    return full


def grabcut_segment(
    image: Image.Image,
    box: IntBox,
    iterations: int = 4,
    context: float = 0.3,
    work_side: int = 200,
    min_share: float = 0.05,
    max_share: float = 0.98,
):
    """Segmenter-free object mask inside ``box``: OpenCV GrabCut seeded by the box (weight-free).

    Pixels outside the box are background, pixels inside it probably foreground; colour models of both
    are fitted iteratively and a graph cut separates them. It runs on the box plus ``context`` of its size
    around it, downscaled so the longer side of that window is at most ``work_side`` pixels (about 20-60 ms
    per box), then keeps the largest piece with its holes filled. Returns ``None`` when the result is
    implausible (too small or the whole box), so the caller can fall back.
    """
    import cv2

    W, H = image.size
    x0, y0, x1, y1 = box
    bw, bh = x1 - x0, y1 - y0
    if min(bw, bh) < 8:
        return None
    cx0, cy0 = max(0, int(x0 - context * bw)), max(0, int(y0 - context * bh))
    cx1, cy1 = min(W, int(np.ceil(x1 + context * bw))), min(H, int(np.ceil(y1 + context * bh)))
    scale = min(1.0, work_side / max(cx1 - cx0, cy1 - cy0))
    size = (max(1, round((cx1 - cx0) * scale)), max(1, round((cy1 - cy0) * scale)))
    win = np.asarray(image.resize(size, Image.BILINEAR, box=(cx0, cy0, cx1, cy1)), dtype=np.uint8)
    gc = np.full(win.shape[:2], cv2.GC_BGD, np.uint8)
    bx0, by0 = int((x0 - cx0) * scale), int((y0 - cy0) * scale)
    bx1, by1 = int(np.ceil((x1 - cx0) * scale)), int(np.ceil((y1 - cy0) * scale))
    gc[by0:by1, bx0:bx1] = cv2.GC_PR_FGD
    if (gc == cv2.GC_BGD).sum() < 16:  # the box is the whole photo: its 2-px rim must seed the background
        gc[:2], gc[-2:], gc[:, :2], gc[:, -2:] = cv2.GC_BGD, cv2.GC_BGD, cv2.GC_BGD, cv2.GC_BGD
    try:
        cv2.setRNGSeed(0)  # GrabCut's GMM initialisation is random: keep queries deterministic
        bgd, fgd = np.zeros((1, 65), np.float64), np.zeros((1, 65), np.float64)
        cv2.grabCut(
            np.ascontiguousarray(win[..., ::-1]), gc, None, bgd, fgd, iterations, cv2.GC_INIT_WITH_MASK
        )
    except cv2.error:
        return None
    fg = (gc == cv2.GC_FGD) | (gc == cv2.GC_PR_FGD)
    fg = largest_blob(fg)
    if fg is None:
        return None
    big = (
        np.asarray(Image.fromarray(fg.astype(np.uint8) * 255).resize((cx1 - cx0, cy1 - cy0), Image.BILINEAR))
        >= 128
    )
    full = np.zeros((H, W), dtype=bool)
    full[cy0:cy1, cx0:cx1] = big
    return plausible(full, box, min_share, max_share)


#: the offline (segmenter-free) ways of splitting the object from its box, best first
BOX_SEGMENTERS = {
    "grabcut": grabcut_segment,
    "saliency-grabcut": saliency_grabcut_segment,
    "saliency": saliency_segment,
    "border": border_segment,
}
#: how the answer's notes name each box segmenter
SEGMENTER_NOTES = {
    "grabcut": "object split from the box by GrabCut",
    "saliency-grabcut": "object split from the box by GrabCut seeded with the img-focus saliency map",
    "saliency": "object split from the box by the img-focus saliency map",
    "border": "object split from the box's border colour",
}


def cut_out(image: Image.Image, mask: np.ndarray, background=GRAY) -> tuple[Image.Image, np.ndarray, IntBox]:
    """The object (``mask`` pixels) pasted on ``background``, cropped to the mask's box."""
    box = mask_box(mask)
    if box is None:
        raise QueryError("the object mask is empty")
    x0, y0, x1, y1 = box
    crop = np.asarray(image, dtype=np.uint8)[y0:y1, x0:x1]
    m = mask[y0:y1, x0:x1]
    out = np.empty_like(crop)
    out[:] = np.asarray(background, dtype=np.uint8)
    out[m] = crop[m]
    return Image.fromarray(out), m.copy(), box


def _to_original(photo: Photo, mask: np.ndarray, box: IntBox) -> tuple[np.ndarray, tuple[float, ...]]:
    if photo.scale == 1.0:
        return mask, tuple(float(v) for v in box)
    w, h = photo.original_size
    big = np.asarray(Image.fromarray(mask).resize((w, h), Image.NEAREST), dtype=bool)
    s = photo.scale
    ob = (box[0] / s, box[1] / s, min(box[2] / s, w), min(box[3] / s, h))
    return big, ob


def make_roi(
    photo: Photo,
    prompt: str,
    *,
    box=None,
    mask: np.ndarray | None = None,
    roi_mode: str = "segm",
    model: Callable[[str], object | None],
    background=GRAY,
    min_side: int = 4,
    profile: str = "",
    box_segmenter: str = "grabcut",
) -> Roi:
    """Build the ROI. ``model(role)`` returns the profile's detector/segmenter (loaded on first use) or None."""
    if roi_mode not in ROI_MODES:
        raise QueryError(f"unknown ROI mode {roi_mode!r}; choose from {', '.join(ROI_MODES)}")
    W, H = photo.image.size
    notes: list[str] = []
    score = None
    if mask is not None:
        source = "mask"
        work_box = mask_box(mask)
        if box is not None:
            notes.append("box ignored: a mask was given")
    elif box is not None:
        source = "box"
        work_box = box_to_working(box, photo, min_side)
    else:
        detector = model("detector")
        if detector is None:
            raise QueryError(
                f"the {profile or 'current'} profile has no object detector: pass --box x0,y0,x1,y1 or "
                "--mask MASK.png (or query with --profile paper)"
            )
        found = detector.detect(photo.image, prompt)
        if not found:
            raise QueryError(f"no object matching {prompt!r} was detected: pass --box or --mask")
        (fx0, fy0, fx1, fy1), score = found[0]
        work_box = (int(fx0), int(fy0), int(np.ceil(fx1)), int(np.ceil(fy1)))
        if min(work_box[2] - work_box[0], work_box[3] - work_box[1]) < 1:
            raise QueryError(f"the detected box for {prompt!r} is empty: pass --box or --mask")
        source = "detector"

    if roi_mode == "bbox":
        x0, y0, x1, y1 = work_box
        roi_img = photo.image.crop(work_box)
        full = box_mask((H, W), work_box)
        crop_mask = np.ones((y1 - y0, x1 - x0), dtype=bool)
    else:
        if mask is None:
            segmenter = model("segmenter")
            if segmenter is None:
                if box_segmenter not in BOX_SEGMENTERS:
                    raise QueryError(
                        f"unknown box segmenter {box_segmenter!r}; choose from {', '.join(BOX_SEGMENTERS)}"
                    )
                mask = BOX_SEGMENTERS[box_segmenter](photo.image, work_box)
                if mask is None:
                    mask = box_mask((H, W), work_box)
                    notes.append(
                        f"no segmenter in this profile and {box_segmenter} found no clear object in the box "
                        "(nothing, or only a sliver of it): ROI = the whole box"
                    )
                else:
                    notes.append(f"no segmenter in this profile: {SEGMENTER_NOTES[box_segmenter]}")
            else:
                mask = np.asarray(
                    segmenter.segment(photo.image, tuple(float(v) for v in work_box)), dtype=bool
                )
                if mask.shape != (H, W) or not mask.any():
                    mask = box_mask((H, W), work_box)
                    notes.append("the segmenter found nothing in the box: the ROI is the whole box")
        roi_img, crop_mask, work_box = cut_out(photo.image, mask, background)
        full = mask
    mask_o, box_o = _to_original(photo, full, work_box)
    return Roi(roi_img, mask_o, box_o, source, roi_mode, crop_mask, score, notes)
