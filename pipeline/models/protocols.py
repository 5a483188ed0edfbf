"""Small protocols every model adapter implements.

Only adapters touch models. Everything around them is plain data: PIL images and strings in, Python
strings or float32 NumPy arrays (L2-normalised rows) out.
"""

from __future__ import annotations

from typing import Protocol, runtime_checkable

import numpy as np
from PIL import Image


@runtime_checkable
class Captioner(Protocol):
    """Writes one caption per image."""

    model_id: str

    def caption(self, images: list[Image.Image], prompt: str) -> list[str]: ...


@runtime_checkable
class TextEncoder(Protocol):
    """Embeds texts into L2-normalised float32 rows."""

    model_id: str
    dim: int

    def encode_text(self, texts: list[str]) -> np.ndarray: ...


@runtime_checkable
class ImageEncoder(Protocol):
    """Embeds images into L2-normalised float32 rows."""

    model_id: str
    dim: int

    def encode_image(self, images: list[Image.Image]) -> np.ndarray: ...


@runtime_checkable
class Detector(Protocol):
    """Open-vocabulary box detector: returns boxes (x0, y0, x1, y1) with scores, best first."""

    model_id: str

    def detect(
        self, image: Image.Image, prompt: str
    ) -> list[tuple[tuple[float, float, float, float], float]]: ...


@runtime_checkable
class Segmenter(Protocol):
    """Box-prompted segmenter: returns a boolean HxW mask."""

    model_id: str

    def segment(self, image: Image.Image, box: tuple[float, float, float, float]) -> np.ndarray: ...


def l2_normalise(x: np.ndarray) -> np.ndarray:
    """Row-wise L2 normalisation in float32 (zero rows stay zero)."""
    x = np.asarray(x, dtype=np.float32)
    if x.ndim == 1:
        x = x[None, :]
    n = np.linalg.norm(x, axis=1, keepdims=True)
    return (x / np.maximum(n, 1e-12)).astype(np.float32)
