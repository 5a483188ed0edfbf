"""``report.md`` of ``python -m pipeline.evaluate openset``: the out-of-fold rates and the rejection curve."""

from __future__ import annotations

from pathlib import Path


def _pct(d: dict) -> str:
    if not d or d.get("rate") is None:
        return "-"
    return f"{100 * d['rate']:.1f}% [{100 * d['lo']:.0f}, {100 * d['hi']:.0f}] (n={d['n']})"


def markdown(summary: dict) -> str:
    """Markdown tables: per variant the out-of-fold rates; per slice and the curve for the default one."""
    fit = summary["fit"]
    default = summary["default_variant"]
    lines = [
        "# Open-set acceptance (out of fold, leave one object out)",
        "",
        f"`{fit['command']}`",
        "",
        f"{fit['meshes_left_out']} meshes left out ({fit['absent']}); operating point: the highest "
        f"threshold accepting {100 * fit['target']:.0f}% of the training folds' correct answers. "
        "Rates with 95% bootstrap intervals over objects.",
        "",
        "| variant | features | threshold | absent rejected | correct accepted | wrong rejected | Brier | ECE |",
        "|---|---|---|---|---|---|---|---|",
    ]
    for name, v in summary["variants"].items():
        o, ce = v["out_of_fold"], v["calibration_error"]
        mark = " (default)" if name == default else ""
        lines.append(
            f"| {name}{mark} | {', '.join(v['features'])} | {v['threshold']:.3f} | {_pct(o['absent_rejected'])} "
            f"| {_pct(o['correct_accepted'])} | {_pct(o['wrong_rejected'])} | {ce['brier']:.3f} | {ce['ece']:.3f} |"
        )
    d = summary["variants"][default]
    lines += ["", f"## {default}: by query set and ROI", ""]
    lines += ["| slice | absent rejected | correct accepted | wrong rejected |", "|---|---|---|---|"]
    for name, r in d["slices"].items():
        lines.append(
            f"| {name} | {_pct(r['absent_rejected'])} | {_pct(r['correct_accepted'])} | {_pct(r['wrong_rejected'])} |"
        )
    lines += ["", f"## {default}: rejection curve (one threshold on the out-of-fold confidences)", ""]
    lines += ["| threshold | absent rejected | correct accepted | wrong rejected |", "|---|---|---|---|"]
    for row in d["curve"]:
        lines.append(
            f"| {row['threshold']:.2f} | {_pct(row['absent_rejected'])} | {_pct(row['correct_accepted'])} "
            f"| {_pct(row['wrong_rejected'])} |"
        )
    if summary.get("errors"):
        lines += ["", f"{len(summary['errors'])} queries failed (see openset.json)."]
    return "\n".join(lines) + "\n"


def write_markdown(summary: dict, path: str | Path) -> Path:
    path = Path(path)
    path.write_text(markdown(summary), encoding="utf-8")
    return path
