"""The ROI's vectors, one small strategy per stage-1 space (chosen by the roles a profile has).

* ``image``-to-caption (paper): the ROI's CLIP image embedding is compared with caption CLIP text
  embeddings, as in OSCAR.
* ``caption``-to-caption (offline, no CLIP): the ROI gets an attribute caption of its own, embedded with
  the same text encoder as the library captions, and is matched text to text.

Both can add the prompt's text embedding (``prompt_weight`` > 0 blends it into the stage-1 query vector).
Stage 2 always uses the view encoder on the ROI image.
"""

from __future__ import annotations

from collections.abc import Callable

import numpy as np

from pipeline.query.results import QueryEmbedding
from pipeline.query.roi import Roi

ModelGetter = Callable[[str], object | None]


def _one(rows: np.ndarray) -> np.ndarray:
    return np.asarray(rows, dtype=np.float32).reshape(len(rows), -1)[0]


class ImageToCaption:
    """Paper: CLIP image embedding of the ROI in the CLIP text space of the captions."""

    space = "image"

    def roles(self, with_prompt: bool) -> tuple[str, ...]:
        return ("clip_image_encoder", "view_encoder") + (("text_encoder",) if with_prompt else ())

    def text_vectors(self, model: ModelGetter, roi: Roi, prompt: str | None):
        """(ROI vector, prompt vector or None, ROI caption or None) in the caption-embedding space."""
        roi_vec = _one(model("clip_image_encoder").encode_image([roi.image]))
        prompt_vec = _one(model("text_encoder").encode_text([prompt])) if prompt is not None else None
        return roi_vec, prompt_vec, None


class CaptionToCaption:
    """Offline: the ROI's own attribute caption, embedded like the library's captions."""

    space = "caption"

    def roles(self, with_prompt: bool) -> tuple[str, ...]:
        return ("captioner", "text_encoder", "view_encoder")

    def text_vectors(self, model: ModelGetter, roi: Roi, prompt: str | None):
        captioner = model("captioner")
        if roi.roi_mode == "bbox" and hasattr(captioner, "caption_masked") and roi.crop_mask is not None:
            # a raw crop has no gray background to find the object by: the whole crop is the object
            caption = captioner.caption_masked(roi.image, roi.crop_mask)
        else:
            # object on gray, exactly like the onboarding renders: caption it the same way
            caption = captioner.caption([roi.image], "")[0]
        texts = [caption] if prompt is None else [caption, prompt]
        rows = np.asarray(model("text_encoder").encode_text(texts), dtype=np.float32)  # one batch
        return rows[0], (rows[1] if prompt is not None else None), caption


def strategy_for(has_clip_image: bool) -> ImageToCaption | CaptionToCaption:
    return ImageToCaption() if has_clip_image else CaptionToCaption()


def embed_roi(
    strategy: ImageToCaption | CaptionToCaption, model: ModelGetter, roi: Roi, prompt: str, with_prompt: bool
) -> QueryEmbedding:
    """All vectors of one ROI (each model called once)."""
    text_vec, prompt_vec, caption = strategy.text_vectors(model, roi, prompt if with_prompt else None)
    image_vec = _one(model("view_encoder").encode_image([roi.image]))
    return QueryEmbedding(text_vec, image_vec, prompt_vec, caption)


def stage1_vector(emb: QueryEmbedding, prompt_weight: float) -> np.ndarray:
    """Query vector of stage 1: ``(1-w) * roi + w * prompt``.

    Not renormalised on purpose: the inner product with a caption is then exactly the weighted mean of
    the two cosines, so tau keeps its meaning as a similarity.
    """
    w = float(prompt_weight)
    if emb.prompt_vec is None or w <= 0.0:
        return emb.text_space.astype(np.float32)
    return ((1.0 - w) * emb.text_space + w * emb.prompt_vec).astype(np.float32)
