"""Unit tests of the bad-input guards: argparse value types, SQL statement checks, discovery rules."""

from __future__ import annotations

import argparse
import os

import pytest

from pipeline.cli_common import OneLineParser, float_range, image_size, int_range, number_list


@pytest.mark.parametrize(
    "parse, text, ok",
    [
        (int_range(16, 8192), "512", 512),
        (int_range(16, 8192), "0", None),
        (int_range(16, 8192), "1e3", None),
        (float_range(0.0, lo_open=True), "0", None),
        (float_range(0.0, lo_open=True), "0.5", 0.5),
        (float_range(), "nan", None),
        (float_range(), "-inf", None),
        (number_list(float, -1, 1), "0.1:0.3:0.1", (0.1, 0.2, 0.3)),
        (number_list(float, -1, 1), "0:1:0", None),
        (number_list(float, -1, 1), "0.1,2", None),
        (number_list(int, 1), "5,10", (5, 10)),
        (image_size(), "640x480", (640, 480)),
        (image_size(), "640", None),
    ],
)
def test_value_types(parse, text, ok):
    if ok is None:
        with pytest.raises(argparse.ArgumentTypeError):
            parse(text)
    else:
        assert parse(text) == ok


def test_one_line_parser_error(capsys):
    p = OneLineParser(prog="x")
    p.add_argument("--n", type=int_range(1))
    with pytest.raises(SystemExit) as exc:
        p.parse_args(["--n", "0"])
    assert exc.value.code == 2
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and err.startswith("x: error: argument --n: must be >= 1")


@pytest.mark.parametrize(
    "sql, refused",
    [
        ("SELECT 1", False),
        ("SET VARIABLE a = 1", False),
        ("-- comment\nSET VARIABLE a = 1", False),
        ("CREATE TABLE t AS SELECT 1", False),
        ("ATTACH 'x.db'", True),
        ("DETACH x", True),
        ("INSTALL httpfs", True),
        ("LOAD httpfs", True),
        ("SET threads = 1", True),
        ("RESET threads", True),
        ("EXPORT DATABASE 'x'", True),
        ("IMPORT DATABASE 'x'", True),
        ("CREATE OR REPLACE SECRET s (TYPE s3)", True),
    ],
)
def test_statement_checks(sql, refused):
    import duckdb

    from pipeline.sql.confine import RefusedStatement, check_statement

    (statement,) = duckdb.extract_statements(sql)
    if refused:
        with pytest.raises(RefusedStatement, match="refused"):
            check_statement(statement)
    else:
        check_statement(statement)


def test_confined_connection_reads_registered_data_only(tmp_path):
    import duckdb
    import pyarrow as pa
    import pyarrow.dataset as ds
    import pyarrow.parquet as pq

    from pipeline.sql.confine import confine

    pq.write_table(pa.table({"a": [1, 2]}), tmp_path / "t.parquet")
    con = duckdb.connect()
    con.register("t", ds.dataset(str(tmp_path / "t.parquet")))
    out = tmp_path / "out"
    out.mkdir()
    confine(con, out)
    assert con.execute("SELECT sum(a) FROM t").fetchall()[0][0] == 3
    con.execute(f"COPY (SELECT * FROM t) TO '{out}/x.csv'")
    assert (out / "x.csv").is_file()
    for sql in (f"SELECT * FROM read_parquet('{tmp_path}/t.parquet')", f"COPY t TO '{tmp_path}/y.csv'"):
        with pytest.raises(duckdb.PermissionException):
            con.execute(sql)
    with pytest.raises(duckdb.Error, match="locked"):
        con.execute("SET enable_external_access = true")


def test_export_dir_may_not_overlap_the_store(tmp_path):
    from pipeline.sql.confine import check_export_dir

    store = tmp_path / "store"
    store.mkdir()
    for bad in (store, store / "x", tmp_path):
        with pytest.raises(ValueError, match="overlaps the store"):
            check_export_dir(bad, store)
    assert check_export_dir(tmp_path / "out", store).is_dir()


def test_walk_library_special_files(tmp_path):
    from pipeline.mesh.discover import open_regular, walk_library

    (tmp_path / "a").mkdir()
    (tmp_path / "a" / "m.stl").write_bytes(b"solid x\nendsolid x\n")
    os.symlink("a", tmp_path / "b")  # the same folder again: followed once
    os.symlink("..", tmp_path / "a" / "up")  # a loop
    os.symlink("gone.obj", tmp_path / "dangling.obj")
    os.mkfifo(tmp_path / "pipe.obj")
    problems: list = []
    found = walk_library(tmp_path, problems)
    assert [f.source_path for f in found] == ["a/m.stl"]
    reasons = {f.source_path: r for f, r in problems}
    assert "dangling symlink" in reasons["dangling.obj"]
    assert "FIFO" in reasons["pipe.obj"]
    assert "followed once" in reasons["b"] and "followed once" in reasons["a/up"]
    with pytest.raises(ValueError, match="not a regular file"):
        open_regular(tmp_path / "pipe.obj")  # returns at once instead of waiting for a writer
