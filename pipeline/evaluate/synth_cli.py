"""``python -m pipeline.evaluate synth (--store STORE | --library DIR) --out DIR``: write a synthetic query set."""

from __future__ import annotations

import argparse
import json

from pipeline.cli_common import OneLineParser, fail, image_size, non_negative_int, number_list, positive_int


def build_parser() -> argparse.ArgumentParser:
    from pipeline.evaluate.backgrounds import BACKGROUND_KINDS
    from pipeline.evaluate.library import DEFAULT_CLASS_PATTERN
    from pipeline.evaluate.prompts import DEFAULT_PROMPT_TEMPLATE

    p = OneLineParser(
        prog="python -m pipeline.evaluate synth",
        description="Render every library mesh at novel viewpoints over varied backgrounds, with exact masks; "
        "write DIR/queries.jsonl, DIR/images, DIR/masks and DIR/synth_config.json (seeded, deterministic).",
    )
    src = p.add_mutually_exclusive_group(required=True)
    src.add_argument("--store", help="use the store's active meshes (expected model = mesh_id)")
    src.add_argument("--library", help="use a library folder (expected model = path in the library)")
    p.add_argument("--out", required=True, help="output folder")
    p.add_argument("--per-mesh", type=positive_int, default=5, help="queries per mesh (default: 5)")
    p.add_argument("--seed", type=non_negative_int, default=0, help="random seed (default: 0)")
    p.add_argument(
        "--photo-dir", action="append", default=[], help="photos for background crops (repeatable)"
    )
    p.add_argument(
        "--backgrounds",
        default=",".join(BACKGROUND_KINDS),
        help="background kinds to draw from (default: %(default)s; photo needs --photo-dir)",
    )
    p.add_argument(
        "--prompt-template",
        default=DEFAULT_PROMPT_TEMPLATE,
        help="prompt; {name} = readable mesh name, {raw} = mesh name (default: %(default)r)",
    )
    p.add_argument("--names", help="JSON file: mesh name -> readable name used in prompts")
    p.add_argument(
        "--class-pattern",
        default=DEFAULT_CLASS_PATTERN,
        help="regex whose first group is the class label (default: %(default)r)",
    )
    p.add_argument(
        "--size",
        type=image_size(),
        default=(640, 480),
        help="image size WxH, sides 16..8192 (default: 640x480)",
    )
    p.add_argument(
        "--hard",
        action="store_true",
        help="the harder set: white balance, exposure, blur, noise, JPEG, partial occluders, masks a few "
        "pixels too large and loose boxes (use with --photo-dir and --backgrounds photo)",
    )
    p.add_argument(
        "--mask-grow",
        type=mask_grow_range,
        default=None,
        metavar="LO,HI",
        help="with --hard: the query mask grows by LO..HI pixels, drawn per query; negative shrinks it "
        "(default: 0,4, a segmenter's over-reach; 0,0 gives exact masks, as in labelled datasets; write "
        "--mask-grow=-2,0 when LO is negative)",
    )
    p.add_argument("--limit", type=positive_int, help="only the first N meshes")
    p.add_argument("--no-progress", action="store_true")
    return p


def mask_grow_range(text: str) -> tuple[int, int]:
    """``type=`` for ``--mask-grow``: ``LO,HI`` pixels, ``-32 <= LO <= HI <= 32``."""
    values = number_list(int, -32, 32, max_items=2)(text)
    if len(values) != 2 or values[0] > values[1]:
        raise argparse.ArgumentTypeError(f"expected LO,HI with LO <= HI, got {text!r}")
    return values


def degrade_config(args):
    """The harder set's degradations (``None`` without ``--hard``); ``--mask-grow`` without it is an error."""
    from dataclasses import replace

    from pipeline.evaluate.degrade import DegradeConfig

    if not args.hard:
        if args.mask_grow is not None:
            raise ValueError("--mask-grow needs --hard (the plain set's masks are exact)")
        return None
    cfg = DegradeConfig()
    return cfg if args.mask_grow is None else replace(cfg, mask_dilate_px=args.mask_grow)


def store_render_config(store_path: str):
    """The render config of ``store_path``'s latest onboarding run (``None`` if it recorded none)."""
    from pipeline.query.library import latest_onboarding
    from pipeline.store import Store

    with Store.open(store_path) as store:
        return latest_onboarding(store).render_config()


def main(argv: list[str]) -> int:
    args = build_parser().parse_args(argv)
    from dataclasses import replace
    from pathlib import Path

    from pipeline.evaluate.library import read_folder_meshes, read_store_meshes
    from pipeline.evaluate.synth import SynthConfig, generate
    from pipeline.store import StoreError

    try:
        w, h = args.size
        names = json.loads(Path(args.names).read_text()) if args.names else {}
        cfg = SynthConfig(
            per_mesh=args.per_mesh,
            seed=args.seed,
            width=w,
            height=h,
            backgrounds=tuple(b.strip() for b in args.backgrounds.split(",") if b.strip()),
            photo_dirs=tuple(args.photo_dir),
            prompt_template=args.prompt_template,
            names=names,
            class_pattern=args.class_pattern or None,
            degrade=degrade_config(args),
        )
        if args.store:  # avoid the views this store was rendered with
            cfg = replace(cfg, onboarding=store_render_config(args.store) or cfg.onboarding)
        meshes = read_store_meshes(args.store) if args.store else read_folder_meshes(args.library)
    except (ValueError, OSError, StoreError) as exc:  # QueryError is a ValueError
        return fail(str(exc))
    if args.limit:
        meshes = meshes[: args.limit]
    if not meshes:
        return fail("no meshes to render")
    queries = generate(meshes, args.out, cfg, progress=not args.no_progress)
    print(f"{len(queries)} queries from {len(meshes)} meshes -> {Path(args.out) / 'queries.jsonl'}")
    return 0
