"""The evaluation commands' expected failures as one ``error:`` line (``evaluate`` and ``evaluate openset``)."""

from __future__ import annotations

import argparse
from collections.abc import Callable

from pipeline.cli_common import fail


def run_reporting_errors(run: Callable, args: argparse.Namespace, argv: list[str]) -> int:
    """``run(args, argv)``, with the evaluation commands' expected failures (store, model, query file,
    bad value, missing file) as one ``error:`` line and exit 2, and Ctrl-C as exit 130."""
    from pipeline.evaluate.datasets import QueryFileError
    from pipeline.models.registry import ModelLoadError
    from pipeline.store import StoreError

    try:
        return run(args, argv)
    except (StoreError, ModelLoadError, QueryFileError, ValueError, FileNotFoundError) as exc:
        return fail(str(exc))
    except KeyboardInterrupt:
        return fail("interrupted", 130)
