"""Validated inputs: photos (any mode, any size), masks, boxes and prompts, each with one-line errors.

Photos larger than ``max_side`` are decoded downscaled; boxes and masks are always given in the
photo's own pixels and mapped to the working scale here.
"""

from __future__ import annotations

import math
import os
import re
import warnings
from dataclasses import dataclass
from pathlib import Path

import numpy as np
from PIL import Image, ImageOps, UnidentifiedImageError

from pipeline.query.errors import QueryError
from pipeline.query.settings import GRAY

Box = tuple[float, float, float, float]


@dataclass
class Photo:
    """A query photo as RGB at working scale; ``scale`` = working pixels per original pixel (<= 1)."""

    image: Image.Image
    original_size: tuple[int, int]  # (width, height) as given
    scale: float
    source: str  # path, or "<PIL image>"


def _open(src) -> tuple[Image.Image, str]:
    if isinstance(src, Image.Image):
        return src, "<PIL image>"
    if isinstance(src, np.ndarray):
        arr = src
        if arr.ndim not in (2, 3) or (arr.ndim == 3 and arr.shape[2] not in (1, 3, 4)):
            raise QueryError(f"image array must be HxW, HxWx3 or HxWx4, got shape {arr.shape}")
        if arr.ndim == 3 and arr.shape[2] == 1:
            arr = arr[:, :, 0]
        if arr.dtype != np.uint8:
            arr = _to_uint8(arr.astype(np.float64))
        return Image.fromarray(arr), "<array>"
    if not isinstance(src, (str, os.PathLike)):
        raise QueryError(f"image must be a path, a PIL image or an array, got {type(src).__name__}")
    path = Path(src)
    if not path.exists():
        raise QueryError(f"image not found: {path}")
    if not path.is_file():
        raise QueryError(f"image path is not a file: {path}")
    try:
        with warnings.catch_warnings():
            warnings.simplefilter("error", Image.DecompressionBombWarning)
            return Image.open(path), str(path)
    except (UnidentifiedImageError, ValueError):
        raise QueryError(f"not an image file (or an unsupported format): {path}") from None
    except (Image.DecompressionBombError, Image.DecompressionBombWarning):
        raise QueryError(f"image is too large to decode safely: {path}") from None
    except OSError as exc:
        raise QueryError(f"cannot read image {path}: {exc}") from None


def _to_uint8(arr: np.ndarray) -> np.ndarray:
    """Scale a 16-bit / integer / float array to 8 bits by its value range (16-bit: /257)."""
    arr = np.nan_to_num(arr, nan=0.0, posinf=0.0, neginf=0.0)
    hi = float(arr.max()) if arr.size else 0.0
    if hi <= 1.0:
        arr = arr * 255.0
    elif hi > 255.0:
        arr = arr * (255.0 / (65535.0 if hi <= 65535.0 else hi))
    return np.clip(np.rint(arr), 0, 255).astype(np.uint8)


def to_rgb(image: Image.Image, background: tuple[int, int, int] = GRAY) -> Image.Image:
    """RGB of any PIL mode: 16-bit and float scaled to 8 bits, transparency composited on ``background``."""
    mode = image.mode
    if mode == "RGB":
        return image
    if mode in ("I", "I;16", "I;16B", "I;16L", "I;16N", "F"):
        gray = _to_uint8(np.asarray(image, dtype=np.float64))
        return Image.fromarray(gray).convert("RGB")
    if mode == "P" and "transparency" in image.info:
        image = image.convert("RGBA")
        mode = "RGBA"
    if mode in ("RGBA", "LA", "RGBa", "La", "PA"):
        rgba = image.convert("RGBA")
        canvas = Image.new("RGB", rgba.size, background)
        canvas.paste(rgba, mask=rgba.getchannel("A"))
        return canvas
    return image.convert("RGB")


def load_photo(src, *, max_side: int = 2048, min_side: int = 16) -> Photo:
    """Open and validate a photo (path, PIL image or array) as RGB, downscaled to ``max_side``."""
    img, name = _open(src)
    try:
        img = ImageOps.exif_transpose(img) if name not in ("<PIL image>", "<array>") else img
        width, height = img.size
        if min(width, height) < min_side:
            raise QueryError(f"image is too small ({width}x{height}); need at least {min_side} px per side")
        if max(width, height) > max_side and img.format == "JPEG":
            img.draft("RGB", (max_side, max_side))  # decode at a reduced scale: fast for huge JPEGs
        img.load()
    except QueryError:
        raise
    except (OSError, SyntaxError, ValueError) as exc:
        reason = "truncated or corrupt" if "truncat" in str(exc).lower() else f"unreadable ({exc})"
        raise QueryError(f"image is {reason}: {name}") from None
    rgb = to_rgb(img)
    scale = 1.0
    if max(rgb.size) > max_side:
        scale = max_side / max(width, height)
        new = (max(1, round(width * scale)), max(1, round(height * scale)))
        rgb = rgb.resize(new, Image.BILINEAR)
    return Photo(rgb, (width, height), scale, name)


def parse_box(text: str | Box | list) -> Box:
    """``"x0,y0,x1,y1"`` (or a 4-sequence) in photo pixels -> floats, validated for shape."""
    if isinstance(text, str):
        parts = [p for p in re.split(r"[,\s]+", text.strip()) if p]
    else:
        parts = list(text) if text is not None else []
    try:
        vals = [float(p) for p in parts]
    except (TypeError, ValueError):
        raise QueryError(f"box must be four numbers x0,y0,x1,y1, got {text!r}") from None
    if len(vals) != 4 or not all(math.isfinite(v) for v in vals):
        raise QueryError(f"box must be four finite numbers x0,y0,x1,y1, got {text!r}")
    x0, y0, x1, y1 = vals
    if x1 <= x0 or y1 <= y0:
        raise QueryError(f"box {text!r} is empty: need x1 > x0 and y1 > y0")
    return (x0, y0, x1, y1)


def box_to_working(box: Box, photo: Photo, min_side: int) -> tuple[int, int, int, int]:
    """Clip a photo-pixel box to the photo and map it to integer working pixels."""
    w, h = photo.original_size
    x0, y0, x1, y1 = box
    cx0, cy0, cx1, cy1 = max(x0, 0.0), max(y0, 0.0), min(x1, float(w)), min(y1, float(h))
    if cx1 <= cx0 or cy1 <= cy0:
        raise QueryError(f"box {_fmt_box(box)} lies outside the {w}x{h} image")
    if min(cx1 - cx0, cy1 - cy0) < min_side:
        raise QueryError(f"box {_fmt_box(box)} is too small inside the {w}x{h} image (min {min_side} px)")
    s = photo.scale
    W, H = photo.image.size
    out = (
        int(math.floor(cx0 * s)),
        int(math.floor(cy0 * s)),
        int(math.ceil(cx1 * s)),
        int(math.ceil(cy1 * s)),
    )
    return (max(0, out[0]), max(0, out[1]), min(W, max(out[2], out[0] + 1)), min(H, max(out[3], out[1] + 1)))


def _fmt_box(box: Box) -> str:
    return ",".join(f"{v:g}" for v in box)


def load_mask(src, photo: Photo, min_side: int = 4) -> np.ndarray:
    """A boolean object mask (path, PIL image or array) of the photo's size, mapped to working scale."""
    if isinstance(src, np.ndarray) and src.dtype == bool:
        arr = src
    else:
        img, name = _open(src)
        try:
            img.load()
        except (OSError, SyntaxError, ValueError):
            raise QueryError(f"mask image is truncated or corrupt: {name}") from None
        if img.mode in ("RGBA", "LA", "PA") or (img.mode == "P" and "transparency" in img.info):
            rgba = img.convert("RGBA")
            alpha = np.asarray(rgba.getchannel("A"))
            # a cut-out (object opaque, rest transparent) is a mask by its alpha channel
            arr = alpha > 127 if alpha.min() < 255 else np.asarray(rgba.convert("L")) > 127
        elif img.mode == "P":
            arr = np.asarray(img) > 0  # palette index 0 = background (label images)
        else:
            values = np.asarray(img if img.mode in ("1", "L", "I", "I;16", "F") else img.convert("L"))
            values = values.astype(np.float64)
            hi = values.max() if values.size else 0.0
            arr = values > (0.5 if hi <= 1.0 else hi / 2.0)
    w, h = photo.original_size
    if arr.shape != (h, w):
        raise QueryError(f"mask is {arr.shape[1]}x{arr.shape[0]} but the image is {w}x{h}")
    if not arr.any():
        raise QueryError("mask is empty (no object pixels)")
    ys, xs = np.nonzero(arr)
    if min(xs.max() - xs.min() + 1, ys.max() - ys.min() + 1) < min_side:
        raise QueryError(f"mask covers less than {min_side} px in width or height")
    if photo.scale != 1.0:
        arr = np.asarray(Image.fromarray(arr).resize(photo.image.size, Image.NEAREST), dtype=bool)
        if not arr.any():
            raise QueryError("mask vanishes when the image is downscaled; pass a larger mask")
    return arr


_WORD = re.compile(r"[^\W\d_]{2,}", re.UNICODE)


def clean_prompt(prompt, max_chars: int = 300) -> str:
    """Whitespace-normalised prompt; rejects empty, wordless or overlong prompts."""
    if not isinstance(prompt, str):
        raise QueryError(f"prompt must be text, got {type(prompt).__name__}")
    text = " ".join("".join(c if c.isprintable() else " " for c in prompt).split())
    if not text:
        raise QueryError('prompt is empty: name the object, e.g. --prompt "the yellow mustard bottle"')
    if len(text) > max_chars:
        raise QueryError(f"prompt is too long ({len(text)} characters; at most {max_chars})")
    if not _WORD.search(text):
        raise QueryError(f'prompt {text!r} has no words: name the object, e.g. "the yellow mustard bottle"')
    return text
