"""What the service adds to an answer beyond ``pipeline.query --json``: the ROI mask for the web page, and
mesh exports as a zip (in metres by default, with ``model_info.json``; see docs/serve.md)."""

from __future__ import annotations

import base64
import io

import numpy as np
from fastapi import HTTPException

from pipeline.query.errors import QueryError


def mask_png_b64(mask: np.ndarray) -> str:
    """A boolean photo-size mask as a 1-bit PNG, base64 (a few KB for a 640x480 photo)."""
    from PIL import Image

    buf = io.BytesIO()
    Image.fromarray(np.asarray(mask, bool)).convert("1").save(buf, format="PNG", optimize=True)
    return base64.b64encode(buf.getvalue()).decode("ascii")


def export_zip(retriever, mesh_id: str, units: str, fmt: str, view: int | None) -> tuple[bytes, str]:
    """The export of ``mesh_id`` (``pipeline.query.export.export_model``) as zip bytes and its folder name.

    ``view``: a view index whose camera goes into ``model_info.json`` as the pose prior (as a query's
    best view would); unknown views are a 404.
    """
    import tempfile
    import zipfile
    from pathlib import Path

    from pipeline.query.export import EXPORT_FORMATS, EXPORT_UNITS, export_model
    from pipeline.query.handoff import view_prior

    if units not in EXPORT_UNITS:
        raise HTTPException(422, f"unknown units {units!r}; choose from {', '.join(EXPORT_UNITS)}")
    if fmt not in EXPORT_FORMATS:
        raise HTTPException(422, f"unknown format {fmt!r}; choose from {', '.join(EXPORT_FORMATS)}")
    rec = retriever.mesh(mesh_id)
    prior = None
    if view is not None:
        rows = [v for v in retriever.view_poses([mesh_id]) if v["view_index"] == view]
        if not rows:
            raise HTTPException(404, f"mesh {mesh_id} has no view {view}")
        prior = {"best_view": view, **(view_prior(rec, rows[0], retriever.handoff.up) or {})}
    with tempfile.TemporaryDirectory(prefix="oscar-export-") as tmp:
        try:
            done = export_model(rec, tmp, units=units, fmt=fmt, prior=prior)
        except QueryError as exc:
            if "no active mesh" in str(exc):
                raise
            raise HTTPException(409, str(exc)) from None
        buf = io.BytesIO()
        with zipfile.ZipFile(buf, "w", zipfile.ZIP_DEFLATED) as z:
            for f in done.files:
                z.write(f, Path(done.folder.name) / Path(f).relative_to(done.folder))
        return buf.getvalue(), done.folder.name
