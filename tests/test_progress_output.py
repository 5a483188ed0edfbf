"""Output that suits cron: plain progress lines off a terminal; a render worker that cannot start says why."""

from __future__ import annotations

import io
import os
import re
import shutil
import subprocess
import sys

import pytest
from conftest import REPO, SAMPLE_LIBRARY

from pipeline.progress import LineBar, duration, iterate, plural, stage_bars


def _onboard(lib, store, env, *extra):
    cmd = [sys.executable, "-m", "pipeline.onboard", str(lib), "--store", str(store), *extra]
    return subprocess.run(cmd, env=env, capture_output=True, text=True, timeout=600, stdin=subprocess.DEVNULL)


@pytest.fixture
def one_mesh_library(tmp_path):
    lib = tmp_path / "lib"
    shutil.copytree(SAMPLE_LIBRARY / "011_banana", lib / "011_banana")
    return lib


def test_line_bar_prints_start_throttled_counts_and_done():
    out = io.StringIO()
    b = LineBar("render", 3, "mesh", stream=out, interval=0.0)
    b.update(2)
    b.update(1)
    b.close()
    b.close()  # idempotent
    lines = out.getvalue().splitlines()
    assert lines[0] == "[progress] render: start, 3 meshes"
    assert re.fullmatch(r"\[progress\] render: 2/3 meshes, \d+\.\ds, [\d.?]+ meshes/s(, ETA \d+s)?", lines[1])
    assert re.fullmatch(r"\[progress\] render: done, 3/3 meshes in \d+\.\ds \([\d.?]+ meshes/s\)", lines[-1])
    assert len(lines) == 4
    assert (plural("query"), plural("view"), plural("mesh")) == ("queries", "views", "meshes")


def test_line_bar_rate_and_eta():
    out, now = io.StringIO(), [100.0]
    b = LineBar("render", 78, "mesh", stream=out, interval=60.0, clock=lambda: now[0])
    now[0] = 130.0
    b.update(15)  # throttled: no line yet
    now[0] = 160.0
    b.update(15)
    now[0] = 256.0
    b.update(48)
    b.close()
    lines = out.getvalue().splitlines()
    assert lines[1] == "[progress] render: 30/78 meshes, 60.0s, 0.50 meshes/s, ETA 1m 36s"
    assert lines[2] == "[progress] render: 78/78 meshes, 156.0s, 0.50 meshes/s, ETA 0s"
    assert lines[3] == "[progress] render: done, 78/78 meshes in 156.0s (0.50 meshes/s)"
    assert [duration(s) for s in (42, 185, 7620)] == ["42s", "3m 05s", "2h 07m"]


def test_off_a_terminal_no_bars_and_disabled_prints_nothing(capsys):
    bars = stage_bars({"render": 2, "caption": 0}, enabled=True)  # pytest's stderr is not a TTY
    assert isinstance(bars["render"], LineBar) and not isinstance(bars["caption"], LineBar)
    assert list(iterate([1, 2], "queries", unit="query", enabled=False)) == [1, 2]
    assert list(iterate([1, 2], "queries", unit="query")) == [1, 2]
    err = capsys.readouterr().err
    assert "render: start, 2 meshes" in err and "queries: done, 2/2 queries" in err
    assert "\r" not in err and "\x1b" not in err


def test_onboarding_into_a_log_has_plain_lines_only(one_mesh_library, tmp_path):
    env = {**os.environ, "PYTHONPATH": str(REPO), "TERM": "xterm-256color"}
    r = _onboard(one_mesh_library, tmp_path / "store", env, "--workers", "1")
    assert r.returncode == 0, r.stderr
    assert "\r" not in r.stderr and "\x1b" not in r.stderr and "\r" not in r.stdout
    for stage in ("render", "caption", "embed_text", "embed_image"):
        assert f"[progress] {stage}: start, 1 meshes" in r.stderr
        assert re.search(rf"\[progress\] {stage}: done, 1/1 meshes in \d+\.\ds", r.stderr), r.stderr
    assert "rendered 1 meshes" in r.stdout


def test_render_worker_that_cannot_import_pyrender_says_why(one_mesh_library, tmp_path):
    fake = tmp_path / "fake"
    (fake / "pyrender").mkdir(parents=True)
    (fake / "pyrender" / "__init__.py").write_text(
        "raise ImportError('cannot import name Mapping from collections (fake old pyrender)')\n"
    )
    env = {**os.environ, "PYTHONPATH": os.pathsep.join([str(fake), str(REPO)])}
    r = _onboard(one_mesh_library, tmp_path / "store", env, "--workers", "1", "--no-progress")
    assert r.returncode == 2, r.stderr
    (line,) = r.stderr.strip().splitlines()  # one line, no traceback
    assert line.startswith("error: render worker failed to start: ImportError: cannot import name Mapping")
    assert "libegl1" in line  # the EGL hint stays, after the real cause


def test_on_a_terminal_tqdm_bars_stay(monkeypatch):
    from tqdm import tqdm

    import pipeline.progress as progress

    monkeypatch.setattr(progress, "is_terminal", lambda stream=None: True)
    b = progress.bar("render", 2, unit="mesh")
    assert isinstance(b, tqdm)
    b.close()
