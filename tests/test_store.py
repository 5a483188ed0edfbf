"""The store on its own: Delta commits, latest-row semantics, compaction, vacuum, time travel."""

from __future__ import annotations

import time

import pyarrow as pa
import pytest

from pipeline import schemas
from pipeline.compact import main as compact_main
from pipeline.store import Store, StoreError, latest_rows


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


def _embeddings(ids, run_id, dim=4):
    n = len(ids)
    return pa.table(
        {
            "mesh_id": ids,
            "view_index": pa.array([0] * n, pa.int16()),
            "encoder_id": ["e"] * n,
            "dim": pa.array([dim] * n, pa.int32()),
            "embedding": pa.array([[1.0] + [0.0] * (dim - 1)] * n, pa.list_(pa.float32(), dim)),
            "fingerprint": ["fp"] * n,
            "source_fingerprint": ["s"] * n,
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
    assert s.read("captions").schema.equals(schemas.CAPTIONS)  # explicit schema on write and read
    s.close()

    assert compact_main([str(tmp_path / "st")]) == 0
    assert "captions: 2 files -> 1, 2 rows (1 superseded dropped)" in capsys.readouterr().out
    s = Store.open(tmp_path / "st")
    assert len(s.parts("captions")) == 1
    assert {r["mesh_id"]: r["caption"] for r in s.read("captions").to_pylist()} == latest
    # the default retention (7 days) keeps the replaced files for readers of older snapshots
    assert len(list((tmp_path / "st" / "captions").glob("*.parquet"))) == 3
    assert compact_main([str(tmp_path / "st"), "--retention-hours", "0"]) == 0
    assert len(list((tmp_path / "st" / "captions").glob("*.parquet"))) == 1


def test_embedding_tables_keep_fixed_width_vectors(tmp_path):
    s = Store.open(tmp_path / "st", create=True)
    s.commit({"text_embeddings/enc-a": _embeddings(["m1"], "r1", 4)}, "r1")
    s.commit({"text_embeddings/enc-b": _embeddings(["m1"], "r1", 6)}, "r1")
    s = Store.open(tmp_path / "st")
    assert s.datasets("text_embeddings") == ["text_embeddings/enc-a", "text_embeddings/enc-b"]
    assert s.read("text_embeddings/enc-a").schema.equals(schemas.embedding_schema(4))
    assert s.read("text_embeddings/enc-b").schema.equals(schemas.embedding_schema(6))


def test_empty_commit_writes_nothing(tmp_path):
    s = Store.open(tmp_path / "st", create=True)
    assert s.commit({"captions": _captions([], "r", "x")}, "r") == 0
    assert not (tmp_path / "st" / "captions").exists()


def test_commit_order_is_upstream_first_runs_last(tmp_path):
    s = Store.open(tmp_path / "st", create=True)
    runs = pa.Table.from_pylist([{"run_id": "r", "status": "ok"}], schema=schemas.RUNS)
    s.commit({"runs": runs, "captions": _captions(["m"], "r", "x")}, "r")
    t_caps = (tmp_path / "st/captions/_delta_log/00000000000000000000.json").stat().st_mtime_ns
    t_runs = (tmp_path / "st/runs/_delta_log/00000000000000000000.json").stat().st_mtime_ns
    assert t_caps <= t_runs


def test_reader_keeps_its_snapshot_through_compaction(tmp_path):
    """A DuckDB connection and an Arrow dataset opened before compact + vacuum keep answering."""
    from pipeline.db import connect

    s = Store.open(tmp_path / "st", create=True)
    for i in range(4):
        s.commit({"captions": _captions([f"m{i}", "m0"], f"r{i}", f"c{i}")}, f"r{i}")
    s.close()
    reader = Store.open(tmp_path / "st")
    con = connect(reader)
    arrow = reader.dataset("captions")
    before = con.execute("SELECT count(*) FROM captions_all").fetchall()[0][0]
    assert before == 8

    assert compact_main([str(tmp_path / "st")]) == 0  # default retention: old files stay
    assert con.execute("SELECT count(*) FROM captions_all").fetchall()[0][0] == before
    assert arrow.to_table().num_rows == before
    assert con.execute("SELECT count(*) FROM captions_latest").fetchall()[0][0] == 4  # views too
    fresh = Store.open(tmp_path / "st")
    assert fresh.read("captions").num_rows == 4 and len(fresh.parts("captions")) == 1


def test_second_writer_gets_a_clear_error(tmp_path):
    s = Store.open(tmp_path / "st", create=True)
    with pytest.raises(StoreError, match="locked by another writer"):
        Store.open(tmp_path / "st", writable=True)
    assert compact_main([str(tmp_path / "st")]) == 2  # compact too
    s.close()
    Store.open(tmp_path / "st", writable=True).close()


def test_time_travel_by_runs_version_and_time(tmp_path):
    s = Store.open(tmp_path / "st", create=True)
    stamps = []
    for i in range(3):
        runs = pa.Table.from_pylist([{"run_id": f"r{i}", "status": "ok"}], schema=schemas.RUNS)
        s.commit({"captions": _captions([f"m{i}"], f"r{i}", "x"), "runs": runs}, f"r{i}")
        stamps.append(time.time())
        time.sleep(0.05)
    s.close()
    assert Store.open(tmp_path / "st", as_of=0).read("captions").num_rows == 1
    assert Store.open(tmp_path / "st", as_of="1").read("captions").num_rows == 2
    assert Store.open(tmp_path / "st").read("captions").num_rows == 3
    from datetime import datetime, timezone

    at = datetime.fromtimestamp(stamps[1], tz=timezone.utc).isoformat()
    assert Store.open(tmp_path / "st", as_of=at).read("captions").num_rows == 2
    with pytest.raises(StoreError, match="no runs version 7"):
        Store.open(tmp_path / "st", as_of=7)


def test_sql_as_of(tmp_path, capsys):
    import json

    from pipeline.sql.cli import main as sql_main

    s = Store.open(tmp_path / "st", create=True)
    for i in range(2):
        runs = pa.Table.from_pylist([{"run_id": f"r{i}", "status": "ok"}], schema=schemas.RUNS)
        s.commit({"captions": _captions([f"m{i}"], f"r{i}", "x"), "runs": runs}, f"r{i}")
    s.close()
    sql = ["-c", "SELECT count(*) AS n FROM captions_all", "--format", "json"]
    assert sql_main([str(tmp_path / "st"), "--as-of", "0", *sql]) == 0
    assert json.loads(capsys.readouterr().out) == [{"n": 1}]
    assert sql_main([str(tmp_path / "st"), *sql]) == 0
    assert json.loads(capsys.readouterr().out) == [{"n": 2}]
    assert sql_main([str(tmp_path / "st"), "--as-of", "yesterday", *sql]) == 2
    assert "--as-of expects" in capsys.readouterr().err


def _views(ids, n_views, run_id):
    rows = [(m, v) for v in range(n_views) for m in ids]  # not in model order, as a batch may come
    n = len(rows)
    return pa.table(
        {
            "mesh_id": [m for m, _ in rows],
            "view_index": pa.array([v for _, v in rows], pa.int16()),
            "azimuth_deg": pa.array([0.0] * n, pa.float32()),
            "elevation_deg": pa.array([0.0] * n, pa.float32()),
            "camera_pose": pa.array([[0.0] * 16] * n, schemas.MAT4),
            "yfov_deg": pa.array([40.0] * n, pa.float32()),
            "width": pa.array([8] * n, pa.int32()),
            "height": pa.array([8] * n, pa.int32()),
            "image": [f"{m}/{v}".encode() for m, v in rows],
            "fingerprint": ["fp"] * n,
            "run_id": [run_id] * n,
        }
    )


def test_views_are_written_by_model_in_small_row_groups(tmp_path):
    """The views table (the PNGs) is written sorted by model in row groups of VIEW_ROW_GROUP_ROWS, so a
    read of one model's views skips the others' row groups; other tables keep the large groups; compaction
    keeps the small groups, and the query path's read of some views of a model gives the same bytes."""
    import pyarrow.parquet as pq

    from pipeline.store import ROW_GROUP_ROWS, VIEW_ROW_GROUP_ROWS

    ids = [f"m{i:02d}" for i in range(9)]
    s = Store.open(tmp_path / "st", create=True)
    s.commit({"views": _views(ids, 12, "r1"), "captions": _captions(ids * 3, "r1", "c")}, "r1")
    s.commit({"views": _views(ids[:3], 12, "r2")}, "r2")

    def groups(dataset):
        out = []
        for f in sorted((tmp_path / "st" / dataset).glob("*.parquet")):
            md = pq.ParquetFile(f).metadata
            for g in range(md.num_row_groups):
                col = md.row_group(g).column(0)  # mesh_id
                out.append((md.row_group(g).num_rows, col.statistics.min, col.statistics.max))
        return out

    views = groups("views")
    assert max(n for n, _, _ in views) == VIEW_ROW_GROUP_ROWS == 12
    assert all(lo == hi for _, lo, hi in views)  # 12 views per model: one model per row group
    assert len(groups("captions")) == 1 and ROW_GROUP_ROWS > 27
    s.close()
    assert compact_main([str(tmp_path / "st")]) == 0
    s = Store.open(tmp_path / "st")
    assert len(s.parts("views")) == 1 and max(n for n, _, _ in groups("views")) <= VIEW_ROW_GROUP_ROWS
    assert s.read("views").num_rows == 9 * 12  # the superseded rows of r1 dropped
    from pipeline.db import connect, load_sql

    con = connect(s)
    got = con.sql(
        load_sql("view_images"),
        params={"mesh_id": "m01", "view_indices": [0, 5, 99], "render_fingerprint": "fp"},
    ).fetchall()
    assert sorted((int(v), bytes(b)) for v, b in got) == [(0, b"m01/0"), (5, b"m01/5")]
    s.close()
    # another camera layout (8 views per model): the groups follow the model, not VIEW_ROW_GROUP_ROWS
    s = Store.open(tmp_path / "st8", create=True)
    s.commit({"views": _views(ids[:4], 8, "r1")}, "r1")
    s.commit({"views": _views(ids[4:], 8, "r2")}, "r2")
    s.close()
    assert compact_main([str(tmp_path / "st8")]) == 0

    def live_groups(root):  # the row groups of the files the current version names (not the old ones)
        with Store.open(root) as st:
            files = [pq.ParquetFile(path).metadata for path, _ in st.files("views")]
        return [
            (md.row_group(g).num_rows, md.row_group(g).column(0).statistics.min, md.row_group(g).column(0).statistics.max)
            for md in files
            for g in range(md.num_row_groups)
        ]

    eight = live_groups(tmp_path / "st8")
    assert [n for n, _, _ in eight] == [8] * 9 and all(lo == hi for _, lo, hi in eight)
    mixed = Store.open(tmp_path / "mixed", create=True)  # models with different view counts: fixed groups
    mixed.commit({"views": pa.concat_tables([_views(ids[:2], 8, "r1"), _views(ids[2:4], 13, "r1")])}, "r1")
    mixed.close()
    assert max(n for n, _, _ in live_groups(tmp_path / "mixed")) == VIEW_ROW_GROUP_ROWS
