"""``python -m pipeline.onboard LIBRARY_DIR --store STORE_DIR``: onboard a CAD library into a store."""

from __future__ import annotations

import argparse
import json
import sys

from pipeline.cli_common import (
    OneLineParser,
    add_model_args,
    fail,
    float_range,
    int_range,
    model_overrides,
    non_negative_int,
    number_list,
    positive_float,
    positive_int,
)
from pipeline.threads import add_torch_threads_arg


def share(text: str) -> float:
    """``type=`` for ``--max-removed``: ``10%`` or ``0.1``."""
    from pipeline.onboard.guard import parse_share

    try:
        return parse_share(text)
    except ValueError as exc:
        raise argparse.ArgumentTypeError(str(exc)) from None


def build_parser() -> argparse.ArgumentParser:
    from pipeline.adapter.probes import ProbeConfig
    from pipeline.onboard.config import DEFAULT_MAX_TEXTURE_PIXELS
    from pipeline.onboard.guard import DEFAULT_MAX_REMOVED
    from pipeline.onboard.stages import STAGE_NAMES
    from pipeline.profiles import DEFAULT_PROMPT_STYLE, PROMPT_STYLES

    p = OneLineParser(
        prog="python -m pipeline.onboard",
        description="Render, caption and embed every new mesh of LIBRARY_DIR into the store (incremental).",
    )
    p.add_argument(
        "library", metavar="LIBRARY_DIR", help="folder tree of meshes (.obj/.ply/.glb/.gltf/.stl/.off)"
    )
    p.add_argument("--store", required=True, metavar="STORE_DIR", help="store directory (created if missing)")
    add_model_args(p)
    p.add_argument(
        "--prompt-style",
        default=DEFAULT_PROMPT_STYLE,
        choices=sorted(PROMPT_STYLES),
        help="captioning prompt style of the paper's prompt table (default: %(default)s)",
    )
    p.add_argument(
        "--cameras",
        default="oscar",
        choices=["oscar", "cap3d"],
        help="oscar: 4 views at -15 and 4 at +15 deg elevation; cap3d: the reference scripts' 8 positions",
    )
    p.add_argument(
        "--extra-bg-view",
        action="store_true",
        help="also render view 0 on black as an extra stage-2 (DINOv2) reference view, not captioned "
        "(the reference scripts' _bg render)",
    )
    p.add_argument(
        "--resolution",
        type=int_range(16, 8192),
        default=512,
        help="view size in pixels, 16..8192 (default: 512)",
    )
    p.add_argument(
        "--elevations",
        type=number_list(float, -89.0, 89.0, max_items=6),
        metavar="DEG,DEG,...",
        help="elevation rings of the oscar layout, 4 views each, -89..89 (default: the profile's: paper -15,15 "
        "as in the paper; offline -15,15,45, a third ring for top-down tabletop photos); a list that starts "
        "with '-' needs '=': --elevations=-15,15,45",
    )
    p.add_argument(
        "--upper-ring-offset",
        type=float_range(-360.0, 360.0),
        default=45.0,
        help="azimuth offset in degrees of each ring from the one below (default: 45; 0 aligns the rings)",
    )
    p.add_argument(
        "--up", default="auto", choices=["auto", "z", "y"], help="up axis of the meshes (auto: z, y for glTF)"
    )
    p.add_argument(
        "--max-faces", type=positive_int, default=2_000_000, help="meshes with more faces fail (default: 2M)"
    )
    p.add_argument(
        "--max-texture-pixels",
        type=positive_int,
        default=DEFAULT_MAX_TEXTURE_PIXELS,
        help="meshes with a larger texture (width x height) fail: a decompression-bomb guard "
        f"(default: {DEFAULT_MAX_TEXTURE_PIXELS:,} = 8192 x 8192)",
    )
    p.add_argument(
        "--render-timeout",
        type=float_range(0.0, 86400.0, lo_open=True),
        default=120.0,
        help="seconds per mesh before it fails, > 0 (default: 120)",
    )
    p.add_argument(
        "--workers",
        type=int_range(0, 256),
        default=2,
        help="render processes (0: render in-process, no timeout)",
    )
    p.add_argument(
        "--batch-size", type=int_range(1, 100_000), default=16, help="meshes per commit (default: 16)"
    )
    p.add_argument(
        "--force",
        action="append",
        default=[],
        choices=list(STAGE_NAMES),
        help="redo STAGE (and what depends on it) for every mesh; repeatable",
    )
    p.add_argument(
        "--retry-failed", action="store_true", help="retry meshes that failed with the same config"
    )
    p.add_argument(
        "--max-removed",
        type=share,
        default=DEFAULT_MAX_REMOVED,
        metavar="SHARE",
        help="removal guard: stop, committing nothing, when the run would mark more than this share of the "
        f"library's active files removed, e.g. 10%% or 0.1 (default: {DEFAULT_MAX_REMOVED * 100:g}%%); a library "
        "that yields no file at all always stops",
    )
    p.add_argument(
        "--allow-removal",
        action="store_true",
        help="turn the removal guard off for this run (files were removed on purpose)",
    )
    p.add_argument(
        "--local-features",
        default="sift",
        choices=["sift", "orb", "none"],
        help="local features stored per view for query-time verification (default: sift; none: skip the stage)",
    )
    p.add_argument(
        "--max-keypoints",
        type=int_range(16, 4096),
        default=256,
        help="local features kept per view, 16..4096 (default: 256)",
    )
    p.add_argument(
        "--probes",
        type=int_range(0, 64),
        default=ProbeConfig().per_mesh,
        metavar="N",
        help="probe queries per model, made from its own views, on which the store's query adapter of the "
        f"learned encoder is fitted at the end of the run (default: {ProbeConfig().per_mesh}; 0: no probe "
        "stage and no adapter; docs/architecture.md, Query adapter)",
    )
    p.add_argument(
        "--no-patch-tokens",
        action="store_true",
        help="do not store the learned encoder's object patch tokens of each view (about 1 MB per model): "
        "the open-set verdict then encodes the top-1's views on each query, about 110 ms more on 2 cores "
        "(docs/performance.md, Stored patch tokens)",
    )
    p.add_argument("--engine", default="local", choices=["local", "ray"], help="executor (default: local)")
    p.add_argument(
        "--address",
        default=None,
        help="Ray cluster for --engine ray: 'auto', 'ray://HEAD:10001' (default: start a local instance)",
    )
    p.add_argument(
        "--ray-render-workers", type=non_negative_int, default=0, help="Ray render actors (0: one per CPU)"
    )
    p.add_argument(
        "--ray-caption-actors", type=positive_int, default=1, help="Ray captioner actors (default: 1)"
    )
    p.add_argument(
        "--ray-embed-actors", type=positive_int, default=1, help="Ray actors per encoder (default: 1)"
    )
    p.add_argument(
        "--ray-gpus-per-actor",
        type=positive_float,
        default=None,
        help="GPUs per model actor (default: encoders a quarter, captioners share the rest)",
    )
    # tests only (RayOptions.pause_at): an actor waits at STAGE:MESH_ID_PREFIX:MARKER for a node to be killed
    p.add_argument("--ray-pause-at", default="", help=argparse.SUPPRESS)
    add_torch_threads_arg(p, "every core (onboarding is throughput work)")
    p.add_argument("--no-progress", action="store_true", help="no progress bars")
    p.add_argument("--json", action="store_true", help="print the run summary as JSON")
    return p


def main(argv: list[str] | None = None) -> int:
    from pipeline.onboard import supervise

    argv = list(sys.argv[1:] if argv is None else argv)
    args = build_parser().parse_args(argv)
    if args.engine == "ray" and not supervise.is_child():
        return supervise.supervise(argv)  # the driver in a child: a lost head still gets a clear line
    try:
        code = run(args)
    except SystemExit as exc:
        supervise.note_exit(exc.code if isinstance(exc.code, int) else 1)
        raise
    except BaseException:
        supervise.note_exit(1)  # a Python error (its traceback is printed): not a driver ended from outside
        raise
    supervise.note_exit(code)
    return code


def run(args) -> int:
    """The onboarding command on parsed arguments; its exit code."""
    from pathlib import Path

    from pipeline.adapter.probes import ProbeConfig
    from pipeline.localfeat import FeatureConfig
    from pipeline.mesh.settings import RenderConfig
    from pipeline.onboard.config import OnboardConfig
    from pipeline.onboard.engines.ray_options import RayOptions
    from pipeline.profiles import default_elevations

    if Path(args.library).exists() and not Path(args.library).is_dir():
        return fail(f"library path {args.library} is a file: give the folder that holds the meshes")
    if not Path(args.library).is_dir():
        return fail(f"library folder not found: {args.library}")
    if args.torch_threads is not None:  # unset: torch's own default (every core)
        from pipeline.threads import apply_torch_threads

        apply_torch_threads(args.torch_threads)
    try:
        cfg = OnboardConfig(
            profile=args.profile,
            model_overrides=model_overrides(args),
            prompt_style=args.prompt_style,
            render=RenderConfig(
                cameras=args.cameras,
                resolution=args.resolution,
                upper_ring_offset_deg=args.upper_ring_offset,
                elevations_deg=args.elevations or default_elevations(args.profile),
                up=args.up,
                extra_bg_view=args.extra_bg_view,
            ),
            max_faces=args.max_faces,
            max_texture_pixels=args.max_texture_pixels,
            render_timeout_s=args.render_timeout,
            workers=args.workers,
            batch_size=args.batch_size,
            retry_failed=args.retry_failed,
            max_removed=args.max_removed,
            allow_removal=args.allow_removal,
            force=tuple(args.force),
            engine=args.engine,
            features=FeatureConfig(detector=args.local_features, max_keypoints=args.max_keypoints),
            probes=ProbeConfig(per_mesh=args.probes),
            patch_tokens=not args.no_patch_tokens,
            ray=RayOptions(
                address=args.address,
                render_workers=args.ray_render_workers,
                caption_actors=args.ray_caption_actors,
                embed_actors=args.ray_embed_actors,
                gpus_per_actor=args.ray_gpus_per_actor,
                pause_at=args.ray_pause_at,
            ),
        )
        cfg.fingerprints()
    except ValueError as exc:
        return fail(str(exc))

    from pipeline.models.registry import ModelLoadError
    from pipeline.onboard.engines.ray import RayEngineError
    from pipeline.onboard.engines.render_pool import RenderSetupError
    from pipeline.onboard.guard import RemovalGuardError
    from pipeline.onboard.interrupt import RunInterrupted
    from pipeline.onboard.run import run_onboarding
    from pipeline.store import StoreError

    try:
        summary = run_onboarding(args.library, args.store, cfg, progress=not args.no_progress)
    except RemovalGuardError as exc:
        return fail(str(exc), 3)
    except RunInterrupted as exc:
        return fail(str(exc), exc.exit_code)
    except (StoreError, ModelLoadError, RenderSetupError, RayEngineError) as exc:
        return fail(str(exc))
    except OSError as exc:  # a library or store file system failing outside a commit
        return fail(f"I/O error on the store or library: {type(exc).__name__}: {str(exc).splitlines()[0]}")
    except KeyboardInterrupt:
        return fail(
            "interrupted at once: the meshes committed so far are kept; run the same command again to do "
            "the rest",
            130,
        )
    for line in summary.warnings:
        print(f"warning: {line}", file=sys.stderr)
    if args.json:
        print(json.dumps(summary.to_dict(), indent=2))
    else:
        for line in summary.lines():
            print(line)
    return 0


if __name__ == "__main__":
    sys.exit(main())
