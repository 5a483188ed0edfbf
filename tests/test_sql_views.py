"""The relations and views of ``pipeline.db.connect`` over hand-made stores."""

from __future__ import annotations

import duckdb
import pytest
from tiny_store import TinyStore

from pipeline.db import connect, load_sql, relation_name, view_files, view_names

LATER = "20250101T000000000000Z-zzzzzz"


def q(con, sql: str, params=None) -> list[tuple]:
    return con.execute(sql, params or []).fetchall()


@pytest.fixture
def store(tmp_path):
    t = TinyStore(tmp_path / "s")
    t.complete("a", "A red box-shaped object")
    t.complete("b", "A blue can")
    t.mesh("b", source_path="copy/b.obj")  # the same file twice in the library
    t.complete("old", "A green ball")
    t.mesh("old", status="removed", run_id=LATER)  # its file vanished
    t.complete("new", "A yellow bottle")
    t.mesh("new", source_path="old/old.obj")  # ... and a new file took its path
    t.views("a", fingerprint="r0")  # rows of an older render config
    t.embeddings("text_embeddings", "a", fingerprint="t0", encoder_id="clip_text:old", dim=5)
    t.error("caption", "b", "boom", fingerprint="c1")  # resolved: b has captions at c1
    t.run()
    return t.commit()


def test_every_view_file_has_a_header_and_comments():
    files = view_files()
    assert len(files) == len(view_names()) > 10
    for path in files:
        text = path.read_text()
        assert text.startswith("-- "), path.name
        assert "CREATE OR REPLACE VIEW" in text and "COMMENT ON VIEW" in text, path.name
        assert text.count("COMMENT ON COLUMN") >= 1, path.name


def test_raw_relations_keep_their_names(store):
    con = connect(store, views=False)
    assert q(con, "SELECT count(*) FROM meshes_all")[0][0] == 7
    assert q(con, "SELECT count(*) FROM text_embeddings__minilm_txt")[0][0] == 8
    assert q(con, "SELECT count(*) FROM text_embeddings__clip_text_old")[0][0] == 2
    # all encoders in one relation, vectors as variable-length lists
    dims = q(con, "SELECT DISTINCT len(embedding) FROM text_embeddings_all ORDER BY 1")
    assert dims == [(3,), (5,)]
    assert relation_name("views") == "views_all"
    assert relation_name("text_embeddings/minilm-txt") == "text_embeddings__minilm_txt"
    with pytest.raises(duckdb.CatalogException):
        con.execute("SELECT * FROM meshes")  # no views when asked for none


def test_empty_store_still_has_every_relation(tmp_path):
    t = TinyStore(tmp_path / "s")
    t.mesh("m")
    store = t.commit()
    con = connect(store)
    for name in ("errors_all", "runs_all", "views_all", "text_embeddings_all", "image_embeddings_all"):
        assert q(con, f"SELECT count(*) FROM {name}")[0][0] == 0
    assert q(con, "SELECT count(*) FROM captions")[0][0] == 0  # no run: nothing is current


def test_meshes_are_the_active_files(store):
    con = connect(store)
    rows = q(con, "SELECT mesh_id, source_path FROM meshes ORDER BY source_path")
    assert rows == [
        ("a", "a/a.obj"),
        ("b", "b/b.obj"),
        ("b", "copy/b.obj"),
        ("new", "new/new.obj"),
        ("new", "old/old.obj"),
    ]
    status = dict(q(con, "SELECT mesh_id, status FROM meshes_latest WHERE source_path = 'old/old.obj'"))
    assert status == {"old": "removed", "new": "active"}
    assert q(con, "SELECT n_paths FROM mesh_names WHERE mesh_id = 'b'") == [(2,)]


def test_current_views_captions_and_embeddings(store):
    con = connect(store)
    assert q(con, "SELECT stage, fingerprint FROM current_fingerprints ORDER BY stage") == [
        ("caption", "c1"),
        ("embed_image:view_encoder", "i1"),
        ("embed_text", "t1"),
        ("render", "r1"),
    ]
    assert q(con, "SELECT expected_views FROM current_config") == [(2,)]
    # current fingerprint and active meshes only
    assert q(con, "SELECT DISTINCT fingerprint FROM views") == [("r1",)]
    assert {m for (m,) in q(con, "SELECT DISTINCT mesh_id FROM captions")} == {"a", "b", "new"}
    assert q(con, "SELECT count(*) FROM views_latest WHERE mesh_id = 'a'") == [(4,)]  # r0 and r1
    assert q(con, "SELECT DISTINCT encoder_id FROM text_embeddings") == [("minilm:txt",)]
    assert q(con, "SELECT DISTINCT role FROM image_embeddings") == [("view_encoder",)]
    details = q(
        con, "SELECT name, view_index, elevation_deg, caption FROM caption_details WHERE mesh_id = 'a'"
    )
    assert sorted(details) == [
        ("a", 0, -15.0, "A red box-shaped object"),
        ("a", 1, 15.0, "A red box-shaped object"),
    ]
    assert q(con, "SELECT count(*) FROM caption_details WHERE mesh_id = 'b'") == [(2,)]  # not doubled


def test_encoders_and_errors(store):
    con = connect(store)
    enc = q(con, "SELECT table_name, encoder_id, dim, is_current, n_meshes FROM encoders ORDER BY 1, 2")
    assert enc == [
        ("image_embeddings", "descriptor:desc", 3, True, 4),
        ("text_embeddings", "clip_text:old", 5, False, 1),
        ("text_embeddings", "minilm:txt", 3, True, 4),
    ]
    assert q(con, "SELECT count(*) FROM errors_open") == [(0,)]  # b's caption error is resolved
    assert q(con, "SELECT stage, n_errors, n_open FROM error_summary") == [("caption", 1, 0)]


def test_view_sql_is_valid_without_python(store, tmp_path):
    """The view files run on plain DuckDB once the raw relations exist (as the init script does)."""
    con = connect(store, views=False)
    for name in view_names():
        con.execute(load_sql(f"views/{name}"))
    assert q(con, "SELECT count(*) FROM runs") == [(1,)]
