"""Only successful runs decide what is current: a failed, interrupted or refused run is recorded with its
status, and the views and audits follow the latest run with status ok, as queries do."""

from __future__ import annotations

import json
import shutil

import pytest
from conftest import SAMPLE_LIBRARY
from onboard_helpers import onboard
from tiny_store import FINGERPRINTS, RENDER, TinyStore

from pipeline.db import connect
from pipeline.mesh.settings import RenderConfig
from pipeline.sql.cli import main as sql_main
from pipeline.sql.session import run_audit
from pipeline.store import Store

LATER = "20250601T000000000000Z-bbbbbb"
PAPER = {"render": "r2", "caption": "c2", "embed_text": "t2", "embed_image:view_encoder": "i2"}


def rows(store, sql: str) -> list[tuple]:
    return connect(store).execute(sql).fetchall()


def audit(store, name: str) -> list[dict]:
    columns, found = run_audit(connect(store), name)
    return [dict(zip(columns, r, strict=True)) for r in found]


@pytest.mark.parametrize("status", ["failed", "interrupted", "refused"])
def test_a_run_that_did_not_finish_is_not_current(tmp_path, status, capsys):
    t = TinyStore(tmp_path / "s")
    t.complete("m1", "A red box-shaped object")
    t.complete("m2", "A blue bottle standing upright")
    t.run()
    t.run(run_id=LATER, fingerprints=PAPER, status=status)  # e.g. --profile paper failing at model load
    store = t.commit()
    assert rows(store, "SELECT run_id FROM current_config") == [(t.run_id,)]
    assert rows(store, "SELECT count(*) FROM captions") == [(4,)]
    assert {r[0] for r in rows(store, "SELECT fingerprint FROM current_fingerprints")} == set(
        FINGERPRINTS.values()
    )
    assert audit(store, "missing_outputs") == []
    assert rows(store, "SELECT status FROM runs ORDER BY run_id DESC") == [(status,), ("ok",)]
    capsys.readouterr()
    assert sql_main([str(tmp_path / "s"), "--audit", "all", "--check"]) == 0, capsys.readouterr().out


def test_a_later_successful_run_is_current(tmp_path):
    t = TinyStore(tmp_path / "s")
    t.complete("m1")
    t.run()
    t.run(run_id=LATER, fingerprints=PAPER)
    store = t.commit()
    assert rows(store, "SELECT run_id FROM current_config") == [(LATER,)]
    assert rows(store, "SELECT count(*) FROM captions") == [(0,)]
    assert {r["stage"] for r in audit(store, "missing_outputs")} == set(PAPER)


def test_no_successful_run_means_nothing_is_current(tmp_path):
    t = TinyStore(tmp_path / "s")
    t.complete("m1")
    t.run(status="failed")
    store = t.commit()
    assert rows(store, "SELECT count(*) FROM current_config") == [(0,)]
    assert rows(store, "SELECT count(*) FROM captions") == [(0,)]


def test_missing_outputs_counts_local_features(tmp_path):
    t = TinyStore(tmp_path / "s")
    for m in ("with", "without"):
        t.complete(m)
    t.features("with")
    t.run(fingerprints={**FINGERPRINTS, "features": "f1"})
    store = t.commit()
    assert rows(store, "SELECT table_name FROM current_fingerprints WHERE stage = 'features'") == [
        ("view_features",)
    ]
    assert [(r["mesh_id"], r["stage"], r["table_name"]) for r in audit(store, "missing_outputs")] == [
        ("without", "features", "view_features")
    ]


def test_missing_outputs_counts_the_extra_background_view(tmp_path):
    """With --extra-bg-view the render config makes one more view: rendered, embedded, never captioned."""
    t = TinyStore(tmp_path / "s")
    t.mesh("whole")
    t.views("whole", indices=(0, 1, 2))
    t.captions("whole", ["A red box", "A red box"])
    t.embeddings("text_embeddings", "whole")
    t.embeddings("image_embeddings", "whole", indices=(0, 1, 2))
    t.complete("no_bg")  # 2 views only: its background view is missing
    t.run(render={**RENDER, "extra_bg_view": True})
    store = t.commit()
    assert rows(store, "SELECT expected_views, expected_rendered_views FROM current_config") == [(2, 3)]
    got = {
        (r["mesh_id"], r["stage"]): (r["n_rows"], r["expected_rows"]) for r in audit(store, "missing_outputs")
    }
    assert got == {("no_bg", "render"): (2, 3), ("no_bg", "embed_image:view_encoder"): (2, 3)}


def test_a_failed_paper_run_changes_no_view_or_audit(tmp_path, offline_models):
    """The issue's case end to end: an offline store, then ``--profile paper`` failing at model load
    (no weights offline)."""
    pytest.importorskip("transformers")
    from pipeline.models.registry import ModelLoadError
    from pipeline.query.library import latest_onboarding

    lib = tmp_path / "lib"
    shutil.copytree(SAMPLE_LIBRARY / "011_banana", lib / "banana")
    store_path = tmp_path / "store"
    onboard(lib, store_path, offline_models, render=RenderConfig(resolution=32))
    before = Store.open(store_path)
    views = ("current_config", "current_fingerprints", "captions", "views", "text_embeddings", "errors_open")
    snapshot = {
        v: rows(
            before,
            f"SELECT * EXCLUDE (config) FROM {v}" if v == "current_config" else f"SELECT count(*) FROM {v}",
        )
        for v in views
    }  # noqa: S608
    audits = {n: audit(before, n) for n in ("missing_outputs", "stale_rows", "errors_by_stage")}
    ok_run = latest_onboarding(before).run_id

    with pytest.raises(ModelLoadError):
        onboard(lib, store_path, profile="paper", model_overrides={"captioner": str(tmp_path / "no-weights")})
    after = Store.open(store_path)
    runs = sorted(after.read("runs").to_pylist(), key=lambda r: r["run_id"])
    assert [r["status"] for r in runs] == ["ok", "failed"]
    assert json.loads(runs[-1]["config_json"])["profile"] == "paper"
    assert latest_onboarding(after).run_id == ok_run
    assert {
        v: rows(
            after,
            f"SELECT * EXCLUDE (config) FROM {v}" if v == "current_config" else f"SELECT count(*) FROM {v}",
        )
        for v in views
    } == snapshot  # noqa: S608
    assert {n: audit(after, n) for n in audits} == audits
    assert audits["missing_outputs"] == []
