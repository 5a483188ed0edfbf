"""``pipeline.migrate``: an old-format store (Parquet parts + ``_log``) becomes the same Delta store."""

from __future__ import annotations

import shutil

import pyarrow.compute as pc
from conftest import SAMPLE_LIBRARY
from onboard_helpers import content, onboard

from pipeline.migrate import main as migrate_main
from pipeline.migrate import write_legacy
from pipeline.store import Store, StoreError


def test_migrate_old_store_keeps_every_row_and_needs_no_rendering(tmp_path, offline_models, capsys):
    lib, store = tmp_path / "lib", tmp_path / "store"
    shutil.copytree(SAMPLE_LIBRARY / "011_banana", lib / "banana")
    onboard(lib, store, offline_models)
    s = Store.open(store)
    # the same rows in the old layout, one old commit per table and run, as the old writer made them
    commits = []
    for dataset in s.all_datasets():
        t = s.read(dataset)
        for run in sorted(set(t.column("run_id").to_pylist())):
            commits.append((run, {dataset: t.filter(pc.field("run_id") == run)}))
    commits.sort(key=lambda c: c[0])
    write_legacy(tmp_path / "old", commits)

    try:
        Store.open(tmp_path / "old")
        raise AssertionError("an old store must not open as a Delta store")
    except StoreError as exc:
        assert "pipeline.migrate" in str(exc)

    assert migrate_main([str(tmp_path / "old"), str(tmp_path / "new")]) == 0
    assert "migrated" in capsys.readouterr().out
    assert content(tmp_path / "new") == content(store)
    # the migrated store is a working store: an unchanged re-run renders nothing
    summary = onboard(lib, tmp_path / "new", offline_models)
    assert summary.rendered == 0 and summary.captioned == 0
    # refusing a non-empty target and an old store with a missing part, with one line
    assert migrate_main([str(tmp_path / "old"), str(tmp_path / "new")]) == 2
    next((tmp_path / "old" / "views").glob("*.parquet")).unlink()
    assert migrate_main([str(tmp_path / "old"), str(tmp_path / "new2")]) == 2
    assert "missing" in capsys.readouterr().err
