"""The query path's model adapters of one profile, built once on first use (thread-safe) and shared by
:meth:`pipeline.query.Retriever.reopened` snapshots.

Adapters come from :func:`pipeline.models.registry.create_model` (imported when the first one is built:
``--help`` and stores without models stay light) unless injected by role (tests, notebooks).
"""

from __future__ import annotations

import threading
import time
from collections.abc import Iterable


class QueryModels:
    """Role -> adapter of ``profile`` on ``device``; ``adapters`` holds the built and injected ones."""

    def __init__(self, profile, device: str | None = None, adapters: dict[str, object] | None = None):
        self.profile = profile
        self.device = device
        self.adapters: dict[str, object] = dict(adapters or {})
        self.load_seconds: dict[str, float] = {}  # role -> seconds its adapter took to build
        self._lock = threading.Lock()

    def get(self, role: str):
        """The adapter of ``role`` (built on first use), or ``None`` when the profile has no such role."""
        if role in self.adapters:
            return self.adapters[role]
        spec = getattr(self.profile, role, None)
        if spec is None:
            return None
        from pipeline.models.registry import create_model

        with self._lock:  # concurrent first uses build the model once
            if role in self.adapters:
                return self.adapters[role]
            extra = {} if self.device in (None, "", "auto") else {"device": self.device}
            t0 = time.perf_counter()
            adapter = create_model(role, spec, **extra)
            self.load_seconds[role] = time.perf_counter() - t0
            self.adapters[role] = adapter
        return adapter

    def load(self, roles: Iterable[str]) -> None:
        """Build the adapters of ``roles`` now (not yet loaded ones only)."""
        for role in roles:
            self.get(role)

    def snapshot(self) -> dict[str, object]:
        """The adapters built so far (to hand to a reopened Retriever)."""
        with self._lock:
            return dict(self.adapters)

    def available(self, roles: Iterable[str]) -> list[str]:
        """Those of ``roles`` that are injected or that the profile has."""
        return [r for r in roles if r in self.adapters or getattr(self.profile, r, None) is not None]


def roles_for(embedding_roles: Iterable[str], source: str | None, roi_mode: str = "segm") -> list[str]:
    """Roles a query needs: the embedding roles, plus what finds the object when it comes from ``source``
    ("detector": detector and segmenter; "box": segmenter; "mask" or None: nothing more)."""
    roles = list(embedding_roles)
    if source == "detector":
        roles.append("detector")
    if source in ("detector", "box") and roi_mode == "segm":
        roles.append("segmenter")
    return roles
