"""``python -m pipeline.evaluate --store STORE --queries QUERIES --out REPORT_DIR``: metrics, sweeps, report.

See ``docs/evaluation.md`` for every option and the metric definitions.
"""

from __future__ import annotations

import argparse
import shlex
import sys
from pathlib import Path

from pipeline.cli_common import (
    OneLineParser,
    add_model_args,
    fail,
    float_range,
    int_range,
    model_overrides,
    non_negative_int,
    number_list,
    positive_int,
)
from pipeline.query.modes import MODES

OFFLINE_NOTE = (
    "Offline profile: attribute captioner + MiniLM text encoder + classical image descriptor, no downloaded "
    "weights. These numbers measure this build's offline models, not the paper's LLaVA/CLIP/DINOv2/"
    "GroundedSAM pipeline; reproducing the paper's numbers needs `--profile paper` with the real weights."
)


_floats = number_list(float, -1.0, 1.0)  # tau values: ``0.1,0.2`` or ``START:STOP:STEP`` (inclusive)
_ints = number_list(int, 1)  # fallback top-k values


def _words(text: str) -> tuple[str, ...]:
    return tuple(w.strip() for w in text.split(",") if w.strip())


def build_parser() -> argparse.ArgumentParser:
    from pipeline.evaluate.library import DEFAULT_CLASS_PATTERN
    from pipeline.evaluate.metrics import MAP_NORMALISERS, METRIC_SETS, TIE_POLICIES
    from pipeline.evaluate.prompts import DEFAULT_PROMPT_TEMPLATE

    p = OneLineParser(
        prog="python -m pipeline.evaluate",
        description="Evaluate retrieval on a query set: the paper's metrics, tau/top-k/mode/ROI sweeps, "
        "prompt styles, and a report (metrics.json, report.md, report.html, plots, failure gallery). "
        "`python -m pipeline.evaluate synth --help` writes a synthetic query set; "
        "`python -m pipeline.evaluate openset --help` calibrates open-set acceptance; "
        "`python -m pipeline.evaluate pose_prior --help` measures the best view's pose prior.",
    )
    p.add_argument("--store", required=True, metavar="STORE_DIR", help="onboarded store to query")
    src = p.add_argument_group("queries")
    src.add_argument("--queries", metavar="PATH", help="JSONL/JSON/CSV query file or BOP dataset folder")
    src.add_argument(
        "--synthetic",
        type=positive_int,
        metavar="N",
        help="generate N synthetic queries per store mesh into OUT/synthetic",
    )
    src.add_argument(
        "--seed", type=non_negative_int, default=0, help="seed of the synthetic generator (default: 0)"
    )
    src.add_argument(
        "--photo-dir",
        action="append",
        default=[],
        metavar="DIR",
        help="real photos to crop synthetic backgrounds from (repeatable)",
    )
    src.add_argument(
        "--prompt-template",
        default=DEFAULT_PROMPT_TEMPLATE,
        help="synthetic/BOP prompt; {name} = mesh name without its id (default: %(default)r)",
    )
    src.add_argument("--limit", type=positive_int, help="evaluate only the first N queries")
    src.add_argument(
        "--boxes-only",
        action="store_true",
        help="ignore the queries' masks: box-only ROIs (a mask-only query uses its mask's box)",
    )
    src.add_argument("--bop-objects", metavar="JSON", help="BOP object id -> mesh (and prompt, label) map")
    src.add_argument(
        "--bop-min-visib", type=float_range(0.0, 1.0), default=0.1, help="skip BOP instances less visible"
    )
    src.add_argument("--bop-max-per-object", type=positive_int, help="at most N BOP queries per object id")
    rel = p.add_argument_group("relevance and metrics")
    rel.add_argument(
        "--class-pattern",
        default=DEFAULT_CLASS_PATTERN,
        help="regex whose first group is a mesh's class label (default: %(default)r; '' = the mesh name)",
    )
    rel.add_argument(
        "--classes", metavar="FILE", help="JSON/CSV mesh -> class label map (wins over the pattern)"
    )
    rel.add_argument(
        "--metrics",
        default="paper",
        choices=METRIC_SETS,
        help="paper: the reference scripts' definitions (mAP@k over library views, hits normaliser; NN, FT, "
        "ST, F, nDCG, AP, ANMRR as the reference computes them); standard: textbook definitions over the "
        "ranked meshes (default: %(default)s; docs/evaluation.md)",
    )
    rel.add_argument(
        "--ties",
        default="pessimistic",
        choices=TIE_POLICIES,
        help="order of equal scores (default: %(default)s)",
    )
    rel.add_argument(
        "--map-norm",
        default="min",
        choices=MAP_NORMALISERS,
        help="AP@k normaliser of --metrics standard: min(k,R), R, or hits in the top k (default: %(default)s; "
        "the paper set always uses hits)",
    )
    add_model_args(p)
    p.add_argument("--device", help="torch device for the paper profile (default: cuda when available)")
    base = p.add_argument_group("base setting")
    base.add_argument("--mode", default="two-stage", choices=MODES)
    base.add_argument(
        "--tau",
        type=float_range(-1.0, 1.0),
        help="stage-1 threshold (default: the retriever's, the paper's 0.37)",
    )
    base.add_argument(
        "--fallback-k", type=positive_int, default=10, help="stage-1 top-k when none passes tau (default: 10)"
    )
    base.add_argument(
        "--fallback-unit",
        default="captions",
        choices=["captions", "meshes"],
        help="what --fallback-k counts: caption rows, kept as their distinct models (paper, default), or models",
    )
    base.add_argument("--roi", default="segm", choices=["segm", "bbox"], help="ROI variant (default: segm)")
    base.add_argument(
        "--verify",
        action=argparse.BooleanOptionalAction,
        default=None,
        help="local-feature verification of the top candidates (default: the profile's; offline: on)",
    )
    base.add_argument(
        "--verify-top", type=int_range(0, 1000), help="candidates verified per query, 0..1000 (default: 20)"
    )
    base.add_argument(
        "--adapter",
        action=argparse.BooleanOptionalAction,
        default=None,
        help="rank with the store's query adapter of the learned encoder (default: on where the store has "
        "one that matches its models; docs/query.md)",
    )
    sw = p.add_argument_group("sweeps")
    sw.add_argument(
        "--taus", type=_floats, default=None, help="tau values, e.g. 0.10:0.65:0.05 (the default)"
    )
    sw.add_argument("--top-ks", type=_ints, default=None, help="fallback top-k values (default: 5:40:5)")
    sw.add_argument("--modes", type=_words, default=None, help="modes to compare (default: all three)")
    sw.add_argument("--rois", type=_words, default=None, help="ROI variants to compare (default: segm,bbox)")
    sw.add_argument("--no-sweeps", action="store_true", help="score the base setting only")
    sw.add_argument(
        "--style-store",
        action="append",
        default=[],
        metavar="STYLE=STORE",
        help="a store onboarded with another prompt style, compared at the base setting (repeatable)",
    )
    sw.add_argument(
        "--onboard-styles",
        type=_words,
        metavar="STYLE,...",
        help="onboard --library once per prompt style into --styles-dir (if missing) and compare",
    )
    sw.add_argument("--library", metavar="DIR", help="library folder for --onboard-styles")
    sw.add_argument(
        "--styles-dir", metavar="DIR", help="where --onboard-styles puts its stores (default: OUT/stores)"
    )
    out = p.add_argument_group("report")
    out.add_argument("--out", required=True, metavar="REPORT_DIR", help="report directory (created)")
    out.add_argument(
        "--group-by",
        action="append",
        default=None,
        metavar="KEY",
        help="also break the base metrics down by a query field or metadata key (repeatable; default: "
        "background, when the queries have it)",
    )
    out.add_argument(
        "--gallery", type=non_negative_int, default=24, help="failures shown in the gallery (default: 24)"
    )
    out.add_argument("--no-plots", action="store_true", help="skip the matplotlib figures")
    out.add_argument("--no-progress", action="store_true", help="no progress bars")
    return p


def main(argv: list[str] | None = None) -> int:
    argv = sys.argv[1:] if argv is None else argv
    if argv[:1] == ["synth"]:
        from pipeline.evaluate.synth_cli import main as synth_main

        return synth_main(argv[1:])
    if argv[:1] == ["openset"]:
        from pipeline.evaluate.openset_cli import main as openset_main

        return openset_main(argv[1:])
    if argv[:1] == ["pose_prior"]:
        from pipeline.evaluate.pose_prior import main as pose_prior_main

        return pose_prior_main(argv[1:])
    args = build_parser().parse_args(argv)
    if not args.queries and not args.synthetic:
        return fail("give --queries PATH or --synthetic N")
    from pipeline.evaluate.cli_errors import run_reporting_errors

    return run_reporting_errors(_run, args, argv)


def _run(args: argparse.Namespace, argv: list[str]) -> int:
    import json
    from datetime import datetime, timezone

    from pipeline.evaluate.engine import Engine, Setting
    from pipeline.evaluate.library import Library, load_class_map, read_store_meshes
    from pipeline.evaluate.report import write_report
    from pipeline.evaluate.sweep import MetricOptions, SweepPlan, evaluate, evaluate_styles, group_metrics

    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    class_map = load_class_map(args.classes) if args.classes else {}
    pattern = args.class_pattern or None
    library = Library(read_store_meshes(args.store), pattern, class_map)
    if not len(library):
        return fail(f"store {args.store} has no active meshes")
    queries, source = _queries(args, library, out)
    if args.limit:
        queries = queries[: args.limit]
    if args.boxes_only:
        from pipeline.evaluate.datasets import drop_mask

        queries = [drop_mask(q) for q in queries]
    if not queries:
        return fail(f"no queries in {source}")
    overrides = model_overrides(args)
    progress = not args.no_progress
    say = print if progress else (lambda *a, **k: None)
    say(f"{len(queries)} queries, {len(library)} library meshes; loading the {args.profile} models")
    changes = {"verify": args.verify, "verify_top": args.verify_top, "adapter": args.adapter}
    engine = Engine.open(args.store, args.profile, overrides, args.device, settings_changes=changes)
    base = Setting(args.mode, args.tau, args.fallback_k, args.roi, args.fallback_unit)
    plan = SweepPlan(base=base)
    for name in ("taus", "top_ks", "modes", "rois"):
        if getattr(args, name):
            setattr(plan, name, getattr(args, name))
    opts = MetricOptions(args.ties, args.map_norm, args.metrics)
    run = evaluate(engine, queries, library, plan, opts, sweeps=not args.no_sweeps, progress=_bar(progress))

    # adapters already loaded by the main retriever are shared with style onboarding and style retrievers
    shared = engine.retriever.models.snapshot()
    styles = _style_stores(args, out, shared)
    style_results = None
    if styles:
        engines = {}
        for style, store in styles.items():
            lib = Library(read_store_meshes(store), pattern, class_map)
            engines[style] = (Engine.open(store, args.profile, overrides, args.device, models=shared), lib)
        style_results = evaluate_styles(engines, queries, base, opts)
        for style, store in styles.items():
            style_results[style]["store"] = store

    summary = run.summary()
    doc = {
        "config": {
            "command": "python -m pipeline.evaluate " + shlex.join(argv),
            "store": str(args.store),
            "profile": args.profile,
            "model_overrides": overrides,
            "queries": source,
            "metric_set": opts.metric_set,
            "ties": opts.ties,
            "map_normaliser": "hits (views)" if opts.metric_set == "paper" else opts.map_normaliser,
            "class_pattern": pattern,
            "classes": args.classes,
            "created_at": datetime.now(timezone.utc).isoformat(timespec="seconds"),
            "note": OFFLINE_NOTE if args.profile == "offline" else None,
        },
        "n_queries": len(queries),
        "n_evaluated": len(run.records),
        "unresolved": run.unresolved,
        "failed": run.failed,
        "library": {"n_meshes": len(library), "n_classes": len(set(library.labels.values()))},
        **summary,
        "prompt_styles": style_results,
        "groups": {
            key: group_metrics(run.records, key, opts.metric_set) for key in _group_keys(args, run.records)
        },
    }
    paths = write_report(doc, run.records, out, args.store, library, args.gallery, plots=not args.no_plots)
    inst = doc["base"]["instance"]
    paper = opts.metric_set == "paper"
    first = (
        ("mAP@1", "mAP@5", "NN", "FT", "AP", "ANMRR")
        if paper
        else ("mAP@1", "mAP@5", "top1", "top5", "FT", "ANMRR")
    )
    second = ("NN", "FT", "ST", "F", "nDCG", "ANMRR") if paper else ("NN", "FT", "ST", "F", "DCG", "ANMRR")
    print(f"metric set: {opts.metric_set}" + (" (reference scripts' definitions; NN in %)" if paper else ""))
    print(
        "instance: "
        + ", ".join(f"{k} {inst.get(k, float('nan')):.3f}" for k in first)
        + f" (n={inst.get('n', 0)})"
    )
    if doc["base"].get("class"):
        cls = doc["base"]["class"]
        print("class:    " + ", ".join(f"{k} {cls.get(k, float('nan')):.3f}" for k in second))
    if run.unresolved or run.failed:
        print(
            f"warning: {len(run.unresolved)} queries name no library mesh, {len(run.failed)} failed "
            f"(listed in {paths['metrics']})",
            file=sys.stderr,
        )
    print(f"report: {paths['html']} ({paths['metrics'].name}, {paths['markdown'].name})")
    json.dumps(doc["base"], default=str)  # fail here, not in a reader, if something is not serialisable
    return 0


def _queries(args, library, out: Path):
    from pipeline.evaluate.datasets import load_queries

    if args.synthetic:
        from pipeline.evaluate.synth import SynthConfig, generate

        cfg = SynthConfig(
            per_mesh=args.synthetic,
            seed=args.seed,
            photo_dirs=tuple(args.photo_dir),
            prompt_template=args.prompt_template,
            class_pattern=args.class_pattern or None,
        )
        target = out / "synthetic"
        return generate(library.meshes, target, cfg, progress=not args.no_progress), str(
            target / "queries.jsonl"
        )
    bop = {
        "library": library,
        "objects": args.bop_objects,
        "prompt_template": args.prompt_template,
        "min_visib": args.bop_min_visib,
        "max_per_object": args.bop_max_per_object,
    }
    return load_queries(args.queries, **bop), str(args.queries)


def _style_stores(args, out: Path, models: dict | None = None) -> dict[str, str]:
    styles: dict[str, str] = {}
    for item in args.style_store:
        style, sep, store = item.partition("=")
        if not sep or not style or not store:
            raise ValueError(f"--style-store expects STYLE=STORE_DIR, got {item!r}")
        styles[style.strip()] = store.strip()
    if args.onboard_styles:
        if not args.library:
            raise ValueError("--onboard-styles needs --library DIR (the library to onboard per style)")
        from pipeline.onboard.config import OnboardConfig
        from pipeline.onboard.run import run_onboarding

        root = Path(args.styles_dir or out / "stores")
        reuse = _onboarded_from(args.store) == {str(Path(args.library).resolve())}
        for style in args.onboard_styles:
            store = root / style
            if reuse and not store.exists():
                # start from a copy of --store: same renders and image embeddings (same fingerprints), so
                # onboarding only re-captions and re-embeds the captions for this style
                import shutil

                shutil.copytree(args.store, store, ignore=shutil.ignore_patterns("_lock", "_cache", "*.tmp"))
            cfg = OnboardConfig(
                profile=args.profile, model_overrides=model_overrides(args), prompt_style=style
            )
            summary = run_onboarding(
                args.library, str(store), cfg, progress=not args.no_progress, models=models
            )
            print(f"prompt style {style}: " + summary.lines()[0])
            styles[style] = str(store)
    return styles


def _group_keys(args, records) -> list[str]:
    if args.group_by is not None:
        return list(args.group_by)
    return ["background"] if any("background" in r.query.meta for r in records) else []


def _onboarded_from(store_path: str) -> set[str]:
    """Library roots of a store's active meshes."""
    from pipeline.evaluate.library import read_store_meshes

    return {m.library_root for m in read_store_meshes(store_path)}


def _bar(progress: bool):
    if not progress:
        return None
    from pipeline.progress import iterate  # tqdm on a terminal, plain lines in a log

    return lambda it: iterate(it, "queries", unit="query")


if __name__ == "__main__":
    sys.exit(main())
