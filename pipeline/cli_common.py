"""Pieces shared by the command-line entry points: model options and one-line errors."""

from __future__ import annotations

import argparse
import sys


class OneLineParser(argparse.ArgumentParser):
    """An ``ArgumentParser`` whose errors are one line (``prog: error: ...; see --help``), exit code 2."""

    def error(self, message: str):  # type: ignore[override]
        self.exit(2, f"{self.prog}: error: {message} (see --help)\n")


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


def add_read_model_args(group) -> None:
    """``--profile auto|offline|paper`` (auto: the store's own) and ``--model`` for readers (query, serve)."""
    group.add_argument(
        "--profile",
        default="auto",
        choices=["auto", "offline", "paper"],
        help="model profile (default auto: the profile the store was onboarded with)",
    )
    group.add_argument(
        "--model",
        action="append",
        default=[],
        metavar="ROLE=ID_OR_DIR",
        help="override a role's model; roles: captioner, text_encoder, view_encoder, clip_image_encoder, "
        "detector, segmenter",
    )


def model_overrides(args: argparse.Namespace) -> dict[str, str]:
    from pipeline.profiles import parse_overrides

    return parse_overrides(args.model)


def fail(message: str, code: int = 2) -> int:
    """Print ``error: message`` (one line) to stderr and return ``code``."""
    print(f"error: {message}", file=sys.stderr)
    return code


def reader_gone() -> int:
    """After ``BrokenPipeError`` on stdout (``... | head``): point stdout at /dev/null, so that the flush
    at exit raises nothing either, and return 0: the reader stopped on purpose."""
    import os

    try:
        devnull = os.open(os.devnull, os.O_WRONLY)
        os.dup2(devnull, sys.stdout.fileno())
    except (OSError, ValueError):  # stdout is not a file descriptor (tests): nothing to flush
        pass
    return 0


# ---------------------------------------------------------------- argparse value types
# Each returns a callable for ``type=``; a bad value becomes argparse's one-line
# ``error: argument --x: ...`` with exit code 2, before anything is loaded or written.


def _number(text: str, kind: type) -> int | float:
    import math

    try:
        value = kind(text)
    except (TypeError, ValueError):
        raise argparse.ArgumentTypeError(
            f"expected {'an integer' if kind is int else 'a number'}, got {text!r}"
        ) from None
    if kind is float and not math.isfinite(value):
        raise argparse.ArgumentTypeError(f"expected a finite number, got {text!r}")
    return value


def int_range(lo: int | None = None, hi: int | None = None):
    """``type=`` for an integer in ``[lo, hi]`` (either bound may be ``None``)."""

    def parse(text: str) -> int:
        value = _number(text, int)
        _check_bounds(value, lo, hi, text)
        return value

    parse.__name__ = "integer"
    return parse


def float_range(lo: float | None = None, hi: float | None = None, *, lo_open: bool = False):
    """``type=`` for a finite float in ``[lo, hi]`` (``(lo, hi]`` with ``lo_open``); NaN and inf refused."""

    def parse(text: str) -> float:
        value = _number(text, float)
        if lo_open and lo is not None and value <= lo:
            raise argparse.ArgumentTypeError(f"must be > {lo:g}, got {text!r}")
        _check_bounds(value, lo, hi, text)
        return value

    parse.__name__ = "number"
    return parse


def _check_bounds(value: float, lo: float | None, hi: float | None, text: str) -> None:
    if lo is not None and value < lo:
        raise argparse.ArgumentTypeError(f"must be >= {lo:g}, got {text!r}")
    if hi is not None and value > hi:
        raise argparse.ArgumentTypeError(f"must be <= {hi:g}, got {text!r}")


positive_int = int_range(1)
non_negative_int = int_range(0)
positive_float = float_range(0.0, lo_open=True)
finite_float = float_range()


def number_list(kind: type = float, lo: float | None = None, hi: float | None = None, max_items: int = 1000):
    """``type=`` for ``a,b,c`` or an inclusive ``START:STOP:STEP`` range of finite numbers in ``[lo, hi]``."""

    def parse(text: str) -> tuple:
        parts = text.split(":")
        if len(parts) == 3:
            a, b, step = (_number(x.strip(), float) for x in parts)
            if step <= 0 or b < a:
                raise argparse.ArgumentTypeError(f"range {text!r} needs START <= STOP and STEP > 0")
            n = int(round((b - a) / step)) + 1
            if n > max_items:
                raise argparse.ArgumentTypeError(f"range {text!r} has {n} values (at most {max_items})")
            values = [round(a + i * step, 6) for i in range(n)]
        elif len(parts) == 1:
            values = [_number(x.strip(), float) for x in text.split(",") if x.strip()]
        else:
            raise argparse.ArgumentTypeError(f"expected a,b,c or START:STOP:STEP, got {text!r}")
        if not values:
            raise argparse.ArgumentTypeError(f"no values in {text!r}")
        out = tuple(int(round(v)) if kind is int else v for v in values)
        for v in out:
            _check_bounds(v, lo, hi, str(v))
        return out

    parse.__name__ = "list"
    return parse


def image_size(lo: int = 16, hi: int = 8192):
    """``type=`` for ``WxH`` with both sides in ``[lo, hi]``; returns ``(w, h)``."""

    def parse(text: str) -> tuple[int, int]:
        w, sep, h = text.lower().partition("x")
        if not sep:
            raise argparse.ArgumentTypeError(f"expected WxH, e.g. 640x480, got {text!r}")
        side = int_range(lo, hi)
        return side(w.strip()), side(h.strip())

    parse.__name__ = "size"
    return parse
