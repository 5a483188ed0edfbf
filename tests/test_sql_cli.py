"""``python -m pipeline.sql``: -c, -f, formats, audits, the piped shell, exports."""

from __future__ import annotations

import csv
import io
import json
import subprocess
import sys

import duckdb
import pytest
from tiny_store import TinyStore

from pipeline.sql.cli import main


@pytest.fixture
def store(tmp_path):
    t = TinyStore(tmp_path / "store")
    t.complete("a", "A red box-shaped object")
    t.complete("b", "blue")
    t.run()
    t.commit()
    return str(tmp_path / "store")


def run(capsys, *argv) -> tuple[int, str, str]:
    code = main(list(argv))
    out = capsys.readouterr()
    return code, out.out, out.err


def test_command_prints_a_table(store, capsys):
    code, out, _ = run(capsys, store, "-c", "SELECT mesh_id, caption FROM captions ORDER BY 1, view_index")
    assert code == 0
    lines = out.splitlines()
    assert lines[0].split() == ["mesh_id", "caption"] and lines[-1] == "(4 rows)"
    assert "A red box-shaped object" in out


@pytest.mark.parametrize("fmt", ["csv", "json", "markdown"])
def test_formats(store, capsys, fmt):
    sql = "SELECT mesh_id, view_index, image, embedding FROM views JOIN text_embeddings USING (mesh_id, view_index) ORDER BY 1, 2"
    code, out, _ = run(capsys, store, "--format", fmt, "-c", sql)
    assert code == 0
    if fmt == "csv":
        rows = list(csv.DictReader(io.StringIO(out)))
        assert (
            len(rows) == 4
            and rows[0]["image"].startswith("<blob ")
            and rows[0]["embedding"] == "[1.0, 0.0, 0.0]"
        )
    elif fmt == "json":
        rows = json.loads(out)
        assert (
            rows[0]["mesh_id"] == "a"
            and rows[0]["view_index"] == 0
            and rows[0]["embedding"] == [1.0, 0.0, 0.0]
        )
    else:
        assert out.splitlines()[0] == "| mesh_id | view_index | image | embedding |"
        assert out.splitlines()[1] == "|---|---|---|---|"


def test_file_runs_every_statement(store, capsys, tmp_path):
    sql = tmp_path / "q.sql"
    sql.write_text(
        "-- two results\nCREATE TEMP TABLE t AS SELECT 41 AS x;\nSELECT x + 1 AS y FROM t;\nSELECT 'z' AS z;\n"
    )
    code, out, _ = run(capsys, store, "-f", str(sql), "--format", "csv")
    assert code == 0 and out.split() == ["y", "42", "z", "z"]


def test_audits_from_the_command_line(store, capsys):
    code, out, _ = run(capsys, store, "--audit", "short_captions")
    assert code == 0 and "audit short_captions: 2 offending row(s)" in out
    code, out, _ = run(capsys, store, "--audit", "all", "--check")
    assert code == 1 and out.count("-- audit ") == 6
    code, _, _ = run(
        capsys,
        store,
        "--audit",
        "short_captions",
        "--check",
        "--set",
        "audit_min_caption_chars=1",
        "--set",
        "audit_min_caption_words=1",
    )
    assert code == 0
    code, _, err = run(capsys, store, "--audit", "nope")
    assert code == 1 and "no audit 'nope'" in err
    code, out, _ = run(capsys, store, "--list-audits")
    assert "missing_outputs" in out.split()


def test_errors_are_one_line(store, capsys, tmp_path):
    code, _, err = run(capsys, store, "-c", "SELECT * FROM no_such_table")
    assert code == 1 and err.startswith("error: ") and len(err.strip().splitlines()) == 1
    code, _, err = run(capsys, str(tmp_path / "nowhere"), "-c", "SELECT 1")
    assert code == 2 and "no store at" in err


def test_piped_shell(store, capsys, monkeypatch):
    script = "SELECT count(*) AS n\nFROM captions;\n.mode csv\n.describe meshes\nSELECT 1 AS broken FROM nope;\nSELECT 2 AS two;\n"
    monkeypatch.setattr(sys, "stdin", io.StringIO(script))
    code, out, err = run(capsys, store)
    assert code == 1  # one statement failed; the others still ran
    assert out.startswith("n\n-\n4\n(1 row)\n")
    assert "mesh_id,VARCHAR,sha256" in out and out.rstrip().endswith("two\n2")
    assert "Error:" in err


def test_exports_open_in_plain_duckdb(store, capsys, tmp_path):
    db = tmp_path / "out.duckdb"
    code, out, _ = run(capsys, store, "--export-duckdb", str(db))
    assert code == 0 and db.exists()
    with duckdb.connect(str(db), read_only=True) as con:
        assert con.execute("SELECT count(*) FROM caption_details").fetchall() == [(4,)]
        assert con.execute("SELECT count(*) FROM meshes_all").fetchall() == [(2,)]
    code, _, err = run(capsys, store, "--export-duckdb", str(db))
    assert code == 2 and "exists" in err
    assert run(capsys, store, "--export-duckdb", str(db), "--force")[0] == 0

    code, script, _ = run(capsys, store, "--init-script")
    assert code == 0 and "read_parquet([" in script
    con = duckdb.connect()
    con.execute(script)
    assert con.execute("SELECT count(*) FROM captions").fetchall() == [(4,)]
    assert con.execute("SELECT count(*) FROM errors_all").fetchall() == [(0,)]  # empty table, typed


def test_module_entry_point(store):
    out = subprocess.run(
        [
            sys.executable,
            "-m",
            "pipeline.sql",
            store,
            "-c",
            "SELECT count(*) AS n FROM meshes",
            "--format",
            "json",
        ],
        capture_output=True,
        text=True,
        check=True,
    )
    assert json.loads(out.stdout) == [{"n": 2}]


def test_store_in_object_storage_through_a_pyarrow_filesystem(store, capsys, tmp_path):
    """A store copied to object storage is read through pyarrow filesystems (file:// stands in for s3://)."""
    uri = "file://" + str(tmp_path / "store")
    sql = "SELECT mesh_id, view_index, caption FROM captions ORDER BY 1, 2"
    assert (
        run(capsys, store, "-c", sql, "--format", "json")[1]
        == run(capsys, uri, "-c", sql, "--format", "json")[1]
    )
    code, out, _ = run(capsys, uri, "--audit", "short_captions", "--format", "csv")
    assert code == 0 and out.count("\nb,") == 2
    code, _, err = run(capsys, uri, "--init-script")
    assert code == 2 and "local store" in err
    code, _, err = run(capsys, "file://" + str(tmp_path / "nowhere"), "-c", "SELECT 1")
    assert code == 2 and "no OSCAR store" in err
