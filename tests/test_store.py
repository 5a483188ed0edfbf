"""The store on its own: commits, latest-row semantics, compaction."""

from __future__ import annotations

import pyarrow as pa

from pipeline import schemas
from pipeline.compact import main as compact_main
from pipeline.store import Store, latest_rows


def _captions(ids, run_id, text):
    n = len(ids)
    return pa.table(
        {
            "mesh_id": ids,
            "view_index": pa.array([0] * n, pa.int16()),
            "captioner_id": ["c"] * n,
            "caption": [text] * n,
            "fingerprint": ["fp"] * n,
            "view_fingerprint": ["v"] * n,
            "run_id": [run_id] * n,
        }
    )


def test_latest_rows_keeps_highest_run_id():
    t = pa.table({"k": ["a", "b", "a", "a"], "run_id": ["1", "1", "3", "2"], "v": [1, 2, 3, 4]})
    assert sorted(latest_rows(t, ["k"]).to_pylist(), key=lambda r: r["k"]) == [
        {"k": "a", "run_id": "3", "v": 3},
        {"k": "b", "run_id": "1", "v": 2},
    ]


def test_commit_read_and_compact(tmp_path, capsys):
    s = Store.open(tmp_path / "st", create=True)
    s.commit({"captions": _captions(["m1", "m2"], "r1", "old")}, "r1")
    s.commit({"captions": _captions(["m1"], "r2", "new")}, "r2")
    assert s.read("captions").num_rows == 3
    latest = {r["mesh_id"]: r["caption"] for r in s.read_latest("captions").to_pylist()}
    assert latest == {"m1": "new", "m2": "old"}
    assert s.read("captions").schema.equals(schemas.CAPTIONS)  # conformed on write
    s.close()

    assert compact_main([str(tmp_path / "st")]) == 0
    assert "captions: 2 parts -> 1, 2 rows" in capsys.readouterr().out
    s = Store.open(tmp_path / "st")
    assert len(s.parts("captions")) == 1
    assert {r["mesh_id"]: r["caption"] for r in s.read("captions").to_pylist()} == latest
    assert len(list((tmp_path / "st" / "captions").glob("*.parquet"))) == 1  # replaced parts are deleted


def test_empty_commit_writes_nothing(tmp_path):
    s = Store.open(tmp_path / "st", create=True)
    assert s.commit({"captions": _captions([], "r", "x")}, "r") == 0
    assert not (tmp_path / "st" / "_log").exists()
