"""End to end: onboard a tiny library, generate synthetic queries, evaluate with the real offline retriever."""

from __future__ import annotations

import json

import pytest
from test_eval_synth import make_toy_library

from pipeline.evaluate.cli import main
from pipeline.onboard.config import OnboardConfig
from pipeline.onboard.run import run_onboarding


@pytest.fixture(scope="module")
def tiny_store(tmp_path_factory, offline_models):
    root = tmp_path_factory.mktemp("e2e")
    lib = make_toy_library(root / "lib")
    store = root / "store"
    run_onboarding(str(lib), str(store), OnboardConfig(workers=0), progress=False, models=offline_models)
    return lib, store


def test_synthetic_evaluation_report(tiny_store, tmp_path, capsys):
    lib, store = tiny_store
    queries = tmp_path / "queries"
    assert (
        main(
            [
                "synth",
                "--store",
                str(store),
                "--out",
                str(queries),
                "--per-mesh",
                "2",
                "--size",
                "200x150",
                "--backgrounds",
                "solid,gradient,noise",
                "--no-progress",
            ]
        )
        == 0
    )
    out = tmp_path / "report"
    rc = main(
        [
            "--store",
            str(store),
            "--queries",
            str(queries / "queries.jsonl"),
            "--out",
            str(out),
            "--taus",
            "0.3,0.6,0.9",
            "--top-ks",
            "1,5",
            "--style-store",
            f"attributes={store}",
            "--onboard-styles",
            "blind",
            "--library",
            str(lib),
            "--gallery",
            "3",
            "--no-progress",
        ]
    )
    assert rc == 0, capsys.readouterr().err
    doc = json.loads((out / "metrics.json").read_text())
    assert doc["n_queries"] == doc["n_evaluated"] == 6
    assert doc["unresolved"] == [] and doc["failed"] == []
    assert doc["config"]["metric_set"] == "paper" and doc["base"]["metric_set"] == "paper"
    base = doc["base"]["instance"]
    assert base["n"] == 6 and base["n_mi3dor"] == 6  # three models: the expected one is always ranked
    assert 0.0 <= base["mAP@1"] <= 1.0 and 0.0 <= base["NN"] <= 100.0 and "top5" not in base
    assert doc["base"]["class"]["n"] == 6  # synthetic queries carry class labels
    assert [r["setting"]["threshold"] for r in doc["sweeps"]["tau"]] == [0.3, 0.6, 0.9]
    assert {r["setting"]["mode"] for r in doc["sweeps"]["mode"]} == {"two-stage", "text-only", "image-only"}
    assert {r["setting"]["roi"] for r in doc["sweeps"]["roi"]} == {"segm", "bbox"}
    assert doc["prompt_styles"]["attributes"]["instance"] == base
    # the blind-style store starts as a copy (renders reused) and is re-captioned; the offline captioner
    # ignores the prompt, so its captions and therefore its numbers equal the attributes store's
    blind = doc["prompt_styles"]["blind"]
    assert blind["store"] == str(out / "stores" / "blind") and blind["instance"] == base
    assert doc["timings"]["roi_embed_segm_ms"]["n"] == 6
    assert sum(g["n"] for g in doc["groups"]["background"].values()) == 6
    for name in ("report.md", "report.html", "per_query.jsonl", "plots/tau_sweep.png"):
        assert (out / name).is_file(), name
    for g in doc["gallery"]:
        assert (out / g["file"]).is_file()
    printed = capsys.readouterr().out
    assert "instance: mAP@1" in printed and "metric set: paper" in printed
    assert "Metric set `paper`" in (out / "report.md").read_text()

    # the textbook set and the mesh-counted fallback on the same queries, base setting only
    std = tmp_path / "standard"
    args = ["--store", str(store), "--queries", str(queries / "queries.jsonl"), "--out", str(std)]
    rc = main(args + ["--metrics", "standard", "--fallback-unit", "meshes", "--no-sweeps", "--no-progress"])
    assert rc == 0, capsys.readouterr().err
    sdoc = json.loads((std / "metrics.json").read_text())
    assert sdoc["config"]["metric_set"] == "standard" and sdoc["base"]["setting"]["fallback_unit"] == "meshes"
    assert sdoc["base"]["instance"]["top5"] == 1.0
    assert "Metric set `standard`" in (std / "report.md").read_text()


def test_missing_store_is_one_line(tmp_path, capsys):
    rc = main(["--store", str(tmp_path / "nope"), "--synthetic", "1", "--out", str(tmp_path / "r")])
    err = capsys.readouterr().err
    assert rc == 2 and err.startswith("error: ") and err.count("\n") == 1
    assert main(["--store", str(tmp_path), "--out", str(tmp_path / "r")]) == 2  # no query source


def test_synth_avoids_the_views_its_store_was_rendered_with(tiny_store):
    from pipeline.evaluate.synth_cli import store_render_config
    from pipeline.mesh.settings import RenderConfig

    _, store = tiny_store
    cfg = store_render_config(str(store))
    assert cfg == OnboardConfig(workers=0).render  # the rings, resolution, ... the store recorded
    assert cfg.elevations_deg == (-15.0, 15.0, 45.0) and cfg != RenderConfig()
