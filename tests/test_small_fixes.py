"""Small things a platform team trips on: readable ``fsck --runs``, a lock that names its holder, SQL
output piped into ``head``, no Ray core-worker line on the console of a normal ``--engine ray`` run."""

from __future__ import annotations

import os
import re
import subprocess
import sys

import pytest
from conftest import REPO
from tiny_store import TinyStore

from pipeline.store import Store, StoreError

LATER = "20250601T000000000000Z-bbbbbb"


def test_fsck_runs_has_a_header_and_readable_times(tmp_path, capsys):
    from pipeline.fsck import main

    t = TinyStore(tmp_path / "s")
    t.complete("m")
    t.run()
    t.run(run_id=LATER, status="failed")
    t.commit()
    assert main([str(tmp_path / "s"), "--runs"]) == 0
    lines = capsys.readouterr().out.splitlines()
    start = next(i for i, line in enumerate(lines) if line.lstrip().startswith("version"))
    assert lines[start].split() == ["version", "recorded", "at", "(UTC)", "run_id", "status"]
    body = [line.split() for line in lines[start + 1 : start + 3]]
    assert [(b[0], b[3], b[4]) for b in body] == [("0", t.run_id, "ok"), ("1", LATER, "failed")]
    for b in body:
        assert re.fullmatch(r"\d{4}-\d\d-\d\d", b[1]) and re.fullmatch(r"\d\d:\d\d:\d\d\.\d{3}", b[2])


def test_a_held_lock_names_its_process(tmp_path):
    import socket

    holder = subprocess.Popen(
        [
            sys.executable,
            "-c",
            "import sys, time; from pipeline.store import Store; s = Store.open(sys.argv[1], create=True); "
            "print('held', flush=True); time.sleep(60)",
            str(tmp_path / "st"),
        ],
        env={**os.environ, "PYTHONPATH": str(REPO)},
        stdout=subprocess.PIPE,
        text=True,
    )
    try:
        assert holder.stdout.readline().strip() == "held"
        with pytest.raises(StoreError) as exc:
            Store.open(tmp_path / "st", writable=True)
        msg = str(exc.value)
        assert "locked by another writer" in msg and "\n" not in msg
        assert f"pid {holder.pid} on {socket.gethostname()}" in msg
        assert (
            "python" in msg and "time.sleep(60)" in msg and re.search(r"since \d{4}-\d\d-\d\d \d\d:\d\d", msg)
        )
    finally:
        holder.kill()
        holder.wait()
    Store.open(tmp_path / "st", writable=True).close()  # the holder is gone: the lock is free


def test_sql_output_into_head_exits_quietly(tmp_path):
    t = TinyStore(tmp_path / "s")
    t.complete("m")
    t.run()
    t.commit()
    cmd = [sys.executable, "-m", "pipeline.sql", str(tmp_path / "s"), "-c", "SELECT * FROM range(200000)"]
    proc = subprocess.Popen(
        cmd, env={**os.environ, "PYTHONPATH": str(REPO)}, stdout=subprocess.PIPE, stderr=subprocess.PIPE
    )
    proc.stdout.readline()  # what `head -1` reads, then it goes away
    proc.stdout.close()
    err = proc.stderr.read().decode()
    assert proc.wait(timeout=60) == 0
    assert err == ""


def test_ray_driver_core_worker_connects_quietly(monkeypatch, capfd):
    """Ray's C++ core worker of the driver reads its log threshold when ``ray.init`` connects; at its
    default it copies an ERROR line per actor start to the console ("... has constructor arguments in the
    object store and max_restarts > 0", on a normal run). ``--engine ray`` connects with the threshold at
    FATAL, holds what the connect itself prints, and leaves the environment as it was. (No Ray is
    started: the connect is a stand-in; a failed connect still shows its output.)"""
    ray = pytest.importorskip("ray")
    import ray._private.worker as ray_worker

    from pipeline.onboard.engines import ray as engine
    from pipeline.onboard.engines.ray_cluster import CORE_LOG_LEVEL
    from pipeline.onboard.engines.ray_options import RayOptions

    seen: dict = {}

    def connect(*args, **kwargs):
        seen["level"] = os.environ.get(CORE_LOG_LEVEL)
        os.write(2, b"core_worker.cc: the log threshold is read now\n")
        if seen.get("fail"):
            raise ConnectionError("no GCS")

    def init(**kwargs):
        seen["kwargs"] = kwargs
        ray_worker.connect()  # what ray.init does once the local instance's processes are up

    monkeypatch.setattr(ray_worker, "connect", connect)
    monkeypatch.setattr(ray, "is_initialized", lambda: False)
    monkeypatch.setattr(ray, "init", init)
    monkeypatch.setenv(CORE_LOG_LEVEL, "debug")
    capfd.readouterr()
    assert engine._start_ray(RayOptions()) is True
    assert seen["level"] == "fatal" and seen["kwargs"]["address"] == "local"
    assert os.environ[CORE_LOG_LEVEL] == "debug" and ray_worker.connect is connect
    assert capfd.readouterr().err == ""

    seen["fail"] = True
    with pytest.raises(engine.RayEngineError, match="cannot start Ray on a local instance"):
        engine._start_ray(RayOptions())
    assert "the log threshold is read now" in capfd.readouterr().err
    assert os.environ[CORE_LOG_LEVEL] == "debug" and ray_worker.connect is connect
