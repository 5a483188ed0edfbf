"""Onboarding stages: callables over Arrow tables, each holding its model for its whole life.

Every stage maps an input ``pa.Table`` to an output ``pa.Table`` whose rows either conform to a store
table or carry an ``error`` (one row per failed mesh), so the same code runs in the local executor and
under Ray Data ``map_batches``. :func:`split_errors` separates the two.
"""

from pipeline.onboard.stages.base import ERROR_FIELDS, split_errors
from pipeline.onboard.stages.caption import CaptionStage
from pipeline.onboard.stages.embed import ImageEmbedStage, TextEmbedStage
from pipeline.onboard.stages.render import RENDER_OUT, RenderStage

__all__ = [
    "ERROR_FIELDS",
    "RENDER_OUT",
    "CaptionStage",
    "ImageEmbedStage",
    "RenderStage",
    "TextEmbedStage",
    "split_errors",
]
