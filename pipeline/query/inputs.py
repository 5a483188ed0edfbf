"""A query's inputs checked and cut out: photo, prompt, box or mask into a :class:`~pipeline.query.roi.Roi`,
and the knobs a query refuses before any work (unknown mode, accept threshold outside [0, 1])."""

from __future__ import annotations

from collections.abc import Callable

from pipeline.query.errors import QueryError
from pipeline.query.images import clean_prompt, load_mask, load_photo, parse_box
from pipeline.query.modes import MODES
from pipeline.query.roi import Roi, make_roi
from pipeline.query.settings import QuerySettings


def roi_from_inputs(
    settings: QuerySettings,
    model: Callable,
    profile: str,
    image,
    prompt: str,
    box=None,
    mask=None,
    roi_mode: str = "segm",
) -> Roi:
    """Validate the inputs and cut the prompted object out of ``image`` (path, PIL image or array)."""
    s = settings
    prompt = clean_prompt(prompt, s.max_prompt_chars)
    photo = load_photo(image, max_side=s.max_side, min_side=s.min_side)
    box_v = parse_box(box) if box is not None else None
    mask_v = load_mask(mask, photo, s.min_roi_side) if mask is not None else None
    opts = {"background": s.background, "min_side": s.min_roi_side, "box_segmenter": s.box_segmenter}
    roi = make_roi(photo, prompt, box=box_v, mask=mask_v, roi_mode=roi_mode, model=model, profile=profile, **opts)
    roi.notes.extend([] if photo.scale == 1.0 else [f"image downscaled by {photo.scale:.3f}"])
    roi.photo_source, roi.photo_size = photo.source, photo.original_size
    return roi


def check_knobs(knobs: dict) -> None:
    """A :class:`~pipeline.query.errors.QueryError` for a mode or accept threshold no query can use."""
    if knobs.get("mode") is not None and knobs["mode"] not in MODES:
        raise QueryError(f"unknown mode {knobs['mode']!r}; choose from {', '.join(MODES)}")
    value = knobs.get("accept_threshold")
    if value is not None and not 0.0 <= float(value) <= 1.0:
        raise QueryError(f"accept threshold must be within [0, 1], got {value}")
