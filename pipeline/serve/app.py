"""The HTTP API (FastAPI): routes, uploads, errors. See ``docs/serve.md``.

Every answer is JSON; every error is ``{"error": "<one line>"}`` with a 4xx status (503/504 when busy or
slow; 503 also when the store changed under a query and its newest snapshot failed too); an unexpected
failure is logged with its traceback and answered 500 without one.
"""

from __future__ import annotations

import asyncio
import base64
import binascii
import io
import logging
import time
from importlib import resources
from typing import Annotated, Any

from fastapi import FastAPI, File, Form, HTTPException, Query, Request, UploadFile
from fastapi.exceptions import RequestValidationError
from fastapi.responses import HTMLResponse, JSONResponse, Response
from pydantic import BaseModel, Field
from starlette.exceptions import HTTPException as StarletteHTTPException

from pipeline.query.errors import QueryError, StoreUnavailable
from pipeline.query.modes import MODES
from pipeline.serve.guard import GuardMiddleware
from pipeline.serve.service import Busy, QueryService

log = logging.getLogger("pipeline.serve")

ROI_MODES = ("segm", "bbox")


def error(status: int, message: str, headers: dict | None = None) -> JSONResponse:
    return JSONResponse({"error": " ".join(str(message).split())}, status_code=status, headers=headers)


# ---------------------------------------------------------------------------- inputs
def decode_image(data: bytes, what: str, max_pixels: int):
    """A PIL image from uploaded bytes, its size checked against ``max_pixels`` before decoding."""
    import warnings

    from PIL import Image, UnidentifiedImageError

    if not data:
        raise HTTPException(422, f"{what} is empty")
    try:
        with warnings.catch_warnings():
            warnings.simplefilter("error", Image.DecompressionBombWarning)
            img = Image.open(io.BytesIO(data))
    except (UnidentifiedImageError, ValueError):
        raise HTTPException(422, f"{what} is not an image file (or an unsupported format)") from None
    except (Image.DecompressionBombError, Image.DecompressionBombWarning):
        raise HTTPException(413, f"{what} has too many pixels to decode safely") from None
    except OSError as exc:
        raise HTTPException(422, f"cannot read {what}: {exc}") from None
    w, h = img.size
    if w * h > max_pixels:
        raise HTTPException(413, f"{what} is {w}x{h} = {w * h} pixels; the limit is {max_pixels}")
    return img


def b64_bytes(text: str, what: str) -> bytes:
    try:
        return base64.b64decode(text, validate=True)
    except (binascii.Error, ValueError):
        raise HTTPException(422, f"{what} is not valid base64") from None


class RankOptions(BaseModel):
    top: int = Field(5, ge=1, le=100, description="how many models to list")
    mode: str = Field("two-stage", description="two-stage | text-only | image-only")
    roi: str = Field("segm", description="segm: object on gray (paper); bbox: raw box crop")
    threshold: float | None = Field(None, description="stage-1 tau (default: the profile's)")
    fallback_k: int = Field(10, ge=1, le=1000, description="stage-1 top-k when nothing passes tau")
    accept_threshold: float | None = Field(
        None, ge=0.0, le=1.0, description="open-set operating point (default: the server's)"
    )
    roi_mask: bool = Field(
        False, description="add the ROI mask (photo size, PNG base64) as query.roi.mask_png_b64"
    )


class BatchItem(BaseModel):
    id: Any = None
    image_b64: str = Field(..., description="the photo, base64")
    prompt: str
    box: list[float] | str | None = Field(None, description="[x0, y0, x1, y1] or 'x0,y0,x1,y1'")
    mask_b64: str | None = Field(None, description="object mask of the photo's size, base64 PNG")


class BatchRequest(RankOptions):
    queries: list[BatchItem]


def check_options(opts: RankOptions) -> None:
    if opts.mode not in MODES:
        raise HTTPException(422, f"unknown mode {opts.mode!r}; choose from {', '.join(MODES)}")
    if opts.roi not in ROI_MODES:
        raise HTTPException(422, f"unknown roi {opts.roi!r}; choose from {', '.join(ROI_MODES)}")


def run_query(retriever, image, prompt, box, mask, opts: RankOptions, name: str | None) -> dict:
    """One query on ``retriever`` -> the same dict as ``python -m pipeline.query --json``."""
    if box is None and mask is None and retriever.profile.detector is None:
        raise QueryError(f"the {retriever.profile.name} profile has no object detector: give a box or a mask")
    result = retriever.query(
        image,
        prompt,
        box=box,
        mask=mask,
        roi_mode=opts.roi,
        mode=opts.mode,
        threshold=opts.threshold,
        fallback_k=opts.fallback_k,
        top=opts.top,
        accept_threshold=opts.accept_threshold,
    )
    if name:
        result.query["image"] = name
    out = result.to_dict()
    if opts.roi_mask and result.roi is not None:
        from pipeline.serve.answer import mask_png_b64

        out["query"]["roi"]["mask_png_b64"] = mask_png_b64(result.roi.mask)
    return out


# ---------------------------------------------------------------------------- app
def create_app(service: QueryService, *, token: str | None = None) -> FastAPI:
    """The FastAPI app over ``service``; ``token`` (if set) is required as ``Authorization: Bearer``."""
    limits = service.limits
    app = FastAPI(
        title="OSCAR query service",
        description="Open-set CAD retrieval: a photo + a prompt -> ranked CAD models of an onboarded store.",
        version="1",
    )
    app.add_middleware(GuardMiddleware, max_body_bytes=limits.max_body_bytes, token=token)
    app.state.service = service

    # ------------------------------------------------------------------ errors
    @app.exception_handler(StarletteHTTPException)
    async def _http(_: Request, exc: StarletteHTTPException):
        return error(exc.status_code, str(exc.detail), getattr(exc, "headers", None))

    @app.exception_handler(RequestValidationError)
    async def _invalid(_: Request, exc: RequestValidationError):
        parts = []
        for e in exc.errors()[:5]:
            loc = ".".join(str(x) for x in e.get("loc", ()) if x not in ("body", "query", "path"))
            parts.append(f"{loc}: {e.get('msg')}" if loc else str(e.get("msg")))
        return error(422, "; ".join(parts) or "invalid request")

    @app.exception_handler(QueryError)
    async def _query_error(_: Request, exc: QueryError):
        return error(422, str(exc))

    @app.exception_handler(Busy)
    async def _busy(_: Request, exc: Busy):
        return error(503, str(exc), {"Retry-After": "1"})

    @app.exception_handler(StoreUnavailable)
    async def _store_moved(_: Request, exc: StoreUnavailable):
        return error(503, str(exc), {"Retry-After": "2"})

    @app.exception_handler(asyncio.TimeoutError)
    async def _timeout(_: Request, exc: Exception):
        return error(504, f"the query took longer than {limits.timeout:g} s")

    @app.exception_handler(Exception)
    async def _bug(request: Request, exc: Exception):
        log.exception("unexpected error on %s %s", request.method, request.url.path)
        return error(500, f"internal error ({type(exc).__name__}); see the server log")

    # ------------------------------------------------------------------ pages
    @app.get("/", response_class=HTMLResponse, include_in_schema=False)
    async def index():
        return HTMLResponse(resources.files("pipeline.serve").joinpath("static/index.html").read_text())

    @app.get("/health", summary="liveness and the store version served")
    async def health():
        snap = service.snapshot
        return {"status": "ok", "store_version": snap.version, "meshes": snap.retriever.n_meshes}

    @app.get("/stats", summary="store version, counts, latency p50/p99 (ms)")
    async def stats():
        return service.stats()

    # ------------------------------------------------------------------ queries
    @app.post("/query", summary="one photo + prompt -> ranked models (the JSON of `pipeline.query --json`)")
    async def query(
        image: Annotated[UploadFile, File(description="the photo (any PIL format)")],
        prompt: Annotated[str, Form(description='the object, e.g. "the yellow mustard bottle"')],
        box: Annotated[str | None, Form(description="x0,y0,x1,y1 in photo pixels")] = None,
        mask: Annotated[UploadFile | None, File(description="object mask of the photo's size")] = None,
        top: Annotated[int, Form(ge=1, le=100)] = 5,
        mode: Annotated[str, Form()] = "two-stage",
        roi: Annotated[str, Form()] = "segm",
        threshold: Annotated[float | None, Form()] = None,
        fallback_k: Annotated[int, Form(ge=1, le=1000)] = 10,
        accept_threshold: Annotated[float | None, Form(ge=0.0, le=1.0)] = None,
        roi_mask: Annotated[bool, Form(description="add the ROI mask as query.roi.mask_png_b64")] = False,
    ):
        opts = RankOptions(
            top=top,
            mode=mode,
            roi=roi,
            threshold=threshold,
            fallback_k=fallback_k,
            accept_threshold=accept_threshold,
            roi_mask=roi_mask,
        )
        check_options(opts)
        photo = decode_image(await image.read(), "image", limits.max_pixels)
        mask_img = None
        if mask is not None and mask.filename:
            mask_img = decode_image(await mask.read(), "mask", limits.max_pixels)
        box_v = box if box not in (None, "") else None
        t0 = time.perf_counter()
        try:
            out = await service.run(run_query, photo, prompt, box_v, mask_img, opts, image.filename)
        except Exception:
            service.record(time.perf_counter() - t0, ok=False)
            raise
        service.record(time.perf_counter() - t0, ok=True)
        return out

    @app.post("/query/batch", summary="many queries (base64 images) -> one result or error per query")
    async def query_batch(req: BatchRequest):
        check_options(req)
        if len(req.queries) > limits.max_batch:
            raise HTTPException(413, f"{len(req.queries)} queries; the limit per batch is {limits.max_batch}")

        async def one(i: int, item: BatchItem) -> dict:
            qid = item.id if item.id is not None else i + 1
            t0 = time.perf_counter()
            try:
                photo = decode_image(b64_bytes(item.image_b64, "image_b64"), "image", limits.max_pixels)
                mask = None
                if item.mask_b64:
                    mask = decode_image(b64_bytes(item.mask_b64, "mask_b64"), "mask", limits.max_pixels)
                out = await service.run(run_query, photo, item.prompt, item.box, mask, req, None)
            except (QueryError, HTTPException) as exc:
                service.record(time.perf_counter() - t0, ok=False)
                return {"id": qid, "error": str(getattr(exc, "detail", exc))}
            service.record(time.perf_counter() - t0, ok=True)
            return {"id": qid, **out}

        return {"results": list(await asyncio.gather(*(one(i, q) for i, q in enumerate(req.queries))))}

    # ------------------------------------------------------------------ meshes
    @app.get(
        "/meshes/{mesh_id}", summary="a mesh record (size, bounds, units) with its views (captions, URLs)"
    )
    async def mesh(mesh_id: str):
        def work(r):
            rec = r.mesh(mesh_id)
            views = r.candidate_views([mesh_id])
            return rec, views

        from pipeline.query.handoff import metric_info

        rec, views = await service.run(_not_found(work))
        out = {k: _jsonable(v) for k, v in rec.items()}
        out.update(metric_info(rec))  # units_guess, units_from, scale_to_metres, extent_m (issue 19)
        out["views"] = [
            {
                "view_index": v["view_index"],
                "azimuth_deg": v["azimuth_deg"],
                "elevation_deg": v["elevation_deg"],
                "caption": v["caption"],
                "url": f"/meshes/{mesh_id}/views/{v['view_index']}.png",
            }
            for v in views
        ]
        return out

    @app.get(
        "/meshes/{mesh_id}/views/{k}.png",
        summary="a rendered view (PNG)",
        response_class=Response,
        responses={200: {"content": {"image/png": {}}}},
    )
    async def view(mesh_id: str, k: int):
        def work(r):
            r.mesh(mesh_id)
            return [v for v in r.candidate_views([mesh_id]) if v["view_index"] == k]

        found = await service.run(_not_found(work))
        if not found:
            raise HTTPException(404, f"mesh {mesh_id} has no view {k}")
        return Response(found[0]["image"], media_type="image/png", headers={"Cache-Control": "max-age=3600"})

    @app.get(
        "/meshes/{mesh_id}/export",
        summary="the mesh in metres (or mm, or as is) with its materials, textures and model_info.json (zip)",
        response_class=Response,
        responses={200: {"content": {"application/zip": {}}}},
    )
    async def export(
        mesh_id: str,
        units: Annotated[str, Query(description="m (default) | mm | source")] = "m",
        format: Annotated[str, Query(description="mesh (the source file type) | bop")] = "mesh",
        view: Annotated[
            int | None, Query(description="view whose pose prior goes into model_info.json")
        ] = None,
    ):
        from pipeline.serve.answer import export_zip

        data, name = await service.run(_not_found(export_zip), mesh_id, units, format, view)
        return Response(
            data,
            media_type="application/zip",
            headers={"Content-Disposition": f'attachment; filename="{name}.zip"'},
        )

    return app


def _not_found(fn):
    """Turn an unknown mesh id (QueryError from Retriever.mesh) into a 404."""

    def wrapped(r, *args):
        try:
            return fn(r, *args)
        except QueryError as exc:
            if "no active mesh" in str(exc):
                raise HTTPException(404, str(exc)) from None
            raise

    return wrapped


def _jsonable(value):
    import datetime

    if isinstance(value, (datetime.datetime, datetime.date)):
        return value.isoformat()
    if isinstance(value, bytes):
        return None
    if isinstance(value, dict):
        return {k: _jsonable(v) for k, v in value.items()}
    if isinstance(value, list):
        return [_jsonable(v) for v in value]
    return value
