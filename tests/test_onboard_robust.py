"""Nightly-run robustness: bad meshes become errors rows, kill -9 + resume, atomic parts."""

from __future__ import annotations

import os
import shutil
import signal
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest
from conftest import REPO, SAMPLE_LIBRARY
from onboard_helpers import V, content, onboard

from pipeline.store import Store


def _write_bad_library(lib: Path) -> dict[str, str]:
    """Broken meshes beside one good one; returns file -> expected reason fragment."""
    lib.mkdir(parents=True)
    shutil.copytree(SAMPLE_LIBRARY / "011_banana", lib / "good")
    (lib / "empty.obj").write_bytes(b"")
    (lib / "corrupt.ply").write_bytes(
        b"ply\nformat binary_little_endian 1.0\nelement vertex 99999\n" + os.urandom(64)
    )
    (lib / "garbage.glb").write_bytes(os.urandom(256))
    (lib / "zero_area.obj").write_text("v 0 0 0\nv 1 0 0\nv 2 0 0\nf 1 2 3\n")
    (lib / "nan.obj").write_text("v 0 0 0\nv nan 0 0\nv 0 1 0\nv 0 0 1\nf 1 2 3\nf 1 3 4\n")
    (lib / "notex").mkdir()
    (lib / "notex" / "model.obj").write_text(
        "mtllib model.mtl\nv 0 0 0\nv 1 0 0\nv 0 1 0\nvt 0 0\nf 1/1 2/1 3/1\n"
    )
    (lib / "notex" / "model.mtl").write_text("newmtl m\nmap_Kd missing_texture.png \n")
    (lib / "nomtl.obj").write_text("mtllib nowhere.mtl\nv 0 0 0\nv 1 0 0\nv 0 1 0\nf 1 2 3\n")
    (lib / "five_million.ply").write_bytes(
        b"ply\nformat binary_little_endian 1.0\nelement vertex 2500000\nproperty float x\nproperty float y\n"
        b"property float z\nelement face 5000000\nproperty list uchar int vertex_indices\nend_header\n"
    )
    import trimesh

    trimesh.creation.icosphere(subdivisions=6).export(lib / "too_big.stl")  # 81,920 faces
    return {
        "empty.obj": "empty mesh",
        "corrupt.ply": "cannot parse",
        "garbage.glb": "cannot parse",
        "zero_area.obj": "zero-area",
        "nan.obj": "non-finite",
        "notex/model.obj": "missing texture",
        "nomtl.obj": "missing material file",
        "too_big.stl": "too many faces",
        "five_million.ply": "too many faces: 5,000,000",
    }


def test_bad_meshes_become_error_rows(tmp_path, offline_models):
    lib, store = tmp_path / "lib", tmp_path / "store"
    expected = _write_bad_library(lib)
    summary = onboard(lib, store, offline_models, max_faces=50_000)
    assert summary.rendered == 1 and summary.failed == len(expected)
    s = Store.open(store)
    errors = {r["source_path"]: r for r in s.read("errors").to_pylist()}
    for path, fragment in expected.items():
        assert path in errors, f"no errors row for {path}"
        reason = errors[path]["reason"]
        assert fragment in reason and "\n" not in reason, (path, reason)
    active = [r for r in s.read("meshes").to_pylist() if r["status"] == "active"]
    assert [r["source_path"] for r in active] == ["good/model.obj"]
    assert s.read("views").num_rows == V

    # a re-run neither retries the known failures nor duplicates their rows
    n_err = s.read("errors").num_rows
    summary = onboard(lib, store, offline_models, max_faces=50_000)
    assert summary.rendered == 0 and summary.failed_before >= 1
    assert Store.open(store).read("errors").num_rows == n_err

    # --retry-failed tries them again (with a bigger face budget the sphere now renders)
    summary = onboard(lib, store, offline_models, max_faces=100_000, retry_failed=True)
    assert summary.rendered >= 1
    names = {
        r["source_path"] for r in Store.open(store).read("meshes").to_pylist() if r["status"] == "active"
    }
    assert "too_big.stl" in names


def test_render_timeout_kills_only_that_mesh(tmp_path, offline_models):
    lib, store = tmp_path / "lib", tmp_path / "store"
    lib.mkdir()
    shutil.copytree(SAMPLE_LIBRARY / "011_banana", lib / "good")
    # a large ASCII OBJ takes seconds to parse: longer than the timeout
    n = 400_000
    v = np.random.default_rng(0).random((n, 3))
    with open(lib / "slow.obj", "w") as fh:
        np.savetxt(fh, v, fmt="v %.5f %.5f %.5f")
        idx = np.arange(1, n - 1)
        np.savetxt(fh, np.stack([idx, idx + 1, idx + 2], 1), fmt="f %d %d %d")
    summary = onboard(lib, store, offline_models, workers=1, render_timeout_s=2.0, max_faces=10_000_000)
    errors = Store.open(store).read("errors").to_pylist()
    assert [e["source_path"] for e in errors] == ["slow.obj"]
    assert "timed out" in errors[0]["reason"] and errors[0]["error_type"] == "Timeout"
    assert summary.rendered == 1


def _onboard_cmd(lib: Path, store: Path) -> list[str]:
    return [
        sys.executable,
        "-m",
        "pipeline.onboard",
        str(lib),
        "--store",
        str(store),
        "--batch-size",
        "1",
        "--workers",
        "0",
        "--no-progress",
    ]


def test_kill_during_run_then_resume_equals_uninterrupted(tmp_path):
    lib = tmp_path / "lib"
    shutil.copytree(SAMPLE_LIBRARY, lib)
    env = {**os.environ, "PYTHONPATH": str(REPO)}
    full, killed = tmp_path / "full", tmp_path / "killed"
    subprocess.run(_onboard_cmd(lib, full), check=True, env=env, capture_output=True, timeout=600)

    proc = subprocess.Popen(
        _onboard_cmd(lib, killed), env=env, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL
    )
    deadline = time.time() + 300
    while time.time() < deadline:  # kill -9 once the first batch is committed, mid-run
        log = killed / "views" / "_delta_log"
        if log.exists() and any(p.suffix == ".json" for p in log.iterdir()):
            break
        time.sleep(0.05)
    time.sleep(0.3)
    proc.send_signal(signal.SIGKILL)
    proc.wait()
    partial = Store.open(killed).read("views").num_rows
    assert 0 < partial < 32, "the kill should land mid-run"

    out = subprocess.run(
        _onboard_cmd(lib, killed), check=True, env=env, capture_output=True, text=True, timeout=600
    )
    assert "error" not in out.stderr.lower()
    assert content(killed) == content(full)


def test_uncommitted_files_are_invisible_and_cleaned(tmp_path, offline_models):
    from pipeline.compact import main as compact_main

    lib, store = tmp_path / "lib", tmp_path / "store"
    shutil.copytree(SAMPLE_LIBRARY / "011_banana", lib / "banana")
    onboard(lib, store, offline_models)
    before = content(store)
    # what a writer killed between writing a data file and committing it leaves behind
    orphan = store / "views" / "part-00000-orphan-c000.zstd.parquet"
    shutil.copy(next((store / "views").glob("part-*.parquet")), orphan)
    assert content(store) == before  # readers go by the Delta log
    Store.open(store, writable=True).close()  # a writer does not delete what the log does not name
    assert orphan.exists()
    # compact --remove-orphans does, once they are older than the retention period
    assert compact_main([str(store), "--remove-orphans", "--retention-hours", "0"]) == 0
    assert not orphan.exists()
    assert content(store) == before


def test_two_onboardings_at_once_second_gets_a_clear_error(tmp_path, offline_models):
    from pipeline.store import StoreError

    lib, store = tmp_path / "lib", tmp_path / "store"
    shutil.copytree(SAMPLE_LIBRARY / "011_banana", lib / "banana")
    holder = Store.open(store, create=True)  # stands in for a first onboarding in progress
    with pytest.raises(StoreError, match="locked by another writer"):
        onboard(lib, store, offline_models)
    holder.close()
    assert onboard(lib, store, offline_models).rendered == 1


def test_second_writer_is_refused(tmp_path):
    from pipeline.store import StoreError

    s = Store.open(tmp_path / "st", create=True)
    with pytest.raises(StoreError, match="locked"):
        Store.open(tmp_path / "st", writable=True)
    s.close()
    Store.open(tmp_path / "st", writable=True).close()


def test_cli_errors_are_one_line(tmp_path):
    env = {**os.environ, "PYTHONPATH": str(REPO)}
    r = subprocess.run(
        [sys.executable, "-m", "pipeline.onboard", str(tmp_path / "nope"), "--store", str(tmp_path / "s")],
        capture_output=True,
        text=True,
        env=env,
    )
    assert r.returncode != 0 and r.stderr.strip().count("\n") == 0 and "not found" in r.stderr
    (tmp_path / "notastore").mkdir()
    (tmp_path / "notastore" / "file.txt").write_text("x")
    lib = tmp_path / "lib"
    lib.mkdir()
    r = subprocess.run(
        [sys.executable, "-m", "pipeline.onboard", str(lib), "--store", str(tmp_path / "notastore")],
        capture_output=True,
        text=True,
        env=env,
    )
    assert r.returncode != 0 and "not an OSCAR store" in r.stderr and r.stderr.strip().count("\n") == 0
