"""``python -m pipeline.evaluate openset --store STORE --queries Q.jsonl [--queries ...] --out DIR``: fit,
cross-validate and (``--install``) ship the open-set acceptance calibration (``docs/query.md``)."""

from __future__ import annotations

import argparse
import json
import shlex
import sys
from datetime import datetime, timezone
from pathlib import Path

from pipeline.cli_common import (
    OneLineParser,
    add_model_args,
    fail,
    float_range,
    model_overrides,
    positive_int,
)


def build_parser() -> argparse.ArgumentParser:
    from pipeline.evaluate.library import DEFAULT_CLASS_PATTERN

    p = OneLineParser(
        prog="python -m pipeline.evaluate openset",
        description="Calibrate open-set acceptance: answer each query against the full store and, for the "
        "objects left out (default: the 21 YCB-Video objects), against the store without them; fit "
        "P(top-1 right) per ranking variant, cross-validated leaving one object out; write DIR/report.md, "
        "DIR/openset.json, DIR/examples.jsonl and DIR/calibration.json.",
    )
    p.add_argument("--store", required=True, metavar="STORE_DIR", help="the full store (read only)")
    p.add_argument(
        "--queries", action="append", required=True, metavar="PATH", help="query file (repeatable)"
    )
    p.add_argument("--out", required=True, metavar="DIR", help="report folder")
    p.add_argument(
        "--weigh-together",
        action="append",
        default=[],
        metavar="NAMES",
        help="query files (names without extension, comma-separated) that share one weight in the fit and "
        "the operating point, e.g. ycb_photos,bbq_sauce: the real photos (repeatable; each other file "
        "weighs alone)",
    )
    p.add_argument(
        "--absent",
        default="ycb-video",
        help="class labels left out of the library, comma-separated, or 'ycb-video' (default: the 21 "
        "YCB-Video objects)",
    )
    p.add_argument(
        "--rois", default="mask,box", help="ROI variants per query: mask, box (GrabCut) (default: both)"
    )
    p.add_argument(
        "--target",
        type=float_range(0.5, 1.0),
        default=0.97,
        help="share of the training folds' correct answers the operating point accepts, each query file "
        "weighing the same (default 0.97)",
    )
    p.add_argument("--c", type=float_range(1e-4, 1e4), default=1.0, help="inverse L2 strength (default 1)")
    p.add_argument(
        "--class-pattern", default=DEFAULT_CLASS_PATTERN, help="regex of a mesh name's class label"
    )
    add_model_args(p)
    p.add_argument("--device", help="torch device (default: cuda when available)")
    p.add_argument("--limit", type=positive_int, help="only the first N queries of each file")
    p.add_argument(
        "--install",
        action="store_true",
        help="also write the calibration into the package (pipeline/query/calibration/PROFILE.json), "
        "where queries read it by default",
    )
    p.add_argument(
        "--embeddings",
        metavar="FILE.pkl",
        help="keep the query embeddings here and reuse them on the next run of the same store and "
        "models (a local cache: only ranking and fitting are redone)",
    )
    p.add_argument("--no-progress", action="store_true")
    return p


def main(argv: list[str]) -> int:
    args = build_parser().parse_args(argv)
    from pipeline.evaluate.cli_errors import run_reporting_errors

    return run_reporting_errors(_run, args, argv)


def _weight_groups(specs: list[str], stems: set[str]) -> dict[str, str] | str:
    """``--weigh-together`` as {file name: its group's name}, or a one-line error (an unknown name, a name in
    two groups)."""
    groups: dict[str, str] = {}
    for spec in specs:
        names = [n.strip() for n in spec.split(",") if n.strip()]
        unknown = sorted(set(names) - stems)
        if unknown:
            return f"--weigh-together names {', '.join(unknown)}, not a --queries file (names: {', '.join(sorted(stems))})"
        for n in names:
            if n in groups:
                return f"--weigh-together names {n} twice"
            groups[n] = "+".join(names)
    return groups


def _absent_labels(text: str) -> set[str]:
    from pipeline.evaluate.openset import YCB_VIDEO_LABELS

    labels: set[str] = set()
    for w in (w.strip() for w in text.split(",")):
        if w == "ycb-video":
            labels |= set(YCB_VIDEO_LABELS)
        elif w:
            labels.add(w)
    if not labels:
        raise ValueError("--absent names no class label")
    return labels


def _run(args: argparse.Namespace, argv: list[str]) -> int:
    from pipeline.evaluate.datasets import load_queries
    from pipeline.evaluate.library import Library, read_store_meshes
    from pipeline.evaluate.openset import collect
    from pipeline.evaluate.openset_split import mesh_ids_with_labels, without_meshes
    from pipeline.fingerprint import fingerprint
    from pipeline.query import Retriever
    from pipeline.query.accept import model_identities

    rois = tuple(r.strip() for r in args.rois.split(",") if r.strip())
    if not rois or set(rois) - {"mask", "box"}:
        return fail("--rois takes mask and/or box")
    absent = _absent_labels(args.absent)
    library = Library(read_store_meshes(args.store), args.class_pattern or None)
    drop = mesh_ids_with_labels(library, absent)
    if not drop:
        return fail(f"no mesh of the store has one of the labels {', '.join(sorted(absent))}")
    queries = []
    for path in args.queries:
        qs = load_queries(path)[: args.limit] if args.limit else load_queries(path)
        queries += [(q, Path(path).stem) for q in qs]
    together = _weight_groups(args.weigh_together, {Path(p).stem for p in args.queries})
    if isinstance(together, str):
        return fail(together)
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    errors: list[dict] = []
    with Retriever.open(
        args.store, profile=args.profile, model_overrides=model_overrides(args), device=args.device
    ) as full:
        reduced = without_meshes(full, drop)
        cache_key = fingerprint({"version": full.version, "models": full.tables.onboarding.models,
                                 "settings": repr(full.settings)})  # fmt: skip
        embeddings = _load_embeddings(args.embeddings, cache_key)
        examples = collect(
            full,
            reduced,
            queries,
            library,
            absent,
            rois,
            progress=not args.no_progress,
            on_error=lambda qid, msg: errors.append({"query_id": qid, "error": msg}),
            embeddings=embeddings,
        )
        _save_embeddings(args.embeddings, cache_key, embeddings)
        default = _default_variant(full)
        models = model_identities(
            full.profile, full.tables.onboarding, full.learned is not None, full.settings
        )
        profile = full.profile.name
    for e in examples:
        e.weight_group = together.get(e.source)
    command = "python -m pipeline.evaluate openset " + " ".join(shlex.quote(a) for a in argv)
    _write_examples(examples, out / "examples.jsonl")  # the answers first: fitting takes a while
    summary, calibration = _fit_all(examples, default, args, profile, models, command, len(drop))
    summary["errors"] = errors
    (out / "openset.json").write_text(json.dumps(summary, indent=1) + "\n")
    _write_examples(examples, out / "examples.jsonl")  # now with the out-of-fold confidences
    calibration.write(out / "calibration.json")
    from pipeline.evaluate.openset_report import write_markdown

    write_markdown(summary, out / "report.md")
    if args.install:
        from pipeline.query.accept import shipped_path

        print(f"installed {calibration.write(shipped_path(profile))}")
    print(_headline(summary))
    print(f"report: {out / 'report.md'}")
    return 0 if not errors else 1


def _write_examples(examples, path: Path) -> None:
    with open(path, "w", encoding="utf-8") as f:
        for e in examples:
            f.write(json.dumps(e.to_json()) + "\n")


def _load_embeddings(path: str | None, key: str) -> dict:
    """The embedding cache at ``path`` when it was written for ``key`` (else an empty one)."""
    import pickle

    if not path or not Path(path).is_file():
        return {}
    try:
        with open(path, "rb") as f:
            saved = pickle.load(f)  # noqa: S301 - a local cache this command wrote
    except (OSError, pickle.UnpicklingError, EOFError, AttributeError):
        return {}
    return saved.get("items", {}) if isinstance(saved, dict) and saved.get("key") == key else {}


def _save_embeddings(path: str | None, key: str, items: dict) -> None:
    import pickle

    if path:
        tmp = Path(str(path) + ".tmp")
        with open(tmp, "wb") as f:
            pickle.dump({"key": key, "items": items}, f)
        tmp.replace(path)


def _default_variant(retriever) -> str:
    from pipeline.query.accept import variant_of

    s = retriever.settings
    return variant_of("two-stage", bool(s.verify and retriever.verifier.available))


def _fit_all(examples, default, args, profile, models, command, n_dropped):
    from dataclasses import asdict

    from pipeline.evaluate.openset import (
        calibration_error,
        cross_validate,
        fit,
        rates_at,
        rejection_curve,
        select_features,
        usable_features,
    )
    from pipeline.query.accept import Calibration

    by_variant: dict[str, list] = {}
    for e in examples:
        by_variant.setdefault(e.variant, []).append(e)
    variants, fitted = {}, {}
    for name, exs in sorted(by_variant.items()):
        feats = usable_features(exs)
        if not feats or all(e.correct for e in exs) or not any(e.correct for e in exs):
            continue
        picked = cross_validate(exs, feats, args.target, args.c, select=True)
        chosen = select_features(exs, feats, args.target, args.c)
        model = fit(exs, chosen, args.target, args.c)
        fitted[name] = model
        slices = {}
        for src in sorted({e.source for e in exs}):
            for roi in sorted({e.roi for e in exs}):
                part = [e for e in exs if e.source == src and e.roi == roi]
                if part:
                    slices[f"{src} / {roi}"] = asdict(rates_at(part))
        variants[name] = {
            "features": list(chosen),
            "features_per_fold": picked,
            "threshold": model.threshold,
            "n_answers": len(exs),
            "n_groups": len({e.group for e in exs}),
            "out_of_fold": asdict(rates_at(exs)),
            "slices": slices,
            "calibration_error": calibration_error(exs),
            "curve": rejection_curve(exs),
        }
    if default not in fitted:
        raise ValueError(f"no answers to fit the default variant {default}")
    fit_info = {
        "command": command,
        "date": datetime.now(timezone.utc).strftime("%Y-%m-%dT%H:%M:%SZ"),
        "queries": [str(q) for q in args.queries],
        "absent": args.absent,
        "meshes_left_out": n_dropped,
        "target": args.target,
        "cv": "leave one object out",
        "out_of_fold": {k: v["out_of_fold"] for k, v in variants.items()},
    }
    cal = Calibration(profile, models, fitted, fit_info)
    summary = {"default_variant": default, "variants": variants, "fit": fit_info}
    return summary, cal


def _headline(summary: dict) -> str:
    v = summary["variants"][summary["default_variant"]]["out_of_fold"]

    def pct(d):
        return (
            "-" if d["rate"] is None else f"{100 * d['rate']:.1f}% [{100 * d['lo']:.1f}, {100 * d['hi']:.1f}]"
        )

    return (
        f"{summary['default_variant']} (out of fold): absent rejected {pct(v['absent_rejected'])}, "
        f"correct accepted {pct(v['correct_accepted'])}, wrong rejected {pct(v['wrong_rejected'])}"
    )


if __name__ == "__main__":  # pragma: no cover
    sys.exit(main(sys.argv[1:]))
