"""Sweeps over the cheap stages (with a scripted retriever) and the report files they produce."""

from __future__ import annotations

import json
from types import SimpleNamespace

import numpy as np
import pytest
from PIL import Image

from pipeline.evaluate.datasets import Query
from pipeline.evaluate.engine import Engine, Setting
from pipeline.evaluate.library import Library, MeshRef
from pipeline.evaluate.report import write_report
from pipeline.evaluate.sweep import MetricOptions, SweepPlan, evaluate

STANDARD = MetricOptions(metric_set="standard")

# stage-1 (text) and stage-2 (image) scores per query prompt; the expected model is named after the prompt
TEXT = {"the a": {"A": 0.8, "B": 0.5, "C": 0.2}, "the b": {"A": 0.3, "B": 0.7, "C": 0.6}}
IMAGE = {"the a": {"A": 0.6, "B": 0.9, "C": 0.1}, "the b": {"A": 0.2, "B": 0.8, "C": 0.4}}


class ScriptedRetriever:
    """Mimics pipeline.query.Retriever's contract with fixed scores; counts the expensive calls."""

    mesh_ids = ["A", "B", "C"]

    def __init__(self):
        self.embeds = 0

    def make_roi(self, image, prompt, box=None, mask=None, roi_mode="segm"):
        assert (mask is not None) == (roi_mode == "segm")
        image = Image.open(image).convert("RGB")
        return SimpleNamespace(image=image.crop(tuple(int(v) for v in box)) if box else image, mode=roi_mode)

    def embed(self, roi, prompt):
        self.embeds += 1
        return (prompt, roi.mode)

    def rank(
        self,
        emb,
        mode="two-stage",
        threshold=None,
        fallback_k=10,
        top=5,
        fallback_unit="captions",
        views=False,
    ):
        prompt, roi = emb
        text, image = dict(TEXT[prompt]), dict(IMAGE[prompt])
        if roi == "bbox":  # background clutter in the box hurts the expected model's image score
            expected = prompt[-1].upper()
            image[expected] -= 0.5
        tau = 0.55 if threshold is None else threshold
        used_fallback = False
        if mode == "text-only":
            order = sorted(text, key=lambda m: -text[m])
        elif mode == "image-only":
            order = sorted(image, key=lambda m: -image[m])
        else:
            stage1 = [m for m in text if text[m] >= tau]
            if not stage1:
                used_fallback = True
                stage1 = sorted(text, key=lambda m: -text[m])[:fallback_k]
            order = sorted(stage1, key=lambda m: -image[m])
        cands = [
            SimpleNamespace(
                rank=i + 1,
                mesh_id=m,
                name=f"mesh {m}",
                source_path=f"{m}.obj",
                text_score=text[m],
                image_score=image[m],
                best_view=0,
            )
            for i, m in enumerate(order[:top])
        ]
        view_ranking = None
        if views:  # two views per mesh: the best at the mesh's image score, the other 0.3 lower
            items = [(image[m] - d, self.mesh_ids.index(m)) for m in order for d in (0.0, 0.3)]
            items.sort(key=lambda it: (-it[0], it[1]))
            view_ranking = SimpleNamespace(
                mesh_idx=np.array([i for _, i in items]),
                view_index=np.zeros(len(items), np.int16),
                scores=np.array([s for s, _ in items]),
                tiebreak=None,
            )
        return SimpleNamespace(
            candidates=cands,
            used_fallback=used_fallback,
            decided_by=mode,
            n_stage1=len(order),
            timings={},
            view_ranking=view_ranking,
        )


@pytest.fixture
def setup(tmp_path):
    img = tmp_path / "img.png"
    Image.fromarray(np.full((40, 60, 3), 128, np.uint8)).save(img)
    mask = tmp_path / "mask.png"
    Image.fromarray(np.pad(np.full((10, 10), 255, np.uint8), 10)).save(mask)
    queries = [
        Query("qa", str(img), "the a", ["A.obj"], box=(10, 10, 20, 20), mask=str(mask), label="x"),
        Query("qb", str(img), "the b", ["B"], box=(10, 10, 20, 20), mask=str(mask), label="x"),
        Query("qz", str(img), "the z", ["Z"]),  # names no library mesh
    ]
    lib = Library(
        [MeshRef(m, f"{m}.obj", "/lib", f"mesh {m}", "obj") for m in "ABC"],
        class_map={"A": "x", "B": "x", "C": "y"},
    )
    return queries, lib, ScriptedRetriever()


def _top1(run, **change):
    from dataclasses import replace

    return run.results[replace(run.plan.base, **change)].summary()["instance"]["top1"]


def test_each_setting_is_scored_from_one_embedding_per_roi(setup):
    queries, lib, retriever = setup
    plan = SweepPlan(base=Setting(threshold=0.55), taus=(0.4, 0.55, 0.9), top_ks=(1, 10))
    run = evaluate(Engine(retriever, "unused"), queries, lib, plan, STANDARD)
    assert run.failed == []
    assert retriever.embeds == 2 * 2  # two resolvable queries x two ROI variants
    assert run.unresolved == ["qz"]
    assert _top1(run) == 1.0
    assert _top1(run, threshold=0.4) == 0.5  # B passes for "the a" and wins stage 2
    assert _top1(run, threshold=0.9) == 0.5  # nothing passes: top-10 fallback, ranked by image
    assert run.results[Setting(threshold=0.9)].summary()["fallback_rate"] == 1.0
    assert _top1(run, fallback_k=1) == 1.0  # the k sweep runs at the base tau: no fallback, no change
    assert _top1(run, mode="text-only") == 1.0
    assert _top1(run, mode="image-only") == 0.5
    assert _top1(run, roi="bbox") == 0.5
    # class level: A and B share class x, so "the a" ranked [B, A] at tau 0.4 is a class-level hit
    cls = run.results[Setting(threshold=0.4)].summary()["class"]
    # "the b" ranks [B, C] (A fails stage 1): one of its two class-x models in the top 2 -> FT 0.5
    assert cls["NN"] == 1.0 and cls["FT"] == pytest.approx((1.0 + 0.5) / 2)
    # when nothing passes tau, the fallback k decides: top-1 by text is right for both queries
    never = evaluate(
        Engine(retriever, "unused"), queries, lib, SweepPlan(Setting(threshold=0.9), top_ks=(1, 10)), STANDARD
    )
    assert _top1(never, fallback_k=1) == 1.0 and _top1(never, fallback_k=10) == 0.5
    from pipeline.evaluate.sweep import group_metrics

    by_prompt = group_metrics(run.records, "prompt", "standard")
    assert by_prompt["the a"]["n"] == 1 and by_prompt["the a"]["top1"] == 1.0
    assert group_metrics(run.records, "missing") == {}
    summary = run.summary()
    assert [r["setting"]["threshold"] for r in summary["sweeps"]["tau"]] == [0.4, 0.55, 0.9]
    assert [r["setting"]["mode"] for r in summary["sweeps"]["mode"]] == [
        "two-stage",
        "text-only",
        "image-only",
    ]


def test_paper_set_ranks_views(setup):
    queries, lib, retriever = setup
    plan = SweepPlan(base=Setting(threshold=0.4))
    run = evaluate(Engine(retriever, "unused"), queries, lib, plan, sweeps=False)  # default: paper
    s = run.results[plan.base].summary()
    assert s["metric_set"] == "paper" and "top1" not in s["instance"]
    # "the a" at tau 0.4: meshes [B 0.9, A 0.6]; views B .9, A .6, B .6, A .3 (B's .6 ties A's .6;
    # pessimistic ties put the relevant one last): relevant A at view ranks 3 and 4
    #   AP@1 = 0, AP@3 = mean(1/3) = 1/3, AP@5 = mean(1/3, 2/4) = 5/12
    # "the b": meshes [B .8, C .4] (A fails stage 1); views B .8, B .5, C .4, C .1: B at ranks 1, 2
    #   AP@k = 1 for every k (the hits normaliser: precision 1 at both hits)
    inst = s["instance"]
    assert inst["mAP@1"] == pytest.approx(0.5)
    assert inst["mAP@3"] == pytest.approx((1 / 3 + 1) / 2)
    assert inst["mAP@5"] == pytest.approx((5 / 12 + 1) / 2)
    # MI3DOR part over the meshes: "the a" [B, A] -> NN 0, FT 0, ST 1, AP 1/2; "the b" [B, C] -> all perfect
    assert inst["NN"] == pytest.approx(50.0)  # in %, as the reference reports it
    assert inst["FT"] == pytest.approx(0.5) and inst["ST"] == pytest.approx(1.0)
    assert inst["AP"] == pytest.approx(0.75) and inst["n_mi3dor"] == 2
    # NMRR "the a": kappa 1, K = min(2, 2) = 2, rank 2 -> AVR 2 -> (2 - 1) / (2 - 1) = 1; "the b": 0
    assert inst["ANMRR"] == pytest.approx(0.5)
    # class x = {A, B}: "the b" ranks [B, C]: A is not in the ranking, so kappa = 1 there
    cls = s["class"]
    assert cls["FT"] == pytest.approx(1.0) and cls["NN"] == pytest.approx(100.0)


def test_report_files(setup, tmp_path):
    queries, lib, retriever = setup
    plan = SweepPlan(base=Setting(threshold=0.4), taus=(0.4, 0.9), top_ks=(1, 10))
    run = evaluate(Engine(retriever, "unused"), queries, lib, plan, STANDARD)
    doc = {
        "config": {
            "command": "test",
            "store": "unused",
            "profile": "offline",
            "metric_set": "standard",
            "queries": "inline",
            "ties": "pessimistic",
            "map_normaliser": "min",
            "note": "scripted",
        },
        "n_queries": 3,
        "n_evaluated": len(run.records),
        "unresolved": run.unresolved,
        "failed": run.failed,
        "library": {"n_meshes": 3, "n_classes": 2},
        **run.summary(),
        "prompt_styles": None,
    }
    out = tmp_path / "report"
    paths = write_report(doc, run.records, out, "unused", lib)
    metrics = json.loads(paths["metrics"].read_text())
    assert metrics["base"]["instance"]["top1"] == 0.5
    assert metrics["base"]["instance"]["mAP@3"] == pytest.approx((0.5 + 1.0) / 2)
    assert len(metrics["gallery"]) == 1 and metrics["gallery"][0]["query_id"] == "qa"
    assert (out / metrics["gallery"][0]["file"]).is_file()
    for plot in ("tau_sweep", "fallback_k_sweep", "mode_bars", "roi_bars", "rank_hist"):
        assert (out / metrics["plots"][plot]).is_file(), plot
    per_query = [json.loads(line) for line in paths["per_query"].read_text().splitlines()]
    assert [q["rank"] for q in per_query] == [2, 1]
    md, html = paths["markdown"].read_text(), paths["html"].read_text()
    assert (
        "Threshold sweep (tau) (metric set standard)" in md
        and "| instance |" in md
        and "gallery/qa.png" in md
    )
    assert "Metric set `standard`" in md and "metric set standard" in html
    assert "<table>" in html and "gallery/qa.png" in html
