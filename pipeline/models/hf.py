"""Hugging Face ``transformers`` adapters of the ``paper`` profile, registered on import.

* captioner / llava: :class:`LlavaCaptioner`
* text_encoder / clip_text: :class:`ClipTextEncoder`
* clip_image_encoder and image_encoder / clip_image: :class:`ClipImageEncoder`
* view_encoder and image_encoder / dinov2: :class:`Dinov2Encoder`
* detector / grounding_dino: :class:`GroundingDinoDetector`
* segmenter / sam: :class:`SamSegmenter`

Every factory is ``f(model_id, **options)`` with ``model_id`` a hub id or a local directory and the common
options ``device`` ("auto"), ``dtype`` ("auto": bf16 on GPU, fp16 for LLaVA, fp32 for the detector and
segmenter, fp32 on CPU), ``batch_size`` and ``local_files_only`` (default: on when ``HF_HUB_OFFLINE=1``).
A model that cannot be loaded raises :class:`~pipeline.models.registry.ModelLoadError` with one line.
"""

from __future__ import annotations

from pipeline.models.hf_common import HFAdapter
from pipeline.models.hf_encoders import ClipImageEncoder, ClipTextEncoder, Dinov2Encoder
from pipeline.models.hf_grounded import GroundingDinoDetector, SamSegmenter, grounding_prompt
from pipeline.models.hf_llava import LlavaCaptioner

__all__ = [
    "ClipImageEncoder",
    "ClipTextEncoder",
    "Dinov2Encoder",
    "GroundingDinoDetector",
    "HFAdapter",
    "LlavaCaptioner",
    "SamSegmenter",
    "grounding_prompt",
]
