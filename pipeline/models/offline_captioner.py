"""A deterministic, weight-free captioner: describes the object's colours, shape and surface in English.

It stands in for the paper's vision-language captioner in the ``offline`` profile. Captions of a CAD model's
renders and of a query ROI are written by the same rules, so the text encoder can compare them, and they read
like a short description a person (or a prompt such as "the yellow mustard bottle") would give.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from PIL import Image
from scipy import ndimage

from pipeline.models.offline_imageops import (
    BACKGROUND_TOLERANCE,
    Silhouette,
    object_crop,
    rgb_to_hsv,
    rgb_to_lab,
    silhouette,
)

DEFAULT_MODEL_ID = "oscar-attribute-captioner-v1"
EMPTY_CAPTION = "An empty image with no visible object."

#: working resolution (the object's box is fitted into a square of this side)
WORK_SIZE = 128
#: a colour is named when it covers at least this fraction of the object (the main colour always is)
MIN_COLOUR_SHARE = 0.10
MAX_COLOURS = 3
#: a gradient of the lightness (L units per working pixel) above this counts as an edge
EDGE_THRESHOLD = 6.0

#: palette names, in the order used for per-pixel label codes
COLOURS = (
    "black",
    "gray",
    "white",
    "red",
    "orange",
    "yellow",
    "green",
    "blue",
    "purple",
    "pink",
    "brown",
    "beige",
)
_IDX = {name: i for i, name in enumerate(COLOURS)}
_CHROMATIC = {"red", "orange", "yellow", "green", "blue", "purple", "pink", "brown", "beige"}


def colour_labels(hsv: np.ndarray) -> np.ndarray:
    """Name each pixel with a palette index (vectorised rules in HSV, hue in degrees)."""
    h, s, v = hsv[..., 0], hsv[..., 1], hsv[..., 2]
    lab = np.full(h.shape, _IDX["gray"], dtype=np.int8)
    achromatic = (s < 0.18) | (s * v < 0.07)
    lab[achromatic & (v >= 0.72)] = _IDX["white"]
    hue = np.select(
        [(h < 15) | (h >= 340), h < 38, h < 70, h < 165, h < 255, h < 290],
        [_IDX["red"], _IDX["orange"], _IDX["yellow"], _IDX["green"], _IDX["blue"], _IDX["purple"]],
        default=_IDX["pink"],
    ).astype(np.int8)
    warm = (hue == _IDX["orange"]) | (hue == _IDX["yellow"])
    hue = np.where(warm & (v < np.where(hue == _IDX["orange"], 0.6, 0.45)), _IDX["brown"], hue)
    hue = np.where(warm & (s < 0.45) & (v >= 0.6) & (hue != _IDX["brown"]), _IDX["beige"], hue)
    hue = np.where((hue == _IDX["red"]) & (s < 0.45) & (v >= 0.75), _IDX["pink"], hue)
    hue = np.where((hue == _IDX["pink"]) & (v < 0.5), _IDX["purple"], hue)
    chromatic = ~achromatic
    lab[chromatic] = hue[chromatic]
    lab[v < 0.2] = _IDX["black"]
    lab[achromatic & (v < 0.28)] = _IDX["black"]
    return lab


@dataclass(frozen=True)
class _Colours:
    names: list[str]  # up to MAX_COLOURS, biggest share first
    shares: list[float]
    main_shade: str  # "dark ", "light " or ""
    mean_lightness: float
    highlight_share: float
    n_significant: int  # colours covering at least 5 %


def _colours(rgb: np.ndarray, mask: np.ndarray) -> _Colours:
    px = rgb[mask]
    hsv = rgb_to_hsv(px)
    labels = colour_labels(hsv)
    counts = np.bincount(labels, minlength=len(COLOURS)).astype(np.float64)
    shares = counts / counts.sum()
    gray = labels == _IDX["gray"]
    if shares[_IDX["gray"]] >= MIN_COLOUR_SHARE and hsv[gray, 2].std() > 0.15:
        silver = "silver"  # strongly shaded neutral surface: metallic
    else:
        silver = "gray"
    order = np.argsort(-shares, kind="stable")
    picked = [int(i) for i in order[:MAX_COLOURS] if shares[i] >= MIN_COLOUR_SHARE] or [int(order[0])]
    names = [silver if COLOURS[i] == "gray" else COLOURS[i] for i in picked]
    main = labels == picked[0]
    mv, ms = float(hsv[main, 2].mean()), float(hsv[main, 1].mean())
    shade = ""
    if names[0] in _CHROMATIC | {"gray"}:
        if mv < 0.4:
            shade = "dark "
        elif mv > 0.85 and ms < 0.5 and names[0] not in ("beige", "pink"):
            shade = "light "
    lightness = rgb_to_lab(px)[:, 0]
    highlight = float(((hsv[:, 2] > 0.93) & (hsv[:, 1] < 0.12)).mean())
    return _Colours(
        names,
        [float(shares[i]) for i in picked],
        shade,
        float(lightness.mean()),
        highlight,
        int((shares >= 0.05).sum()),
    )


def _join(words: list[str]) -> str:
    return words[0] if len(words) == 1 else ", ".join(words[:-1]) + " and " + words[-1]


def _a(phrase: str) -> str:
    return ("An " if phrase[0] in "aeiou" else "A ") + phrase


def _colour_phrase(c: _Colours) -> str:
    main = c.main_shade + c.names[0]
    if len(c.names) == 1:
        return _a(f"{main} object")
    if c.shares[0] >= 0.5:
        return f"A mostly {main} object with {_join(c.names[1:])}"
    return _a(f"{_join([main, *c.names[1:]])} object")


def _proportions(aspect: float, sil: Silhouette) -> tuple[str, str]:
    """Words for the size and the proportion clause, e.g. ("tall and narrow", "about 2.4 times taller than wide")."""
    if sil.elongation >= 3.0 and 0.5 <= aspect <= 2.0:
        return "long and thin, lying diagonally", f"about {sil.elongation:.1f} times longer than thick"
    if aspect >= 1.25:
        return ("tall and narrow" if aspect >= 2.2 else "tall"), f"about {aspect:.1f} times taller than wide"
    if aspect <= 0.8:
        wide = 1.0 / aspect
        return ("wide and low" if wide >= 2.2 else "wide"), f"about {wide:.1f} times wider than tall"
    return "compact", "about as tall as wide"


def _outline(aspect: float, s: Silhouette) -> str:
    """The silhouette clause, with a coarse object type only when the shape cues agree.

    Thresholds were set on synthetic shapes and on rough point-splat renders of the YCB-Video objects; the 2D silhouette
    cannot tell a box seen corner-on from a can, so "can-shaped" means "upright, symmetric, rounded ends".
    """
    symmetric = "symmetric " if s.symmetry >= 0.9 else ""
    boxy = s.extent >= 0.9 and s.corner_fill >= 0.8
    if (
        aspect >= 1.5
        and s.symmetry >= 0.85
        and s.top_width <= 0.72
        and s.bottom_width >= 0.8
        and s.solidity >= 0.85
    ):
        return f"{symmetric}rounded bottle-like silhouette with a narrow top"
    if max(aspect, 1 / aspect) >= 6.0 or (s.elongation >= 4.0 and not boxy):
        if s.bend >= 0.05 and s.ellipse_iou >= 0.72:
            return "elongated, long thin curved silhouette"
        if s.solidity < 0.8 or s.ellipse_iou < 0.75:
            return "elongated, long thin tool-like silhouette"
        return "elongated, long thin rod-like silhouette"
    if boxy:
        outline = "square" if 0.85 <= aspect <= 1.18 else "rectangular"
        return f"{outline} box-shaped silhouette"
    if (
        0.6 <= aspect <= 2.5
        and s.solidity >= 0.95
        and s.extent >= 0.85
        and s.symmetry >= 0.92
        and s.corner_fill >= 0.3
        and s.width_flatness <= 0.05
    ):
        return "upright cylindrical can-shaped silhouette"
    if s.corner_fill <= 0.3 and s.solidity >= 0.93 and 0.72 <= s.extent <= 0.9:
        if 0.8 <= aspect <= 1.25 and s.circularity >= 0.8:
            return "round ball-shaped silhouette"
        if aspect < 0.7:
            return "oval, flat disc-like silhouette"
        return f"{symmetric}oval silhouette"
    if s.elongation >= 2.0 and s.bend >= 0.08:
        return "curved, elongated silhouette"
    if s.solidity < 0.8 or s.extent < 0.55:
        return "irregular tool-like silhouette" if s.elongation >= 2.5 else "irregular silhouette"
    if s.extent >= 0.8 and s.solidity >= 0.93:
        return f"{symmetric}blocky silhouette"
    if s.corner_fill < 0.4:
        return f"{symmetric}rounded silhouette"
    return f"{symmetric}irregular silhouette"


def _surface(rgb: np.ndarray, mask: np.ndarray, c: _Colours) -> str:
    lightness = rgb_to_lab(rgb)[..., 0]
    interior = ndimage.binary_erosion(mask, iterations=2)
    spread = float(lightness[interior].std()) if interior.any() else float(lightness[mask].std())
    if interior.sum() < max(16, 0.25 * mask.sum()):  # too thin to see a surface: judge by shading only
        return "plain and smooth" if spread < 8 else "mostly plain with a few markings"
    gy, gx = np.gradient(lightness)
    edges = float((np.hypot(gx, gy)[interior] > EDGE_THRESHOLD).mean())
    if edges < 0.03:
        return "plain and smooth" if spread < 8 else "plain with smooth shading"
    if edges < 0.10:
        return "mostly plain with a few markings"
    if c.n_significant >= 2:
        return "printed with text or graphics"
    return "patterned or textured"


def _brightness(c: _Colours) -> str:
    words = []
    if c.mean_lightness < 30 and c.names[0] != "black" and not c.main_shade:
        words.append("dark overall")
    elif c.mean_lightness > 85 and c.names[0] != "white":
        words.append("light-coloured")
    if 0.01 <= c.highlight_share <= 0.2 and c.names[0] not in ("white", "gray", "silver"):
        words.append("with shiny highlights")
    return ", ".join(words)


class AttributeCaptioner:
    """Describes an object on the gray background: colours, proportions, silhouette and surface."""

    def __init__(self, model_id: str = DEFAULT_MODEL_ID, tolerance: int = BACKGROUND_TOLERANCE) -> None:
        self.model_id = model_id
        self.tolerance = int(tolerance)

    def caption(self, images: list[Image.Image], prompt: str = "") -> list[str]:
        """One caption per image; ``prompt`` is accepted for the protocol and ignored."""
        return [self._describe(image, None) for image in images]

    def caption_masked(self, image: Image.Image, mask: np.ndarray) -> str:
        """Caption with an explicit boolean HxW object mask instead of the gray-background rule."""
        return self._describe(image, mask)

    def _describe(self, image: Image.Image, mask: np.ndarray | None) -> str:
        crop = object_crop(image, WORK_SIZE, mask=mask, tolerance=self.tolerance, whole_frame_if_empty=False)
        if crop is None or not crop.mask.any():
            return EMPTY_CAPTION
        colours = _colours(crop.rgb, crop.mask)
        phrase = _colour_phrase(colours)
        sil = silhouette(crop.filled)
        if sil is None or min(crop.box_hw) < 4:
            return f"{phrase}, too small to make out its shape."
        aspect = crop.box_aspect
        size, proportion = _proportions(aspect, sil)
        parts = [
            f"{phrase}, {size} ({proportion})",
            _outline(aspect, sil),
            _surface(crop.rgb, crop.mask, colours),
        ]
        brightness = _brightness(colours)
        if brightness:
            parts.append(brightness)
        return ", ".join(parts) + "."
