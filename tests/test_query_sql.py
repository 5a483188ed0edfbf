"""The query path's SQL files against a few hand-made rows (in-memory DuckDB)."""

from __future__ import annotations

import duckdb
import numpy as np
import pyarrow as pa
import pytest
from query_helpers import make_store, unit

from pipeline.db import load_sql
from pipeline.query.stage1 import TextFilter


def captions(rows: list[tuple[int, list[float]]]) -> pa.Table:
    """stage1_captions rows: (mesh_idx, embedding)."""
    dim = len(rows[0][1])
    flat = np.asarray([v for _, v in rows], dtype=np.float32).reshape(-1)
    return pa.table(
        {
            "mesh_idx": pa.array([m for m, _ in rows], pa.int32()),
            "embedding": pa.FixedSizeListArray.from_arrays(pa.array(flat), dim),
        }
    )


# mesh 0: captions scoring 0.9 and 0.1 against q = e1; mesh 1: 0.5; mesh 2: 0.3 and 0.5; mesh 3: -1
ROWS = [
    (0, [0.9, np.sqrt(1 - 0.81), 0.0]),
    (0, [0.1, 0.0, np.sqrt(1 - 0.01)]),
    (1, [0.5, np.sqrt(0.75), 0.0]),
    (2, [0.3, 0.0, np.sqrt(1 - 0.09)]),
    (2, [0.5, 0.0, np.sqrt(0.75)]),
    (3, [-1.0, 0.0, 0.0]),
]
Q = np.array([1.0, 0.0, 0.0], np.float32)


@pytest.fixture()
def text_filter():
    f = TextFilter(captions(ROWS), threads=1)
    yield f
    f.close()


def test_score_is_max_over_captions_and_threshold_keeps_passing_models(text_filter):
    r = text_filter.run(Q, threshold=0.45, fallback_k=10)
    assert not r.used_fallback
    assert r.mesh_idx.tolist()[0] == 0 and sorted(r.mesh_idx.tolist()[1:]) == [1, 2]
    np.testing.assert_allclose(r.scores, [0.9, 0.5, 0.5], atol=1e-6)


def test_ties_are_broken_by_mesh_index(text_filter):
    r = text_filter.run(Q, threshold=0.45, fallback_k=10)
    assert r.mesh_idx.tolist() == [0, 1, 2]  # meshes 1 and 2 tie at 0.5
    top2 = text_filter.run(Q, threshold=None, fallback_k=2)
    assert top2.mesh_idx.tolist() == [0, 1]


def test_threshold_is_inclusive(text_filter):
    r = text_filter.run(Q, threshold=0.9, fallback_k=10)
    assert r.mesh_idx.tolist() == [0] and not r.used_fallback


def test_fallback_top_k_when_nothing_passes(text_filter):
    r = text_filter.run(Q, threshold=0.95, fallback_k=3)
    assert r.used_fallback
    assert r.mesh_idx.tolist() == [0, 1, 2]
    np.testing.assert_allclose(r.scores, [0.9, 0.5, 0.5], atol=1e-6)
    everything = text_filter.run(Q, threshold=2.0, fallback_k=100)
    assert everything.mesh_idx.tolist() == [0, 1, 2, 3] and everything.scores[-1] == pytest.approx(-1.0)


def test_fallback_counts_captions_or_meshes(text_filter):
    # caption scores: 0.9 (m0), 0.5 (m1), 0.5 (m2), 0.3 (m2), 0.1 (m0), -1 (m3)
    by_caption = text_filter.run(Q, threshold=0.95, fallback_k=3, fallback_unit="captions")
    assert by_caption.used_fallback and by_caption.mesh_idx.tolist() == [0, 1, 2]
    two = text_filter.run(Q, threshold=0.95, fallback_k=2, fallback_unit="captions")
    assert two.mesh_idx.tolist() == [0, 1]  # captions 0.9 (m0) and 0.5 (m1, lower mesh_idx wins the tie)
    five = text_filter.run(Q, threshold=0.95, fallback_k=5, fallback_unit="captions")
    assert five.mesh_idx.tolist() == [0, 1, 2]  # 5 captions, 3 distinct meshes
    np.testing.assert_allclose(five.scores, [0.9, 0.5, 0.5], atol=1e-6)  # a mesh keeps its best caption
    by_mesh = text_filter.run(Q, threshold=0.95, fallback_k=5, fallback_unit="meshes")
    assert by_mesh.mesh_idx.tolist() == [0, 1, 2, 3]
    passing = text_filter.run(Q, threshold=0.45, fallback_k=1, fallback_unit="captions")
    assert (
        passing.mesh_idx.tolist() == [0, 1, 2] and not passing.used_fallback
    )  # unit only matters on fallback
    with pytest.raises(ValueError, match="fallback unit"):
        text_filter.run(Q, threshold=0.5, fallback_k=1, fallback_unit="views")


@pytest.mark.parametrize("k", [1, 3, 7, 20, 400])
def test_caption_fallback_matches_numpy_on_random_rows(k):
    rng = np.random.default_rng(k)
    vecs = unit(rng.standard_normal((400, 16)))
    mesh = rng.integers(0, 60, 400)  # uneven caption counts per mesh
    vecs[::7] = vecs[3]  # tied caption scores across meshes
    f = TextFilter(captions(list(zip(mesh.tolist(), vecs.tolist(), strict=True))))
    q = unit(rng.standard_normal(16))
    r = f.run(q, threshold=None, fallback_k=k, fallback_unit="captions")
    s = f.run(q, threshold=None, fallback_k=400, fallback_unit="meshes")
    mesh_score = dict(zip(s.mesh_idx.tolist(), s.scores.tolist(), strict=True))
    # independent: the k best caption rows by (score desc, mesh_idx), as their distinct meshes
    cap = (vecs @ q).astype(np.float32)
    top = np.lexsort((mesh, -cap))[:k]
    want = sorted(set(mesh[top].tolist()), key=lambda m: (-mesh_score[m], m))
    assert r.mesh_idx.tolist() == want and r.used_fallback
    f.close()


def test_null_threshold_is_plain_top_k(text_filter):
    r = text_filter.run(Q, threshold=None, fallback_k=1)
    assert r.mesh_idx.tolist() == [0] and r.used_fallback


def test_query_vector_width_is_checked(text_filter):
    with pytest.raises(ValueError, match="3"):
        text_filter.run(np.ones(4, np.float32), threshold=0.5, fallback_k=1)


def test_sql_matches_numpy_on_random_rows():
    rng = np.random.default_rng(1)
    vecs = unit(rng.standard_normal((400, 16)))
    mesh = np.repeat(np.arange(50), 8)
    f = TextFilter(captions(list(zip(mesh.tolist(), vecs.tolist(), strict=True))))
    q = unit(rng.standard_normal(16))
    r = f.run(q, threshold=None, fallback_k=50, fallback_unit="meshes")
    ref = (vecs @ q).reshape(50, 8).max(axis=1)
    order = np.lexsort((np.arange(50), -ref))
    assert r.mesh_idx.tolist() == order.tolist()
    np.testing.assert_allclose(r.scores, ref[order], atol=1e-6)


def test_stage1_sql_binds_every_value():
    sql = load_sql("stage1_text_filter")
    assert sql.lstrip().startswith("--")
    for name in [f"$q{i}" for i in range(8)] + ["$threshold", "$fallback_k", "$fallback_unit"]:
        assert name in sql


def _con(store_path):
    from pipeline.query.library import connect_store
    from pipeline.store import Store

    return connect_store(Store.open(store_path))


def test_active_meshes_sql(tmp_path):
    from datetime import datetime, timezone

    from pipeline import schemas
    from pipeline.store import Store

    e = unit(np.eye(4))
    path = make_store(
        tmp_path / "s",
        {
            "m-b": {"name": "bee", "captions": e[:1], "views": e[:1], "source_path": "z/bee.obj"},
            "m-a": {"name": "ay", "captions": e[1:2], "views": e[1:2]},
            "m-gone": {"name": "gone", "captions": e[2:3], "views": e[2:3]},
        },
    )
    store = Store.open(path, writable=True)
    now = datetime(2025, 1, 2, tzinfo=timezone.utc)
    later = "20250102T000000000000Z-bbbbbb"
    rows = [  # m-gone is removed later; m-b gains a second path that sorts first
        {
            "mesh_id": "m-gone",
            "source_path": "gone/model.obj",
            "library_root": "/library",
            "name": "gone",
            "status": "removed",
            "seen_at": now,
            "run_id": later,
        },
        {
            "mesh_id": "m-b",
            "source_path": "a/copy.obj",
            "library_root": "/library",
            "name": "bee copy",
            "status": "active",
            "seen_at": now,
            "run_id": later,
        },
    ]
    store.commit({"meshes": pa.Table.from_pylist(rows, schema=schemas.MESHES)}, later)
    store.close()
    con = _con(path)
    out = con.sql(load_sql("query_active_meshes")).to_arrow_table().to_pylist()
    assert [(r["mesh_idx"], r["mesh_id"], r["source_path"], r["n_paths"]) for r in out] == [
        (0, "m-a", "ay/model.obj", 1),
        (1, "m-b", "a/copy.obj", 2),
    ]


def test_embedding_sql_filters_fingerprint_and_keeps_latest_run(tmp_path):
    e = unit(np.eye(3))
    path = make_store(tmp_path / "s", {"m1": {"name": "one", "captions": e[:2], "views": e[:1]}})
    con = _con(path)
    meshes = con.sql(load_sql("query_active_meshes")).to_arrow_table()
    con.register("query_meshes", meshes.select(["mesh_idx", "mesh_id"]))
    src = pa.table(
        {
            "mesh_id": ["m1", "m1", "m1", "other"],
            "view_index": pa.array([0, 0, 1, 0], pa.int16()),
            "embedding": pa.FixedSizeListArray.from_arrays(
                pa.array(np.vstack([e[0], e[1], e[2], e[2]]).reshape(-1)), 3
            ),
            "fingerprint": ["fp", "fp", "old", "fp"],
            "run_id": ["r1", "r2", "r3", "r1"],
        }
    )
    con.register("query_caption_source", src)
    out = con.sql(load_sql("query_caption_embeddings"), params={"fingerprint": "fp"}).to_arrow_table()
    assert out.num_rows == 1 and out.column("mesh_idx").to_pylist() == [0]
    assert out.column("embedding").to_pylist() == [e[1].tolist()]  # run r2 supersedes r1


def test_candidate_views_sql(tmp_path):
    from PIL import Image

    e = unit(np.eye(3))
    img = Image.new("RGB", (8, 8), (10, 20, 30))
    path = make_store(
        tmp_path / "s",
        {
            "m1": {"name": "one", "captions": e[:1], "views": e[:2], "images": [img, img]},
            "m2": {"name": "two", "captions": e[1:2], "views": e[1:2], "images": [img]},
        },
    )
    con = _con(path)
    params = {"mesh_ids": ["m1"], "render_fingerprint": "fp-render", "caption_fingerprint": "fp-caption"}
    rows = con.sql(load_sql("candidate_views"), params=params).to_arrow_table().to_pylist()
    assert [(r["mesh_id"], r["view_index"]) for r in rows] == [("m1", 0), ("m1", 1)]
    assert rows[0]["image"][:4] == b"\x89PNG"
    injection = {**params, "mesh_ids": ["m1' OR '1'='1"]}
    assert con.sql(load_sql("candidate_views"), params=injection).to_arrow_table().num_rows == 0


def test_duckdb_rejects_unbound_parameters():
    from pipeline.query.stage1 import query_params, slice_layout

    con = duckdb.connect()
    con.register("stage1_captions", slice_layout(captions(ROWS)))
    with pytest.raises(duckdb.Error):
        con.execute(load_sql("stage1_text_filter"), query_params(Q, 1))


@pytest.mark.parametrize("dim", [3, 8, 13, 384])
def test_sliced_layout_keeps_the_inner_product(dim):
    from pipeline.query.stage1 import slice_layout

    rng = np.random.default_rng(dim)
    vecs = unit(rng.standard_normal((16, dim)))
    table = slice_layout(captions(list(zip(range(16), vecs.tolist(), strict=True))))
    assert table.num_columns == 9 and table.schema.metadata[b"dim"] == str(dim).encode()
    f = TextFilter(table)
    q = unit(rng.standard_normal(dim))
    r = f.run(q, threshold=None, fallback_k=16)
    np.testing.assert_allclose(np.sort(r.scores), np.sort(vecs @ q), atol=1e-6)


@pytest.mark.parametrize("unit_", ["captions", "meshes"])
def test_blas_kernel_matches_the_all_sql_reference(unit_):
    """``run_blas`` (BLAS scores + stage1_select.sql) gives the answer of ``run_sql`` (stage1_text_filter.sql)."""
    rng = np.random.default_rng(7)
    mesh = rng.permutation(np.repeat(np.arange(60), 5))  # rows in no particular order, like the cache
    vecs = unit(rng.standard_normal((len(mesh), 20)))
    f = TextFilter(captions(list(zip(mesh.tolist(), vecs.tolist(), strict=True))))
    for q in unit(rng.standard_normal((6, 20))):
        s = np.sort(vecs @ q)[::-1]
        for tau in (None, float(s[3] + s[4]) / 2, float(s[40] + s[41]) / 2, 1.5):
            a, b = f.run_blas(q, tau, 7, unit_), f.run_sql(q, tau, 7, unit_)
            assert a.mesh_idx.tolist() == b.mesh_idx.tolist() and a.used_fallback == b.used_fallback
            np.testing.assert_allclose(a.scores, b.scores, atol=1e-6)
    f.close()


def test_run_picks_the_kernel_by_table_size(monkeypatch):
    """``run`` is the all-SQL reference on small tables and the BLAS kernel from BLAS_MIN_ROWS rows on,
    with the same models in the same order (and NumPy's ranking)."""
    import pipeline.query.stage1 as stage1

    rng = np.random.default_rng(3)
    mesh = rng.permutation(np.repeat(np.arange(40), 4))
    vecs = unit(rng.standard_normal((len(mesh), 12)))
    f = TextFilter(captions(list(zip(mesh.tolist(), vecs.tolist(), strict=True))))
    used = []
    monkeypatch.setattr(f, "run_blas", lambda *a: used.append("blas") or TextFilter.run_blas(f, *a))
    monkeypatch.setattr(f, "run_sql", lambda *a: used.append("sql") or TextFilter.run_sql(f, *a))
    q = unit(rng.standard_normal(12))
    small = f.run(q, None, 40, "meshes")
    monkeypatch.setattr(stage1, "BLAS_MIN_ROWS", len(mesh))
    large = f.run(q, None, 40, "meshes")
    monkeypatch.setattr(stage1, "BLAS_MAX_BYTES", 1000)  # a copy this large is not made: the SQL scan
    f._kernel = None
    f.run(q, None, 40, "meshes")
    assert used == ["sql", "blas", "sql"]
    best = np.full(40, -np.inf)
    np.maximum.at(best, mesh, vecs @ q)
    assert small.mesh_idx.tolist() == large.mesh_idx.tolist() == np.argsort(-best, kind="stable").tolist()
    np.testing.assert_allclose(large.scores, best[large.mesh_idx], atol=1e-6)
    f.close()
