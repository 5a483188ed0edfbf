"""Query settings per profile: the paper's values by default, every one overridable.

Thresholds live in the space of the stage-1 scores, which differs per profile:

* ``paper``: cosine between the ROI's CLIP image embedding and caption CLIP text embeddings; tau = 0.37
  (paper and reference scripts); fallback top-10 counted in captions (the paper's k; the reference scripts
  keep the top 15 captions as their distinct meshes), or in meshes with ``fallback_unit="meshes"``.
* ``offline``: weighted mean of two MiniLM cosines (ROI attribute caption vs library captions, and the
  prompt vs library captions). Attribute captions share a template, so these cosines run much higher than
  CLIP's; tau was measured on onboarded YCB meshes (see docs/query.md, "Offline threshold").
"""

from __future__ import annotations

from dataclasses import dataclass, replace

from pipeline.query.modes import MODES as MODES  # re-exported: the settings name the modes

GRAY = (205, 205, 205)
ROI_MODES = ("segm", "bbox")


@dataclass(frozen=True)
class QuerySettings:
    """Defaults of one profile's query path."""

    threshold: float  # stage-1 tau
    mode: str = "two-stage"  # the step list ranking runs (pipeline.query.steps.STEP_LISTS)
    fallback_k: int = 10  # stage-1 top-k when nothing passes tau (reference scripts: 15)
    fallback_unit: str = "captions"  # what fallback_k counts: caption rows (paper) or "meshes"
    prompt_weight: float = 0.0  # weight of the prompt's text embedding in the stage-1 query vector
    top: int = 5
    max_side: int = 2048  # larger photos are downscaled (boxes and masks are given in original pixels)
    min_side: int = 16  # smaller photos are rejected
    min_roi_side: int = 4  # ROIs (box or mask extent) smaller than this are rejected
    max_prompt_chars: int = 300
    background: tuple[int, int, int] = GRAY
    box_segmenter: str = "grabcut"  # box -> mask without a segmenter model: "grabcut" | "border"
    verify: bool = False  # local-feature verification of the top candidates (pipeline.query.verify)
    verify_top: int = 20  # candidates verified (by global score)
    verify_weight: float = 0.3  # weight of the inlier term in the fused score
    stage1: str = "auto"  # "exact" | "index" | "auto" (index from 1M caption rows): pipeline.index.choose
    accept_threshold: float | None = None  # open-set operating point (None: the calibration's default)
    accept_model: str | None = None  # acceptance calibration JSON (None: the one shipped for the profile)
    # fusion with the learned view encoder (pipeline.query.fusion), when the store has its embeddings:
    # fitted on synthetic queries only, tested on the labelled photos (bench/learned_ltr.py, docs/results.md
    # sections 7.2-7.4: refitted for block 11's CLS on exposure-normalised images, bench/learned_exposure.py;
    # three decimals, since two move ranks on the dumps); the learned cosine gets 1 - desc - text - prompt
    # = 0.822
    fuse_desc: float = 0.118  # weight of the descriptor cosine
    fuse_text: float = 0.005  # weight of the ROI caption's text score
    fuse_prompt: float = 0.055  # weight of the prompt's text score
    fuse_verify_weight: float = 0.072  # weight of the inlier term when fusing (verify_weight without fusion)
    fuse_all: bool = (
        True  # two-stage mode fuses every model (the text score is a term) instead of cutting at tau
    )
    # the store's query adapter (pipeline.adapter), when it has one fitted on exactly what the query reads:
    # the ranking uses the adapted learned cosine with these weights (fitted on the synthetic sets with
    # the adapted cue, never on the photos: bench/adapter_fusion.py, docs/results.md section 11); the
    # open-set verdict keeps the plain scores and the weights above
    adapter: bool = True
    adapter_fuse_desc: float = 0.150
    adapter_fuse_text: float = 0.035
    adapter_fuse_prompt: float = 0.095
    adapter_fuse_verify_weight: float = 0.117
    # ... up to this many models: a larger library keeps stage 1's tau cut (and its index), and fuses the
    # shortlist, so a query never ranks every view of a million models
    fuse_all_max_models: int = 20_000

    def with_changes(self, **changes) -> QuerySettings:
        return replace(self, **{k: v for k, v in changes.items() if v is not None})


PROFILE_SETTINGS: dict[str, QuerySettings] = {
    "paper": QuerySettings(threshold=0.37),
    # measured on the 78 YCB meshes (novel-view queries, prompts from the names): docs/query.md
    "offline": QuerySettings(threshold=0.45, prompt_weight=0.5, verify=True),
}


def settings_for(profile: str) -> QuerySettings:
    """Query defaults of ``profile`` (unknown profiles use the paper's values)."""
    return PROFILE_SETTINGS.get(profile, PROFILE_SETTINGS["paper"])
