"""The package is self-contained: a built wheel carries every SQL file and reads it through
importlib.resources from any directory; the lock files meet pyproject.toml's requirements."""

from __future__ import annotations

import importlib.util
import os
import shutil
import subprocess
import sys
import zipfile

import pytest
from conftest import REPO

from pipeline.db import audit_names, load_sql, view_names
from pipeline.resources import sql_root


def _check_lock():
    spec = importlib.util.spec_from_file_location("check_lock", REPO / "scripts" / "check_lock.py")
    mod = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(mod)
    return mod


def test_checkout_reads_the_top_level_sql_folder():
    assert os.path.samefile(str(sql_root()), REPO / "sql")
    assert audit_names() == sorted(p.stem for p in (REPO / "sql" / "audit").glob("*.sql"))
    assert view_names() == sorted(p.stem for p in (REPO / "sql" / "views").glob("*.sql"))
    assert load_sql("stage1_text_filter").startswith("--")
    with pytest.raises(FileNotFoundError, match="no SQL file sql/nope.sql"):
        load_sql("nope")


@pytest.fixture(scope="module")
def wheel(tmp_path_factory):
    """A wheel built from a copy of the checkout's package files (the checkout stays clean)."""
    pytest.importorskip("setuptools")
    src = tmp_path_factory.mktemp("src")
    for name in ("pyproject.toml", "setup.py", "README.md"):
        shutil.copy(REPO / name, src / name)
    ignore = shutil.ignore_patterns("__pycache__", "*.pyc")
    shutil.copytree(REPO / "pipeline", src / "pipeline", ignore=ignore)
    shutil.copytree(REPO / "sql", src / "sql")
    out = tmp_path_factory.mktemp("dist")
    cmd = [
        sys.executable,
        "-m",
        "pip",
        "wheel",
        "-q",
        "--no-deps",
        "--no-build-isolation",
        "-w",
        str(out),
        str(src),
    ]
    r = subprocess.run(cmd, capture_output=True, text=True, timeout=300)
    assert r.returncode == 0, r.stderr[-2000:]
    (whl,) = out.glob("oscar_pipeline-*.whl")
    return whl


def test_wheel_ships_every_sql_file_and_the_oscar_script(wheel):
    assert _check_lock().check_wheel(str(wheel)) == []
    names = zipfile.ZipFile(wheel).namelist()
    assert "pipeline/py.typed" in names
    assert "pipeline/query/calibration/offline.json" in names  # the open-set acceptance calibration
    assert not [n for n in names if n.startswith("sql/")]  # inside the package, not a top-level "sql" package


def test_wheel_reads_its_sql_from_another_directory(wheel, tmp_path):
    site = tmp_path / "site"
    zipfile.ZipFile(wheel).extractall(site)
    code = (
        "from pipeline.resources import sql_root; from pipeline.db import audit_names, load_sql, view_names; "
        "print(sql_root()); print(len(audit_names()), len(view_names()), len(load_sql('candidate_views')))"
    )
    cwd = tmp_path / "elsewhere"
    cwd.mkdir()
    r = subprocess.run(
        [sys.executable, "-c", code],
        cwd=cwd,
        capture_output=True,
        text=True,
        timeout=120,
        env={**os.environ, "PYTHONPATH": str(site)},
    )
    assert r.returncode == 0, r.stderr
    root, counts = r.stdout.splitlines()
    assert root == str(site / "pipeline" / "_sql")
    n_audits, n_views, n_chars = map(int, counts.split())
    assert (n_audits, n_views) == (len(audit_names()), len(view_names())) and n_chars > 0


def test_lock_files_meet_pyproject_and_hold_no_cuda_packages():
    mod = _check_lock()
    assert mod.check_pyproject() == []
    base = mod.read_lock("base")
    assert base["torch"] == "2.13.0" and base["pyrender"] == "0.1.45" and base["pyopengl"] == "3.1.0"
    for s in mod.SETS:  # each set is compiled under the pins of the one before: they install together
        pins = mod.read_lock(s)
        assert not [n for n in pins if mod.CUDA.match(n)]
        assert all(pins[n] == v for n, v in base.items() if n in pins)


def _install(*args, **env):
    return subprocess.run(
        ["bash", str(REPO / "scripts" / "install.sh"), *args],
        capture_output=True,
        text=True,
        timeout=60,
        env={**os.environ, **env},
        stdin=subprocess.DEVNULL,
    )


def test_install_never_touches_a_system_interpreter():
    base = os.path.join(sys.base_prefix, "bin", "python3")
    if not os.access(base, os.X_OK):
        pytest.skip(f"no base interpreter at {base}")
    r = _install("dev", PYTHON=base)
    assert r.returncode == 2
    assert "is not a virtual environment; OSCAR never installs into a system interpreter" in r.stderr


def test_install_rejects_an_unknown_lock_set(tmp_path):
    r = _install("dev,nope", VENV=str(tmp_path / "venv"))
    assert r.returncode == 2 and "no lock set 'nope'" in r.stderr
    assert not (tmp_path / "venv").exists()
