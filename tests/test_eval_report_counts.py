"""The evaluation report: each count stands next to the metrics it counts, and the rank histogram's
labels do not overlap."""

from __future__ import annotations

import pytest

from pipeline.evaluate.report import GROUP_COLUMNS, headline_table


def test_paper_headline_shows_the_n_each_metric_is_over():
    base = {
        "instance": {"n": 21, "n_mi3dor": 18, "mAP@1": 0.5, "NN": 61.1, "FT": 0.4, "ANMRR": 0.3},
        "class": {"n": 21, "n_mi3dor": 18, "mAP@1": 0.5, "NN": 61.1, "FT": 0.4, "ANMRR": 0.3},
    }
    header, rows = headline_table(base, "paper")
    i_map, i_nn = header.index("n (mAP)"), header.index("n (NN..ANMRR)")
    assert header[i_map + 1].startswith("mAP@") and header[i_nn + 1] == "NN"
    assert all(h.startswith("mAP@") for h in header[i_map + 1 : i_nn])
    assert rows[0][i_map] == "21" and rows[0][i_nn] == "18"
    assert "n_mi3dor" in GROUP_COLUMNS["paper"]
    header, rows = headline_table(base, "standard")  # one n: every standard metric counts every query
    assert header[:2] == ["level", "n"] and rows[0][1] == "21"


def test_rank_histogram_labels_do_not_overlap():
    pytest.importorskip("matplotlib")
    from pipeline.evaluate.plots import _plt, rank_histogram_figure

    plt = _plt()
    fig = rank_histogram_figure([1, 1, 2, 5, 11, None, None], "expected model's rank")
    fig.canvas.draw()
    renderer = fig.canvas.get_renderer()
    labels = fig.axes[0].get_xticklabels()
    assert [t.get_text() for t in labels][-2:] == [">10", "not\nreturned"]
    boxes = sorted((b.x0, b.x1) for b in (t.get_window_extent(renderer) for t in labels))
    assert all(a[1] < b[0] for a, b in zip(boxes, boxes[1:], strict=False))
    plt.close(fig)
