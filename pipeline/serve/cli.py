"""``python -m pipeline.serve STORE [--host 127.0.0.1] [--port 8000]``: serve queries over HTTP.

Safe by default: binds the loopback; any other address needs a bearer token (``--token`` or the
``OSCAR_TOKEN`` environment variable); request bodies, image pixels, waiting requests and query time are
limited. See ``docs/serve.md``.
"""

from __future__ import annotations

import argparse
import ipaddress
import os
import sys

from pipeline.cli_common import (
    OneLineParser,
    add_read_model_args,
    fail,
    float_range,
    int_range,
    positive_float,
    positive_int,
)
from pipeline.threads import add_torch_threads_arg

TOKEN_ENV = "OSCAR_TOKEN"


def build_parser() -> argparse.ArgumentParser:
    p = OneLineParser(
        prog="python -m pipeline.serve",
        description="Serve CAD-model queries of an onboarded store over HTTP (JSON API, /docs, a web page).",
    )
    p.add_argument("store", metavar="STORE_DIR", help="store written by pipeline.onboard")
    net = p.add_argument_group("network")
    net.add_argument(
        "--host", default="127.0.0.1", help="address to bind (default: 127.0.0.1, loopback only)"
    )
    net.add_argument(
        "--port", type=int_range(0, 65535), default=8000, help="TCP port (default: 8000; 0 picks a free one)"
    )
    net.add_argument(
        "--token",
        default=None,
        help=f"require 'Authorization: Bearer TOKEN' (default: ${TOKEN_ENV}); required for a non-loopback --host",
    )
    models = p.add_argument_group("models")
    add_read_model_args(models)
    models.add_argument("--device", default=None, help="torch device (default: cuda if available)")
    add_torch_threads_arg(models, "half the cores, 1 to 4")
    models.add_argument("--threads", type=positive_int, default=None, help="DuckDB threads per stage-1 query")
    models.add_argument(
        "--accept-threshold",
        type=float_range(0.0, 1.0),
        metavar="P",
        help="default open-set operating point of the answers (a request's accept_threshold wins; "
        "default: the calibration's)",
    )
    models.add_argument(
        "--accept-model", metavar="CALIBRATION.json", help="acceptance calibration (default: the shipped one)"
    )
    models.add_argument(
        "--no-cache", action="store_true", help="do not use the embedding cache under STORE/_cache"
    )
    lim = p.add_argument_group("limits")
    lim.add_argument(
        "--workers",
        type=positive_int,
        default=None,
        help="queries run at once (default: cores / torch threads, 1 to 4)",
    )
    lim.add_argument(
        "--max-pending", type=positive_int, default=64, help="requests waiting or running; more get 503"
    )
    lim.add_argument(
        "--max-body-mb", type=positive_float, default=20.0, help="largest request body in MiB (default 20)"
    )
    lim.add_argument(
        "--max-pixels", type=positive_int, default=40_000_000, help="largest image in pixels (default 40M)"
    )
    lim.add_argument(
        "--timeout",
        type=positive_float,
        default=60.0,
        help="seconds a query may take before 504 (default 60)",
    )
    lim.add_argument("--max-batch", type=positive_int, default=32, help="queries per /query/batch request")
    lim.add_argument(
        "--reload-interval",
        type=float_range(0.0),
        default=1.0,
        help="seconds between checks for new store commits (0: never reload; default 1)",
    )
    p.add_argument("--log-level", default="info", choices=["critical", "error", "warning", "info", "debug"])
    return p


def is_loopback(host: str) -> bool:
    if host == "localhost":
        return True
    try:
        return ipaddress.ip_address(host).is_loopback
    except ValueError:
        return False


def check_args(args: argparse.Namespace) -> str | None:
    if not is_loopback(args.host) and not args.token:
        return (
            f"--host {args.host} exposes the service beyond this machine: set a bearer token with --token or "
            f"${TOKEN_ENV} (or bind 127.0.0.1)"
        )
    return None  # ports, limits and intervals are checked by their argparse types


def build_service(args: argparse.Namespace):
    """Open the store and load the models once; returns the :class:`QueryService`."""
    from pipeline.query.cli import open_retriever
    from pipeline.serve.service import QueryService, ServiceLimits
    from pipeline.threads import apply_torch_threads, cpu_count

    threads = apply_torch_threads(args.torch_threads)
    workers = args.workers or max(1, min(4, cpu_count() // threads))
    accept = {"accept_threshold": args.accept_threshold, "accept_model": args.accept_model}
    retriever = open_retriever(args, settings_changes=accept)
    source = "detector" if retriever.profile.detector is not None else "box"
    retriever.load_models(retriever.required_roles(source))
    limits = ServiceLimits(
        max_body_bytes=int(args.max_body_mb * 1024 * 1024),
        max_pixels=args.max_pixels,
        timeout=args.timeout,
        workers=workers,
        max_pending=args.max_pending,
        max_batch=args.max_batch,
        reload_interval=args.reload_interval,
    )
    return QueryService(retriever, limits, torch_threads=threads)


def main(argv: list[str] | None = None) -> int:
    args = build_parser().parse_args(argv)
    args.token = args.token or os.environ.get(TOKEN_ENV) or None
    problem = check_args(args)
    if problem:
        return fail(problem)
    from pipeline.threads import apply_torch_threads

    apply_torch_threads(args.torch_threads)  # first: before NumPy's BLAS or torch are loaded
    from pipeline.models.registry import ModelLoadError
    from pipeline.query.errors import QueryError
    from pipeline.store import StoreError

    try:
        service = build_service(args)
    except (QueryError, StoreError, ModelLoadError, ValueError) as exc:
        return fail(str(exc))
    except KeyboardInterrupt:
        return fail("interrupted", 130)
    try:
        return serve(service, args)
    finally:
        service.close()


def serve(service, args: argparse.Namespace) -> int:
    import logging

    import uvicorn

    from pipeline.serve.app import create_app

    logging.basicConfig(level=args.log_level.upper(), format="%(asctime)s %(name)s %(levelname)s %(message)s")
    app = create_app(service, token=args.token)
    service.start_polling()
    snap = service.snapshot
    print(
        f"serving {snap.retriever.store.root} ({snap.retriever.n_meshes} meshes, store version {snap.version}, "
        f"profile {snap.retriever.profile.name}, {service.limits.workers} workers x "
        f"{service.torch_threads} torch threads) on http://{args.host}:{args.port}"
        + (" (bearer token required)" if args.token else ""),
        file=sys.stderr,
        flush=True,
    )
    config = uvicorn.Config(
        app,
        host=args.host,
        port=args.port,
        log_level=args.log_level,
        timeout_keep_alive=5,
        limit_concurrency=service.limits.max_pending + 64,
        access_log=args.log_level == "debug",
    )
    server = uvicorn.Server(config)
    server.run()
    return 0
