"""``python -m pipeline.query --store STORE --image PHOTO --prompt TEXT``: rank the store's CAD models."""

from __future__ import annotations

import argparse
import sys

from pipeline.cli_common import OneLineParser, add_read_model_args, fail, float_range, int_range, positive_int
from pipeline.query.modes import MODES
from pipeline.threads import add_torch_threads_arg


def build_parser() -> argparse.ArgumentParser:
    from pipeline.query.settings import PROFILE_SETTINGS

    p = OneLineParser(
        prog="python -m pipeline.query",
        description="Find the CAD model in an onboarded store that matches the object a prompt names in a photo.",
    )
    p.add_argument("--store", required=True, metavar="STORE_DIR", help="store written by pipeline.onboard")
    what = p.add_argument_group("what to look for (one photo, or a batch)")
    what.add_argument(
        "--image", metavar="PHOTO", help="photo (any PIL format; RGBA/16-bit/gray are converted)"
    )
    what.add_argument("--prompt", help='the object to find, e.g. "the yellow mustard bottle"')
    what.add_argument("--box", metavar="X0,Y0,X1,Y1", help="object box in photo pixels (skips detection)")
    what.add_argument("--mask", metavar="MASK.png", help="object mask of the photo's size (skips detection)")
    what.add_argument(
        "--queries",
        metavar="FILE.jsonl",
        help='batch: one {"image", "prompt", ["box"], ["mask"], ["id"]} object per line; JSONL out',
    )
    what.add_argument("--output", metavar="OUT.jsonl", help="batch output (default: stdout)")

    how = p.add_argument_group("how to rank")
    add_read_model_args(how)
    how.add_argument(
        "--roi",
        default="segm",
        choices=["segm", "bbox"],
        help="segm: object on gray (paper); bbox: raw box crop",
    )
    how.add_argument(
        "--mode",
        default="two-stage",
        choices=MODES,
        help="paper ablations",
    )
    how.add_argument(
        "--threshold",
        type=float_range(-1.0, 1.0),
        metavar="TAU",
        help=f"stage-1 tau (default: paper {PROFILE_SETTINGS['paper'].threshold:g}, offline "
        f"{PROFILE_SETTINGS['offline'].threshold:g}; see docs/query.md)",
    )
    how.add_argument(
        "--fallback-k",
        type=positive_int,
        default=10,
        metavar="K",
        help="stage-1 top-k when nothing passes tau (default 10; reference scripts: 15)",
    )
    how.add_argument(
        "--fallback-unit",
        default="captions",
        choices=["captions", "meshes"],
        help="what --fallback-k counts: caption rows, kept as their distinct models (paper, default), "
        "or models",
    )
    how.add_argument(
        "--prompt-weight",
        type=float_range(0.0, 1.0),
        metavar="W",
        help="weight of the prompt in the stage-1 query vector (offline default "
        f"{PROFILE_SETTINGS['offline'].prompt_weight:g}, paper {PROFILE_SETTINGS['paper'].prompt_weight:g})",
    )
    how.add_argument(
        "--verify",
        action=argparse.BooleanOptionalAction,
        default=None,
        help="re-rank the top candidates by local-feature matches (ratio test + RANSAC inliers) fused with "
        "the image score (default: on for offline stores onboarded with local features)",
    )
    how.add_argument(
        "--adapter",
        action=argparse.BooleanOptionalAction,
        default=None,
        help="rank with the store's query adapter of the learned encoder, fitted at onboarding on probe "
        "queries made from its own views (default: on where the store has one; docs/query.md)",
    )
    how.add_argument(
        "--verify-top",
        type=int_range(0, 1000),
        metavar="N",
        help="candidates verified by local features, 0..1000 (default 20)",
    )
    how.add_argument(
        "--accept-threshold",
        type=float_range(0.0, 1.0),
        metavar="P",
        help="open-set operating point: accept the best model when its confidence is at least P "
        "(default: the calibration's; docs/query.md, Open-set answers)",
    )
    how.add_argument(
        "--accept-model",
        metavar="CALIBRATION.json",
        help="acceptance calibration (default: the one shipped for the profile; written by "
        "`python -m pipeline.evaluate openset`)",
    )
    how.add_argument(
        "--top", type=positive_int, default=5, metavar="N", help="how many models to list (default 5)"
    )
    how.add_argument(
        "--device", default=None, help="torch device for models and stage 2 (default: cuda if available)"
    )
    how.add_argument(
        "--threads",
        type=int_range(1, 1024),
        default=None,
        help="DuckDB threads for stage 1 (default: all cores)",
    )
    how.add_argument(
        "--no-cache", action="store_true", help="do not read or write the embedding cache under STORE/_cache"
    )
    add_torch_threads_arg(how, "half the cores, 1 to 4")

    out = p.add_argument_group("output")
    out.add_argument("--json", action="store_true", help="print the full result as JSON")
    out.add_argument(
        "--explain", metavar="OUT.png", help="write a contact sheet: the ROI and each candidate's best view"
    )
    out.add_argument(
        "--export",
        metavar="DIR",
        help="write the best model's mesh (materials, textures) and model_info.json for a pose estimator",
    )
    out.add_argument(
        "--export-units",
        default="m",
        choices=["m", "mm", "source"],
        help="units of the exported mesh (default m; source: the file as it is; bop is always mm)",
    )
    out.add_argument(
        "--export-format",
        default="mesh",
        choices=["mesh", "bop"],
        help="mesh: the source file type; bop: models/obj_000001.ply (mm) + models_info.json",
    )
    out.add_argument("--no-progress", action="store_true", help="no progress bar in batch mode")
    return p


def _check_args(args: argparse.Namespace) -> str | None:
    if args.queries:
        if args.image or args.prompt or args.box or args.mask:
            return "--queries takes image, prompt, box and mask from the file; drop --image/--prompt/--box/--mask"
        if args.explain or args.export:
            return "--explain and --export apply to single queries (--image/--prompt), not to --queries"
        return None
    if not args.image or args.prompt is None:
        return "give --image PHOTO and --prompt TEXT (or --queries FILE.jsonl)"
    if args.output:
        return "--output is for --queries batches; single queries print to stdout"
    return None


def _prevalidate(args: argparse.Namespace) -> None:
    """Reject bad photos, prompts, boxes and masks before any model is loaded."""
    from pipeline.query.images import box_to_working, clean_prompt, load_mask, load_photo, parse_box
    from pipeline.query.settings import QuerySettings

    limits = QuerySettings(threshold=0.0)
    clean_prompt(args.prompt, limits.max_prompt_chars)
    photo = load_photo(args.image, max_side=limits.max_side, min_side=limits.min_side)
    if args.box and not args.mask:
        box_to_working(parse_box(args.box), photo, limits.min_roi_side)
    if args.mask:
        load_mask(args.mask, photo, limits.min_roi_side)


def quiet_model_loading() -> None:
    """No download bars or tokenizer-fork warnings from Hugging Face libraries (also used by pipeline.serve)."""
    import os

    os.environ.setdefault("HF_HUB_DISABLE_PROGRESS_BARS", "1")
    os.environ.setdefault("TRANSFORMERS_VERBOSITY", "error")
    os.environ.setdefault("TOKENIZERS_PARALLELISM", "false")


def main(argv: list[str] | None = None) -> int:
    args = build_parser().parse_args(argv)
    problem = _check_args(args)
    if problem:
        return fail(problem)
    from pipeline.threads import apply_torch_threads

    apply_torch_threads(args.torch_threads)  # first: before NumPy's BLAS or torch are loaded
    from pipeline.models.registry import ModelLoadError
    from pipeline.query.errors import QueryError, StoreUnavailable
    from pipeline.store import StoreError

    try:
        if not args.queries:
            _prevalidate(args)
        return _run(args)
    except (QueryError, StoreError, ModelLoadError, StoreUnavailable) as exc:
        return fail(str(exc))
    except ValueError as exc:  # --model syntax, unknown roles
        return fail(str(exc))
    except OSError as exc:  # a store file that vanished or cannot be read
        return fail(f"cannot read the store {args.store}: {type(exc).__name__}: {str(exc).splitlines()[0]}")
    except KeyboardInterrupt:
        return fail("interrupted", 130)


def open_retriever(args: argparse.Namespace, **extra):
    """A :class:`Retriever` over ``args.store`` from the readers' shared options (profile, models, device,
    cache, DuckDB threads); models load when first needed. Used by query and serve."""
    from pipeline.profiles import parse_overrides
    from pipeline.query.api import Retriever

    quiet_model_loading()
    if getattr(args, "stage1", None):
        extra["settings_changes"] = {**extra.get("settings_changes", {}), "stage1": args.stage1}
    return Retriever.open(
        args.store,
        profile=args.profile,
        model_overrides=parse_overrides(args.model),
        device=args.device,
        use_cache=not args.no_cache,
        threads=args.threads,
        preload=False,
        **extra,
    )


def _run(args: argparse.Namespace) -> int:
    import json

    from pipeline.query.errors import QueryError

    settings_changes = {
        "prompt_weight": args.prompt_weight,
        "verify": args.verify,
        "verify_top": args.verify_top,
        "accept_model": args.accept_model,
        "adapter": args.adapter,
    }
    retriever = open_retriever(args, settings_changes=settings_changes)
    rank_args = {
        "roi_mode": args.roi,
        "mode": args.mode,
        "threshold": args.threshold,
        "fallback_k": args.fallback_k,
        "fallback_unit": args.fallback_unit,
        "top": args.top,
        "accept_threshold": args.accept_threshold,
    }
    with retriever:
        if args.queries:
            retriever.load_models(retriever.required_roles())
            return _batch(retriever, args, rank_args)
        source = "mask" if args.mask else "box" if args.box else "detector"
        if source == "detector" and retriever.profile.detector is None:
            raise QueryError(
                f"the {retriever.profile.name} profile has no object detector: pass --box x0,y0,x1,y1 or "
                "--mask MASK.png (or query with --profile paper)"
            )
        retriever.load_models(retriever.required_roles(source, args.roi))
        result = retriever.query(args.image, args.prompt, box=args.box, mask=args.mask, **rank_args)
        result.timings["model_load_ms"] = sum(retriever.load_seconds.values()) * 1000
        extra = _side_outputs(retriever, result, args)
        if args.json:
            print(json.dumps({**result.to_dict(), **extra}, indent=2))
        else:
            from pipeline.query.output import format_result

            print(format_result(result))
            for key, value in extra.items():
                print(f"{key}: {value}")
    return 0


def _side_outputs(retriever, result, args) -> dict:
    extra: dict = {}
    if args.explain:
        from pipeline.query.explain import write_explain

        views = retriever.candidate_views([c.mesh_id for c in result.candidates])
        extra["explain"] = str(write_explain(result, views, args.explain))
    if args.export:
        from pipeline.query.errors import QueryError
        from pipeline.query.export import export_model

        best = result.best
        if best is None:
            raise QueryError("no model to export: the query matched nothing")
        prior = {k: getattr(best, k) for k in ("best_view", "best_view_pose", "intrinsics")}
        done = export_model(
            retriever.mesh(best.mesh_id),
            args.export,
            units=args.export_units,
            fmt=args.export_format,
            prior=prior,
        )
        extra["export"] = str(done.folder)
        extra["exported_files"] = [str(f) for f in done.files]
        if not done.unchanged:
            print(f"warning: {done.files[0]} changed since onboarding; re-run onboarding", file=sys.stderr)
    return extra


def _batch(retriever, args, rank_args) -> int:
    from pipeline.query.batch import run_batch

    if args.output:
        try:
            out = open(args.output, "w", encoding="utf-8")  # noqa: SIM115 - closed below
        except OSError as exc:
            return fail(f"cannot write {args.output}: {exc.strerror}")
    else:
        out = sys.stdout
    try:
        ok, failed = run_batch(retriever, args.queries, out, progress=not args.no_progress, **rank_args)
    finally:
        if out is not sys.stdout:
            out.close()
    if failed:
        print(
            f"{failed} of {ok + failed} queries failed; see the error field of their lines", file=sys.stderr
        )
        return 1
    return 0
