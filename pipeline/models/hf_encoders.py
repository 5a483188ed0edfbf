"""Hugging Face embedding adapters: CLIP text, CLIP image and DINOv2 (L2-normalised float32 rows)."""

from __future__ import annotations

from typing import Any

import numpy as np
from PIL import Image

from pipeline.models.hf_common import HFAdapter, batched, dtype_kwargs, move_inputs, register_adapter, rgb
from pipeline.models.protocols import l2_normalise
from pipeline.models.registry import ModelLoadError


def _clip_tower(kind: str, source: str, local_files_only: bool, dtype: Any) -> Any:
    """Load only the text or vision tower (with its projection) of a CLIP checkpoint.

    transformers 5 gotcha: the towers' sub-configs carry their own ``projection_dim`` (default 512) that
    can disagree with the checkpoint's top-level one, so the top-level value is copied over first.
    """
    from transformers import AutoConfig, CLIPTextModelWithProjection, CLIPVisionModelWithProjection

    cls = CLIPTextModelWithProjection if kind == "text" else CLIPVisionModelWithProjection
    config = AutoConfig.from_pretrained(source, local_files_only=local_files_only)
    sub = getattr(config, f"{kind}_config", None)
    if sub is not None:  # a full CLIPModel checkpoint
        sub.projection_dim = getattr(config, "projection_dim", sub.projection_dim)
        config = sub
    elif config.model_type != f"clip_{kind}_model":
        raise ModelLoadError(f"{source!r} is not a CLIP checkpoint (model_type {config.model_type!r})")
    return cls.from_pretrained(
        source, config=config, local_files_only=local_files_only, **dtype_kwargs(dtype)
    )


class ClipTextEncoder(HFAdapter):
    """CLIP text tower + projection; texts truncated to ``max_length`` tokens (77 in the reference)."""

    default_batch_size = 64

    def __init__(
        self, model_id: str, *, role: str = "text_encoder", max_length: int = 77, **common: Any
    ) -> None:
        super().__init__(model_id, role=role, **common)

        def load(source: str, local_files_only: bool) -> tuple[Any, Any]:
            from transformers import AutoTokenizer

            model = _clip_tower("text", source, local_files_only, self.dtype)
            tokenizer = AutoTokenizer.from_pretrained(source, local_files_only=local_files_only)
            return model, tokenizer

        model, self.tokenizer = self._load(load)
        self.model = self._place(model)
        self.dim = int(self.model.config.projection_dim)
        self.max_length = min(int(max_length), int(self.model.config.max_position_embeddings))

    def encode_text(self, texts: list[str]) -> np.ndarray:
        import torch

        rows = []
        for chunk in batched(list(texts), self.batch_size):
            enc = self.tokenizer(
                [str(t) for t in chunk],
                padding=True,
                truncation=True,
                max_length=self.max_length,
                return_tensors="pt",
            )
            with torch.inference_mode():
                out = self.model(**move_inputs(enc, self.device))
            rows.append(out.text_embeds.float().cpu().numpy())
        if not rows:
            return np.zeros((0, self.dim), dtype=np.float32)
        return l2_normalise(np.concatenate(rows))


class _ImageEncoder(HFAdapter):
    """Shared batching for the image encoders: subclasses load ``self.model``/``self.processor`` and pool."""

    default_batch_size = 32
    dim: int

    def _pool(self, out: Any) -> Any:
        raise NotImplementedError

    def encode_image(self, images: list[Image.Image]) -> np.ndarray:
        import torch

        rows = []
        for chunk in batched(list(images), self.batch_size):
            enc = self.processor(images=rgb(chunk), return_tensors="pt")
            with torch.inference_mode():
                out = self.model(**move_inputs(enc, self.device, self.dtype))
            rows.append(self._pool(out).float().cpu().numpy())
        if not rows:
            return np.zeros((0, self.dim), dtype=np.float32)
        return l2_normalise(np.concatenate(rows))


class ClipImageEncoder(_ImageEncoder):
    """CLIP vision tower + projection: images into the CLIP text space."""

    def __init__(self, model_id: str, *, role: str = "clip_image_encoder", **common: Any) -> None:
        super().__init__(model_id, role=role, **common)

        def load(source: str, local_files_only: bool) -> tuple[Any, Any]:
            from transformers import AutoImageProcessor

            model = _clip_tower("vision", source, local_files_only, self.dtype)
            processor = AutoImageProcessor.from_pretrained(source, local_files_only=local_files_only)
            return model, processor

        model, self.processor = self._load(load)
        self.model = self._place(model)
        self.dim = int(self.model.config.projection_dim)

    def _pool(self, out: Any) -> Any:
        return out.image_embeds


class Dinov2Encoder(_ImageEncoder):
    """DINOv2: embedding = mean over all tokens (CLS included) of ``last_hidden_state``."""

    def __init__(self, model_id: str, *, role: str = "view_encoder", **common: Any) -> None:
        super().__init__(model_id, role=role, **common)

        def load(source: str, local_files_only: bool) -> tuple[Any, Any]:
            from transformers import AutoImageProcessor, AutoModel

            model = AutoModel.from_pretrained(
                source, local_files_only=local_files_only, **dtype_kwargs(self.dtype)
            )
            processor = AutoImageProcessor.from_pretrained(source, local_files_only=local_files_only)
            return model, processor

        model, self.processor = self._load(load)
        self.model = self._place(model)
        self.dim = int(self.model.config.hidden_size)

    def _pool(self, out: Any) -> Any:
        return out.last_hidden_state.mean(dim=1)


register_adapter(ClipTextEncoder, ("text_encoder", "clip_text"))
register_adapter(ClipImageEncoder, ("image_encoder", "clip_image"), ("clip_image_encoder", "clip_image"))
register_adapter(Dinov2Encoder, ("image_encoder", "dinov2"), ("view_encoder", "dinov2"))
