"""Model adapters (offline and Hugging Face) behind small protocols, built through one registry."""

from pipeline.models.protocols import Captioner, Detector, ImageEncoder, Segmenter, TextEncoder, l2_normalise
from pipeline.models.registry import ModelLoadError, ModelSpec, backends, create_model, register

__all__ = [
    "Captioner",
    "Detector",
    "ImageEncoder",
    "ModelLoadError",
    "ModelSpec",
    "Segmenter",
    "TextEncoder",
    "backends",
    "create_model",
    "l2_normalise",
    "register",
]
