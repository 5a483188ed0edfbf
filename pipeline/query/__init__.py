"""Query: a photo + a prompt -> ranked CAD models from an onboarded store (``python -m pipeline.query``).

The public API is :class:`Retriever` (see :mod:`pipeline.query.api`); the rest are its records. Names
are imported lazily so that ``python -m pipeline.query --help`` starts instantly.
"""

from __future__ import annotations

import importlib

_EXPORTS = {
    "Retriever": "pipeline.query.api",
    "QueryError": "pipeline.query.errors",
    "Candidate": "pipeline.query.results",
    "QueryEmbedding": "pipeline.query.results",
    "QueryResult": "pipeline.query.results",
    "Roi": "pipeline.query.roi",
    "QuerySettings": "pipeline.query.settings",
}
__all__ = sorted(_EXPORTS)


def __getattr__(name: str):
    if name in _EXPORTS:
        return getattr(importlib.import_module(_EXPORTS[name]), name)
    raise AttributeError(f"module 'pipeline.query' has no attribute {name!r}")
