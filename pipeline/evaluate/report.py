"""Write a report directory: ``metrics.json``, ``per_query.jsonl``, ``report.md``, ``report.html``,
``plots/*.png`` and ``gallery/*.png``."""

from __future__ import annotations

import html
import json
import math
from pathlib import Path

from pipeline.evaluate.metrics import headline

SWEEP_COLUMNS = ("mAP@1", "mAP@5", "top1", "top5", "FT", "DCG", "ANMRR")
PAPER_SWEEP_COLUMNS = ("mAP@1", "mAP@5", "mAP@10", "NN", "FT", "nDCG", "ANMRR")
GROUP_COLUMNS = {
    "paper": ("n", "mAP@1", "mAP@5", "n_mi3dor", "NN", "FT", "ANMRR"),  # n_mi3dor: what NN..ANMRR count
    "standard": ("n", "mAP@1", "mAP@5", "top1", "top5", "FT", "ANMRR"),
}
SET_NOTES = {
    "paper": "Metric set `paper`: the reference scripts' definitions (what the paper's numbers mean): mAP@k "
    "ranks library views (each carries its mesh's label) and averages the precision at the hits in the top "
    "k; NN (in %), FT, ST, F, nDCG, AP and ANMRR over the ranked meshes with kappa = relevant meshes in the "
    "ranking, queries with none left out (n_mi3dor). See docs/evaluation.md.",
    "standard": "Metric set `standard`: textbook definitions over the ranked meshes: mAP@k normalised by "
    "the chosen normaliser, top-k accuracy, and NN, FT, ST, F, DCG, MPEG-7 ANMRR with kappa = relevant "
    "meshes in the library. See docs/evaluation.md.",
}


def _set_of(doc: dict) -> str:
    return doc["config"].get("metric_set", "standard")


def sweep_columns(metric_set: str) -> tuple[str, ...]:
    return PAPER_SWEEP_COLUMNS if metric_set == "paper" else SWEEP_COLUMNS


def _num(v, digits: int = 3) -> str:
    if v is None or (isinstance(v, float) and math.isnan(v)):
        return "-"
    if isinstance(v, float):
        return f"{v:.{digits}f}"
    return str(v)


def _setting(summary: dict) -> str:
    s = summary["setting"]
    tau = (
        s["threshold"]
        if s["threshold"] is not None
        else f"{summary.get('threshold_used')} (retriever default)"
    )
    unit = s.get("fallback_unit", "meshes")
    return f"mode {s['mode']}, tau {tau}, fallback top-{s['fallback_k']} {unit}, ROI {s['roi']}"


def headline_table(summary: dict, metric_set: str) -> tuple[list[str], list[list[str]]]:
    """Header and rows of the headline table. The paper set's MI3DOR measures (NN to ANMRR) average over
    the queries whose ranking holds a relevant model (``n_mi3dor``), mAP@k over all (``n``): both counts
    are shown, each next to the metrics it counts."""
    names = list(headline(metric_set))
    if metric_set != "paper":
        header = ["level", "n", *names]
    else:
        maps = [k for k in names if k.startswith("mAP@")]
        rest = [k for k in names if not k.startswith("mAP@")]
        header = ["level", "n (mAP)", *maps, "n (NN..ANMRR)", *rest]
    rows = []
    for level in ("instance", "class"):
        m = summary.get(level)
        if not m:
            continue
        if metric_set != "paper":
            rows.append([level, str(m.get("n", 0))] + [_num(m.get(k)) for k in names])
        else:
            rows.append(
                [level, str(m.get("n", 0)), *[_num(m.get(k)) for k in maps]]
                + [str(m.get("n_mi3dor", 0)), *[_num(m.get(k)) for k in rest]]
            )
    return header, rows


def _sweep_rows(rows: list[dict], knob: str, metric_set: str) -> list[list[str]]:
    out = []
    for r in rows:
        v = r["setting"][knob]
        inst = r.get("instance") or {}
        cls = r.get("class") or {}
        out.append(
            [_num(v, 2) if isinstance(v, float) else ("default" if v is None else str(v))]
            + [_num(inst.get(k)) for k in sweep_columns(metric_set)]
            + [_num(cls.get("mAP@1")), _num(cls.get("FT"))]
            + [_num(r.get("fallback_rate"), 2), _num(r.get("mean_stage1"), 1)]
        )
    return out


def _sections(doc: dict, plots: dict[str, str], gallery: list[dict]) -> list[tuple[str, object]]:
    """The report as (kind, payload) blocks shared by the Markdown and HTML writers."""
    blocks: list[tuple[str, object]] = [("h1", "OSCAR retrieval evaluation")]
    cfg = doc["config"]
    mset = _set_of(doc)
    facts = [
        f"store: `{cfg['store']}`",
        f"profile: `{cfg['profile']}`"
        + (f", model overrides: `{cfg['model_overrides']}`" if cfg.get("model_overrides") else ""),
        f"queries: `{cfg['queries']}` ({doc['n_queries']} queries, {doc['n_evaluated']} evaluated, "
        f"{len(doc['unresolved'])} with no matching library mesh, {len(doc['failed'])} failed)",
        f"library: {doc['library']['n_meshes']} meshes, {doc['library']['n_classes']} classes",
        f"base setting: {_setting(doc['base'])}",
        f"metric set: `{mset}`; ties: {cfg['ties']}, mAP@k normaliser: {cfg['map_normaliser']}",
        f"command: `{cfg['command']}`",
    ]
    blocks.append(("list", facts))
    if cfg.get("note"):
        blocks.append(("p", cfg["note"]))
    blocks.append(("p", SET_NOTES[mset]))
    blocks.append(("h2", f"Headline metrics (base setting, metric set {mset})"))
    blocks.append(("table", headline_table(doc["base"], mset)))
    b = doc["base"]
    blocks.append(
        (
            "p",
            f"Fallback to top-k used for {_num(b.get('fallback_rate'), 2)} of queries; "
            f"mean stage-1 candidates {_num(b.get('mean_stage1'), 1)}; mean ranking time "
            f"{_num(b.get('mean_rank_ms'), 2)} ms.",
        )
    )
    if "rank_hist" in plots:
        blocks.append(("img", (plots["rank_hist"], "rank of the expected model")))
    cols = ["value"] + list(sweep_columns(mset)) + ["class mAP@1", "class FT", "fallback", "stage-1"]
    titles = {
        "tau": ("Threshold sweep (tau)", "threshold"),
        "fallback_k": ("Fallback top-k sweep", "fallback_k"),
        "mode": ("Retrieval modes", "mode"),
        "roi": ("ROI variants", "roi"),
    }
    for name, rows in doc["sweeps"].items():
        if not rows:
            continue
        title, knob = titles[name]
        blocks.append(("h2", f"{title} (metric set {mset})"))
        blocks.append(("table", (cols, _sweep_rows(rows, knob, mset))))
        for key in (f"{name}_sweep", f"{name}_bars"):
            if key in plots:
                blocks.append(("img", (plots[key], title)))
    if doc.get("prompt_styles"):
        blocks.append(("h2", f"Prompt styles (one onboarded store per style, metric set {mset})"))
        rows = []
        for style, s in doc["prompt_styles"].items():
            inst = s.get("instance") or {}
            rows.append([style, s.get("store", "")] + [_num(inst.get(k)) for k in sweep_columns(mset)])
        blocks.append(("table", (["style", "store"] + list(sweep_columns(mset)), rows)))
        if "styles_bars" in plots:
            blocks.append(("img", (plots["styles_bars"], "prompt styles")))
    for key, groups in (doc.get("groups") or {}).items():
        blocks.append(("h2", f"By {key} (base setting, instance level, metric set {mset})"))
        cols = list(GROUP_COLUMNS[mset])
        rows = [[value] + [_num(m.get(c)) for c in cols] for value, m in groups.items()]
        blocks.append(("table", ([key] + cols, rows)))
    if doc.get("timings"):
        blocks.append(("h2", "Timings (ms)"))
        rows = [
            [k] + [_num(v.get(x), 2) for x in ("mean", "p50", "p95", "n")] for k, v in doc["timings"].items()
        ]
        blocks.append(("table", (["stage", "mean", "p50", "p95", "n"], rows)))
    blocks.append(("h2", f"Failure gallery ({len(gallery)} shown)"))
    if not gallery:
        blocks.append(("p", "No top-1 failures at the base setting."))
    for g in gallery:
        rank = g["expected_rank"] if g["expected_rank"] is not None else "not returned"
        blocks.append(
            (
                "figure",
                (
                    g["file"],
                    f'{g["query_id"]}: "{g["prompt"]}"; expected {g["expected"]} (rank {rank}); '
                    f"retrieved {', '.join(g['retrieved'])}",
                ),
            )
        )
    return blocks


def to_markdown(blocks) -> str:
    out = []
    for kind, payload in blocks:
        if kind == "h1":
            out.append(f"# {payload}\n")
        elif kind == "h2":
            out.append(f"## {payload}\n")
        elif kind == "p":
            out.append(f"{payload}\n")
        elif kind == "list":
            out.append("\n".join(f"* {x}" for x in payload) + "\n")
        elif kind == "table":
            head, rows = payload
            lines = ["| " + " | ".join(head) + " |", "|" + "---|" * len(head)]
            lines += ["| " + " | ".join(r) + " |" for r in rows]
            out.append("\n".join(lines) + "\n")
        elif kind in ("img", "figure"):
            src, alt = payload
            out.append(f"![{alt}]({src})\n" + (f"\n{alt}\n" if kind == "figure" else ""))
    return "\n".join(out)


def to_html(blocks) -> str:
    e = html.escape
    out = [
        "<!doctype html><html><head><meta charset='utf-8'><title>OSCAR evaluation</title><style>"
        "body{font-family:sans-serif;max-width:1200px;margin:2em auto;padding:0 1em}"
        "table{border-collapse:collapse;margin:1em 0}td,th{border:1px solid #ccc;padding:3px 8px;"
        "text-align:right}th{background:#f0f0f0}td:first-child{text-align:left}"
        "figure{margin:1em 0}img{max-width:100%}code{background:#f4f4f4}</style></head><body>"
    ]
    for kind, payload in blocks:
        if kind in ("h1", "h2"):
            out.append(f"<{kind}>{e(payload)}</{kind}>")
        elif kind == "p":
            out.append(f"<p>{_code(e(payload))}</p>")
        elif kind == "list":
            out.append("<ul>" + "".join(f"<li>{_code(e(x))}</li>" for x in payload) + "</ul>")
        elif kind == "table":
            head, rows = payload
            out.append(
                "<table><tr>"
                + "".join(f"<th>{e(h)}</th>" for h in head)
                + "</tr>"
                + "".join("<tr>" + "".join(f"<td>{e(c)}</td>" for c in r) + "</tr>" for r in rows)
                + "</table>"
            )
        elif kind == "img":
            src, alt = payload
            out.append(f"<p><img src='{e(src)}' alt='{e(alt)}'></p>")
        elif kind == "figure":
            src, cap = payload
            out.append(f"<figure><img src='{e(src)}'><figcaption>{e(cap)}</figcaption></figure>")
    out.append("</body></html>")
    return "\n".join(out)


def _code(text: str) -> str:
    parts = text.split("`")
    return "".join(f"<code>{p}</code>" if i % 2 else p for i, p in enumerate(parts))


def make_plots(doc: dict, ranks: list, plot_dir: Path) -> dict[str, str]:
    from pipeline.evaluate import plots as P

    plot_dir.mkdir(parents=True, exist_ok=True)
    made: dict[str, str] = {}

    def keep(key: str, path):
        if path is not None:
            made[key] = f"{plot_dir.name}/{Path(path).name}"

    sw = doc["sweeps"]
    mset = _set_of(doc)
    paper = mset == "paper"
    lines = P.PAPER_SWEEP_METRICS if paper else P.SWEEP_METRICS
    bars = P.PAPER_BAR_METRICS if paper else P.BAR_METRICS
    tag = f" (metric set {mset})"
    keep(
        "tau_sweep",
        P.sweep_plot(
            sw.get("tau", []),
            "threshold",
            plot_dir / "tau_sweep.png",
            "Stage-1 threshold tau" + tag,
            "tau",
            lines,
        ),
    )
    keep(
        "fallback_k_sweep",
        P.sweep_plot(
            sw.get("fallback_k", []),
            "fallback_k",
            plot_dir / "topk_sweep.png",
            "Fallback top-k" + tag,
            "k",
            lines,
        ),
    )
    for name in ("mode", "roi"):
        groups = {r["setting"][name]: r for r in sw.get(name, [])}
        keep(
            f"{name}_bars",
            P.bar_plot(groups, plot_dir / f"{name}.png", f"{name} ablation{tag}", bars)
            if len(groups) > 1
            else None,
        )
    if doc.get("prompt_styles"):
        keep(
            "styles_bars",
            P.bar_plot(doc["prompt_styles"], plot_dir / "prompt_styles.png", "prompt styles" + tag, bars),
        )
    keep("rank_hist", P.rank_histogram(ranks, plot_dir / "rank_hist.png", "expected model's rank (base)"))
    return made


def write_report(
    doc: dict,
    records,
    out_dir: Path,
    store_path: str,
    library=None,
    gallery_limit: int = 24,
    plots: bool = True,
) -> dict[str, Path]:
    """Write every report file into ``out_dir``; return their paths."""
    out_dir.mkdir(parents=True, exist_ok=True)
    paths = {"metrics": out_dir / "metrics.json", "per_query": out_dir / "per_query.jsonl"}
    with open(paths["per_query"], "w") as fh:
        for r in records:
            rk = r.ranked
            fh.write(
                json.dumps(
                    {
                        "query_id": r.query.query_id,
                        "prompt": r.query.prompt,
                        "label": r.query.label,
                        "expected": sorted(r.rel.instance),
                        "rank": r.metrics.get("rank"),
                        "top5": [
                            {"mesh_id": i, "name": n, "text_score": t, "image_score": s}
                            for i, n, t, s in list(
                                zip(rk.ids, rk.names, rk.text_scores, rk.image_scores, strict=True)
                            )[:5]
                        ],
                        "used_fallback": rk.used_fallback,
                        "n_stage1": rk.n_stage1,
                        "metrics": {k: v for k, v in r.metrics.items() if k != "rank"},
                    }
                )
                + "\n"
            )
    made = make_plots(doc, [r.metrics.get("rank") for r in records], out_dir / "plots") if plots else {}
    from pipeline.evaluate.gallery import write_gallery

    gallery = write_gallery(records, store_path, out_dir / "gallery", limit=gallery_limit, library=library)
    doc["plots"] = made
    doc["gallery"] = gallery
    paths["metrics"].write_text(json.dumps(_clean(doc), indent=2, default=_json_default))
    blocks = _sections(doc, made, gallery)
    paths["markdown"] = out_dir / "report.md"
    paths["markdown"].write_text(to_markdown(blocks))
    paths["html"] = out_dir / "report.html"
    paths["html"].write_text(to_html(blocks))
    return paths


def _clean(o):
    """NaN -> null (JSON has no NaN), recursively."""
    if isinstance(o, float) and math.isnan(o):
        return None
    if isinstance(o, dict):
        return {k: _clean(v) for k, v in o.items()}
    if isinstance(o, (list, tuple)):
        return [_clean(v) for v in o]
    return o


def _json_default(o):
    if isinstance(o, float) and math.isnan(o):
        return None
    if hasattr(o, "item"):
        return o.item()
    return str(o)
