"""Matplotlib figures of a report: threshold and top-k sweeps (like the paper's figures), mode / ROI /
prompt-style bars and the distribution of the expected model's rank."""

from __future__ import annotations

from pathlib import Path

SWEEP_METRICS = ("mAP@1", "mAP@5", "top5", "FT")
BAR_METRICS = ("mAP@1", "mAP@5", "top5", "NN", "FT", "DCG")
#: the paper set's (NN is a percentage there, so it stays off these 0..1 axes)
PAPER_SWEEP_METRICS = ("mAP@1", "mAP@5", "FT", "nDCG")
PAPER_BAR_METRICS = ("mAP@1", "mAP@5", "mAP@10", "FT", "ST", "nDCG")


def _plt():
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    return plt


def _series(rows: list[dict], level: str, metric: str) -> list[float]:
    return [(r.get(level) or {}).get(metric, float("nan")) for r in rows]


def sweep_plot(
    rows: list[dict], knob: str, path: Path, title: str, xlabel: str, metrics=SWEEP_METRICS
) -> Path | None:
    """Metrics (instance level; class level dashed) against one knob, with stage-1 size on a second axis."""
    if len(rows) < 2:
        return None
    plt = _plt()
    xs = [r["setting"][knob] for r in rows]
    fig, ax = plt.subplots(figsize=(7, 4.2))
    for metric in metrics:
        (line,) = ax.plot(xs, _series(rows, "instance", metric), marker="o", label=f"{metric} (instance)")
        if any(r.get("class") for r in rows):
            ax.plot(
                xs, _series(rows, "class", metric), ls="--", color=line.get_color(), label=f"{metric} (class)"
            )
    ax.set_ylim(0, 1.02)
    ax.set_xlabel(xlabel)
    ax.set_ylabel("score")
    ax.grid(alpha=0.3)
    stage1 = [r.get("mean_stage1") for r in rows]
    if any(v is not None for v in stage1):
        ax2 = ax.twinx()
        ax2.plot(xs, [v if v is not None else float("nan") for v in stage1], color="gray", ls=":", marker="s")
        ax2.set_ylabel("mean stage-1 candidates (gray, dotted)")
    ax.legend(fontsize=7, loc="lower left", ncol=2)
    ax.set_title(title)
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)
    return path


def bar_plot(groups: dict[str, dict], path: Path, title: str, metrics=BAR_METRICS) -> Path | None:
    """Grouped bars: one group per variant (mode, ROI, prompt style), one bar per headline metric."""
    if not groups:
        return None
    plt = _plt()
    names = list(groups)
    width = 0.8 / len(names)
    fig, ax = plt.subplots(figsize=(7.5, 4))
    for i, name in enumerate(names):
        vals = [(groups[name].get("instance") or {}).get(m, float("nan")) for m in metrics]
        xs = [j + i * width for j in range(len(metrics))]
        ax.bar(xs, vals, width=width, label=name)
    ax.set_xticks([j + 0.4 - width / 2 for j in range(len(metrics))], metrics)
    ax.set_ylim(0, 1.05)
    ax.set_ylabel("score (instance level)")
    ax.legend(fontsize=8)
    ax.set_title(title)
    ax.grid(axis="y", alpha=0.3)
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)
    return path


def rank_histogram(ranks: list[int | None], path: Path, title: str) -> Path | None:
    """How often the expected model came at rank 1, 2, ... 10, later, or was not returned."""
    if not ranks:
        return None
    plt = _plt()
    fig = rank_histogram_figure(ranks, title)
    fig.savefig(path, dpi=110)
    plt.close(fig)
    return path


def rank_histogram_figure(ranks: list[int | None], title: str):
    """The figure of :func:`rank_histogram` (its tick labels never overlap: the long ones wrap)."""
    plt = _plt()
    labels = [str(i) for i in range(1, 11)] + [">10", "not\nreturned"]
    counts = [0] * len(labels)
    for r in ranks:
        counts[-1 if r is None else (r - 1 if r <= 10 else 10)] += 1
    fig, ax = plt.subplots(figsize=(7.5, 3.8))
    ax.bar(range(len(labels)), counts, color="#4c72b0")
    ax.set_xticks(range(len(labels)), labels, fontsize=9)
    ax.set_xlabel("rank of the expected model")
    ax.set_ylabel("queries")
    ax.set_title(title)
    fig.tight_layout()
    return fig
