"""Pieces shared by the command-line entry points: model options and one-line errors."""

from __future__ import annotations

import argparse
import sys


def add_model_args(p: argparse.ArgumentParser) -> None:
    """``--profile`` and repeatable ``--model ROLE=ID_OR_DIR`` overrides."""
    p.add_argument(
        "--profile",
        default="offline",
        choices=["offline", "paper"],
        help="model profile: offline (no downloaded weights) or paper (LLaVA/CLIP/DINOv2)",
    )
    p.add_argument(
        "--model",
        action="append",
        default=[],
        metavar="ROLE=ID_OR_DIR",
        help="override one role's model (hub id or local dir); roles: captioner, text_encoder, "
        "view_encoder, clip_image_encoder, detector, segmenter",
    )


def model_overrides(args: argparse.Namespace) -> dict[str, str]:
    from pipeline.profiles import parse_overrides

    return parse_overrides(args.model)


def fail(message: str, code: int = 2) -> int:
    """Print ``error: message`` (one line) to stderr and return ``code``."""
    print(f"error: {message}", file=sys.stderr)
    return code
