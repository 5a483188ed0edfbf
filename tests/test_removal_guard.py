"""The mass-removal guard: an emptied library (an unmounted share) or a large share of vanished files stops
the run before it commits anything; --allow-removal and --max-removed; empty new libraries only warn."""

from __future__ import annotations

import json
import shutil

import pytest
from conftest import SAMPLE_LIBRARY
from onboard_helpers import content, onboard

from pipeline.mesh.settings import RenderConfig
from pipeline.onboard.guard import RemovalGuardError, check_removals, parse_share
from pipeline.store import Store

SMALL = {"render": RenderConfig(resolution=32)}
TWO = ["011_banana", "006_mustard_bottle"]


def _library(path, names=TWO):
    path.mkdir(parents=True)
    for n in names:
        shutil.copytree(SAMPLE_LIBRARY / n, path / n)
    return path


def _runs(store) -> list[dict]:
    rows = Store.open(store).read("runs").to_pylist()
    return sorted(rows, key=lambda r: r["run_id"])


def _cli(lib, store, *extra) -> list[str]:
    return [str(lib), "--store", str(store), "--workers", "0", "--resolution", "32", "--no-progress", *extra]


def test_an_emptied_library_stops_before_any_commit(tmp_path, offline_models, capsys):
    from pipeline.onboard.cli import main

    lib = _library(tmp_path / "lib")
    store = tmp_path / "store"
    onboard(lib, store, offline_models, **SMALL)
    before, versions = content(store), Store.open(store).versions()
    for p in lib.iterdir():  # the share is not mounted: the folder exists, empty
        shutil.rmtree(p)

    with pytest.raises(RemovalGuardError, match="2 of 2 active files"):
        onboard(lib, store, offline_models, **SMALL)
    assert content(store) == before
    after = Store.open(store).versions()
    assert after == {**versions, "runs": versions["runs"] + 1}  # only the run's own record
    last = _runs(store)[-1]
    assert last["status"] == "refused"
    guard = json.loads(last["config_json"])["removal_guard"]
    assert guard == {
        "max_removed": 0.1,
        "allow_removal": False,
        "active": 2,
        "vanished": 2,
        "share": 1.0,
        "tripped": True,
    }

    # the CLI: one line, non-zero exit, nothing committed; even --max-removed 100% does not pass an empty library
    capsys.readouterr()
    assert main(_cli(lib, store, "--max-removed", "100%")) == 3
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and "yields no mesh file" in err and "--allow-removal" in err
    assert content(store) == before

    # the runs view names the guard
    from pipeline.db import connect

    con = connect(Store.open(store))
    row = con.execute("SELECT status, removal_guard FROM runs ORDER BY run_id DESC LIMIT 1").fetchall()[0]
    assert row[0] == "refused" and json.loads(row[1])["tripped"] is True

    # --allow-removal marks them removed, and says so in the summary
    assert main(_cli(lib, store, "--allow-removal")) == 0
    out = capsys.readouterr().out
    assert "2 removed" in out and "removal guard: 2 of 2 active files vanished (100%), off" in out
    assert not [r for r in Store.open(store).read_latest("meshes").to_pylist() if r["status"] == "active"]


def test_share_of_vanished_files(tmp_path, offline_models):
    lib = _library(tmp_path / "lib")
    store = tmp_path / "store"
    onboard(lib, store, offline_models, **SMALL)
    before = content(store)
    shutil.rmtree(lib / TWO[0])  # 1 of 2 active files: 50%
    with pytest.raises(
        RemovalGuardError, match=r"1 of 2 active files .*\(50%\): more than --max-removed 10%"
    ):
        onboard(lib, store, offline_models, **SMALL)
    with pytest.raises(RemovalGuardError):
        onboard(lib, store, offline_models, max_removed=0.49, **SMALL)
    assert content(store) == before
    summary = onboard(lib, store, offline_models, max_removed=0.5, **SMALL)  # not more than the limit
    assert summary.removed == 1 and summary.status == "ok"
    assert summary.removal_guard["tripped"] is False and "limit 50%" in summary.lines()[-1]


def test_changed_content_is_not_a_removal(tmp_path, offline_models):
    lib = _library(tmp_path / "lib", TWO[:1])
    store = tmp_path / "store"
    onboard(lib, store, offline_models, **SMALL)
    obj = lib / TWO[0] / "model.obj"
    obj.write_text(obj.read_text().replace("v ", "v  ", 1))  # new content: the old mesh row is replaced
    summary = onboard(lib, store, offline_models, **SMALL)
    assert summary.removed == 1 and summary.added == 1 and summary.removal_guard["vanished"] == 0


def test_empty_library_on_a_new_store_is_a_warning(tmp_path, capsys):
    from pipeline.onboard.cli import main

    (tmp_path / "empty").mkdir()
    assert main(_cli(tmp_path / "empty", tmp_path / "store")) == 0
    captured = capsys.readouterr()
    assert captured.err.startswith("warning: library") and "holds no mesh file" in captured.err
    assert "0 files" in captured.out
    assert _runs(tmp_path / "store")[-1]["status"] == "ok"


def test_a_library_that_came_back_counts_right(tmp_path, offline_models):
    lib = _library(tmp_path / "lib")
    store = tmp_path / "store"
    onboard(lib, store, offline_models, **SMALL)
    aside = tmp_path / "aside"
    lib.rename(aside)
    lib.mkdir()
    onboard(lib, store, offline_models, allow_removal=True, **SMALL)
    lib.rmdir()
    aside.rename(lib)
    summary = onboard(lib, store, offline_models, **SMALL)
    assert (summary.added, summary.restored, summary.skipped, summary.rendered) == (2, 2, 0, 0)
    assert "2 added (2 onboarded before, not rendered again), 0 removed, 0 unchanged" in summary.lines()[0]


def test_share_parsing_and_the_verdict():
    assert parse_share("10%") == pytest.approx(0.1) and parse_share("0.25") == 0.25
    for bad in ("10", "-1%", "101%", "x", "nan"):
        with pytest.raises(ValueError):
            parse_share(bad)
    assert not check_removals(100, 10, 90, 0.1, False).tripped  # exactly the limit passes
    assert check_removals(100, 11, 89, 0.1, False).tripped
    assert check_removals(1, 1, 0, 1.0, False).tripped  # no file at all: always
    assert not check_removals(1, 1, 0, 0.1, True).tripped
    assert not check_removals(0, 0, 0, 0.1, False).tripped  # a new, empty library


def test_bad_max_removed_is_a_one_line_usage_error(tmp_path, capsys):
    from pipeline.onboard.cli import main

    with pytest.raises(SystemExit) as exc:
        main(_cli(tmp_path, tmp_path / "s", "--max-removed", "10"))
    assert exc.value.code == 2 and "--max-removed" in capsys.readouterr().err


def test_library_path_that_is_a_file(tmp_path, capsys):
    from pipeline.onboard.cli import main

    f = tmp_path / "lib.obj"
    f.write_text("v 0 0 0\n")
    assert main(_cli(f, tmp_path / "s")) == 2
    err = capsys.readouterr().err
    assert "is a file" in err and "not found" not in err and err.count("\n") == 1
