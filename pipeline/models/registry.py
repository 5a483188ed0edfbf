"""Registry of model adapters keyed by (role, backend) and the one factory that builds them.

Adapters register themselves with :func:`register`; :func:`create_model` builds one from a
:class:`ModelSpec`. Tests pass tiny local models through the same factory users call.
"""

from __future__ import annotations

import importlib
from collections.abc import Callable
from dataclasses import dataclass, field, replace
from typing import Any

#: role -> backend -> factory(model_id, **options)
_REGISTRY: dict[str, dict[str, Callable[..., Any]]] = {}

#: modules that register adapters on import (imported lazily so CLIs start fast)
_ADAPTER_MODULES = ("pipeline.models.offline", "pipeline.models.hf")

ROLES = ("captioner", "text_encoder", "image_encoder", "clip_image_encoder", "detector", "segmenter")


class ModelLoadError(RuntimeError):
    """A model could not be loaded; the message says which and how to fix it."""


@dataclass(frozen=True)
class ModelSpec:
    """What to build for one role: a backend key, a hub id or local directory, and options."""

    backend: str
    model_id: str
    options: dict[str, Any] = field(default_factory=dict)

    def with_model_id(self, model_id: str) -> ModelSpec:
        return replace(self, model_id=model_id)

    def key(self) -> str:
        """Stable identity used in fingerprints and stored ``encoder_id`` columns."""
        return f"{self.backend}:{self.model_id}"


def register(role: str, backend: str) -> Callable[[Callable[..., Any]], Callable[..., Any]]:
    """Decorator: register ``factory`` as the builder of ``backend`` models for ``role``."""

    def deco(factory: Callable[..., Any]) -> Callable[..., Any]:
        _REGISTRY.setdefault(role, {})[backend] = factory
        return factory

    return deco


def _load_adapters() -> None:
    for mod in _ADAPTER_MODULES:
        importlib.import_module(mod)


def backends(role: str) -> list[str]:
    """Names of the registered backends for ``role``."""
    _load_adapters()
    return sorted(_REGISTRY.get(role, {}))


def create_model(role: str, spec: ModelSpec, **overrides: Any) -> Any:
    """Build the adapter for ``role`` described by ``spec`` (options may be overridden)."""
    _load_adapters()
    try:
        factory = _REGISTRY[role][spec.backend]
    except KeyError:
        raise ModelLoadError(
            f"no {role} backend {spec.backend!r}; known: {', '.join(sorted(_REGISTRY.get(role, {})))}"
        ) from None
    return factory(spec.model_id, **{**spec.options, **overrides})
