"""SIGINT / SIGTERM keep finished work: at start-up, during rendering, between stages and during a commit,
the run commits what is finished, says how many meshes it kept, and the re-run does only the rest, so
that the final tables equal those of an uninterrupted run. Render workers print no tracebacks."""

from __future__ import annotations

import os
import shutil
import signal
import subprocess
import sys
import time

import pytest
from conftest import REPO, SAMPLE_LIBRARY
from onboard_helpers import assert_same_tables, onboard

from pipeline.mesh.settings import RenderConfig
from pipeline.onboard.interrupt import RunInterrupted
from pipeline.store import Store

NAMES = ["003_cracker_box", "005_tomato_soup_can", "006_mustard_bottle", "011_banana"]
CFG = {"render": RenderConfig(resolution=32), "batch_size": 2}


@pytest.fixture(scope="module")
def library(tmp_path_factory):
    lib = tmp_path_factory.mktemp("lib")
    for n in NAMES:
        shutil.copytree(SAMPLE_LIBRARY / n, lib / n)
    return lib


@pytest.fixture(scope="module")
def full(library, tmp_path_factory, offline_models):
    """The tables of an uninterrupted run."""
    store = tmp_path_factory.mktemp("full") / "store"
    onboard(library, store, offline_models, **CFG)
    return store


def _signal_on_call(monkeypatch, owner, name: str, signum: int, call: int = 1) -> None:
    """Send ``signum`` to this process when ``owner.name`` is called for the ``call``-th time (before it
    runs: the call itself still finishes, as a step in flight does)."""
    real = getattr(owner, name)
    calls = {"n": 0}

    def wrapped(*a, **kw):
        calls["n"] += 1
        if calls["n"] == call:
            os.kill(os.getpid(), signum)
        return real(*a, **kw)

    monkeypatch.setattr(owner, name, wrapped)


def _interrupted(library, store, models) -> RunInterrupted:
    before = signal.getsignal(signal.SIGINT)  # SIG_IGN where the test runner started in the background
    with pytest.raises(RunInterrupted) as exc:
        onboard(library, store, models, **CFG)
    runs = Store.open(store).read("runs").to_pylist()
    assert [r["status"] for r in runs] == ["interrupted"]
    assert signal.getsignal(signal.SIGINT) is before  # handlers restored
    return exc.value


def _resume_equals_full(library, store, models, full):
    summary = onboard(library, store, models, **CFG)
    assert summary.status == "ok"
    assert_same_tables(store, full)
    return summary


def test_at_start_up(tmp_path, library, full, offline_models, monkeypatch):
    from pipeline.onboard.engines.local import LocalEngine

    _signal_on_call(monkeypatch, LocalEngine, "_load_models", signal.SIGTERM)
    exc = _interrupted(library, tmp_path / "s", offline_models)
    assert (exc.kept, exc.left, exc.exit_code) == (0, 4, 143)
    assert "interrupted by SIGTERM: kept 0 meshes; 4 left to do" in str(exc)
    assert Store.open(tmp_path / "s").dataset("views") is None
    monkeypatch.undo()
    assert _resume_equals_full(library, tmp_path / "s", offline_models, full).rendered == 4


def test_during_rendering(tmp_path, library, full, offline_models, monkeypatch):
    from pipeline.onboard.stages.render import RenderStage

    # the 3rd mesh is being rendered: the first batch (2 meshes) is committed, the 3rd mesh's views are kept
    _signal_on_call(monkeypatch, RenderStage, "render_one", signal.SIGINT, call=3)
    exc = _interrupted(library, tmp_path / "s", offline_models)
    assert (exc.kept, exc.complete, exc.left, exc.exit_code) == (3, 2, 2, 130)
    assert "kept 3 meshes (2 complete, 1 with some stages left); 2 left to do" in str(exc)
    s = Store.open(tmp_path / "s")
    assert len(set(s.read("views").column("mesh_id").to_pylist())) == 3
    assert len(set(s.read("captions").column("mesh_id").to_pylist())) == 2
    monkeypatch.undo()
    summary = _resume_equals_full(library, tmp_path / "s", offline_models, full)
    assert (summary.rendered, summary.captioned) == (1, 2)  # only the rest
    # the summary line adds up: the mesh with stages left is named, not hidden between "added" and
    # "unchanged" (the mesh never started is added)
    assert (summary.added, summary.skipped, summary.resumed, summary.n_files) == (1, 2, 1, 4)
    assert "1 added, 0 removed, 2 unchanged, 1 with stages left, 0 failed" in summary.lines()[0]


def test_between_stages(tmp_path, library, full, offline_models, monkeypatch):
    from pipeline.onboard.stages.caption import CaptionStage

    # while the first batch is captioned: its captions finish and are kept, its embeddings wait
    _signal_on_call(monkeypatch, CaptionStage, "__call__", signal.SIGINT)
    exc = _interrupted(library, tmp_path / "s", offline_models)
    assert exc.complete == 0 and exc.kept >= 2
    s = Store.open(tmp_path / "s")
    assert len(set(s.read("captions").column("mesh_id").to_pylist())) == 2
    assert s.datasets("text_embeddings") == []
    monkeypatch.undo()
    summary = _resume_equals_full(library, tmp_path / "s", offline_models, full)
    assert summary.captioned == 2 and summary.rendered == 4 - exc.kept


def test_during_a_commit(tmp_path, library, full, offline_models, monkeypatch):
    real = Store.commit
    state = {"sent": False}

    def commit(self, tables, run_id):
        if "views" in tables and not state["sent"]:
            state["sent"] = True
            os.kill(os.getpid(), signal.SIGTERM)  # arrives while the batch is being written
        return real(self, tables, run_id)

    monkeypatch.setattr(Store, "commit", commit)
    exc = _interrupted(library, tmp_path / "s", offline_models)
    assert exc.complete == 2 and exc.left == 2  # the commit in flight finished: its batch is whole
    monkeypatch.undo()
    summary = _resume_equals_full(library, tmp_path / "s", offline_models, full)
    assert summary.rendered == 2


def _cli(library, store) -> list[str]:
    return [
        sys.executable,
        "-m",
        "pipeline.onboard",
        str(library),
        "--store",
        str(store),
        "--batch-size",
        "1",
        "--workers",
        "2",
        "--resolution",
        "32",
        "--no-progress",
    ]


ENV = {**os.environ, "PYTHONPATH": str(REPO)}


@pytest.fixture(scope="module")
def full_cli(library, tmp_path_factory):
    """An uninterrupted run of the command the next test interrupts."""
    store = tmp_path_factory.mktemp("full_cli") / "store"
    subprocess.run(_cli(library, store), check=True, env=ENV, capture_output=True, timeout=600)
    return store


@pytest.mark.parametrize("signum,group", [(signal.SIGINT, True), (signal.SIGTERM, False)])
def test_render_workers_stop_quietly(tmp_path, library, full_cli, signum, group):
    """Ctrl-C in a terminal reaches the whole process group (render workers too); ``kill PID`` the parent
    only. Either way: exit 128+signal, one line saying what was kept, no traceback; the re-run finishes."""
    env, store = ENV, tmp_path / "s"
    proc = subprocess.Popen(
        _cli(library, store),
        env=env,
        stdout=subprocess.PIPE,
        stderr=subprocess.PIPE,
        text=True,
        start_new_session=True,
    )
    deadline = time.time() + 300
    log = store / "views" / "_delta_log"
    while time.time() < deadline and proc.poll() is None:  # once the first mesh is committed
        if log.exists() and any(p.suffix == ".json" for p in log.iterdir()):
            break
        time.sleep(0.05)
    if group:
        os.killpg(proc.pid, signum)
    else:
        proc.send_signal(signum)
    out, err = proc.communicate(timeout=120)
    if proc.returncode == 0:
        pytest.skip("the run finished before the signal landed")  # a very fast machine
    assert proc.returncode == 128 + signum, err
    assert "Traceback" not in err and "KeyboardInterrupt" not in err, err
    last = err.strip().splitlines()[-1]
    assert last.startswith(f"error: interrupted by {signal.Signals(signum).name}: kept "), err
    subprocess.run(_cli(library, store), check=True, env=env, capture_output=True, timeout=600)
    assert_same_tables(store, full_cli)


def test_ray_engine_keeps_the_batches_that_arrived(tmp_path, library, full, monkeypatch):
    """The Ray engine commits each batch with every step done: a signal keeps what arrived, the driver
    stops waiting for the rest, and the re-run (here by the local engine) does only that."""
    ray = pytest.importorskip("ray")
    started = not ray.is_initialized()
    if started:
        ray.init(num_cpus=2, include_dashboard=False, logging_level="warning", log_to_driver=False)
    real = Store.commit
    state = {"sent": False}

    def commit(self, tables, run_id):
        if "views" in tables and not state["sent"]:
            state["sent"] = True
            os.kill(os.getpid(), signal.SIGINT)
        return real(self, tables, run_id)

    monkeypatch.setattr(Store, "commit", commit)
    try:
        with pytest.raises(RunInterrupted) as exc:
            onboard(library, tmp_path / "s", None, engine="ray", **{**CFG, "batch_size": 1})
    finally:
        if started:
            ray.shutdown()
    assert exc.value.complete >= 1 and exc.value.kept == exc.value.complete and exc.value.left >= 1
    assert [r["status"] for r in Store.open(tmp_path / "s").read("runs").to_pylist()] == ["interrupted"]
    monkeypatch.undo()
    _resume_equals_full(library, tmp_path / "s", None, full)


def test_a_signal_after_the_last_batch_leaves_a_finished_run(
    tmp_path, library, full, offline_models, monkeypatch
):
    """Nothing was left when the signal came (it landed in the last batch's commit): the run is ok."""
    real = Store.commit
    state = {"views": 0}

    def commit(self, tables, run_id):
        if "views" in tables:
            state["views"] += 1
            if state["views"] == 2:  # the second and last batch of 2 meshes
                os.kill(os.getpid(), signal.SIGTERM)
        return real(self, tables, run_id)

    monkeypatch.setattr(Store, "commit", commit)
    summary = onboard(library, tmp_path / "s", offline_models, **CFG)
    assert summary.status == "ok" and summary.rendered == 4
    assert [r["status"] for r in Store.open(tmp_path / "s").read("runs").to_pylist()] == ["ok"]
    monkeypatch.undo()
    assert_same_tables(tmp_path / "s", full)
