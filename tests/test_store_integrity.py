"""A freshly onboarded store read without this project, and every store-corruption case: one-line
errors naming the file in onboard, sql and query, and ``pipeline.fsck``."""

from __future__ import annotations

import shutil

import pytest
from conftest import SAMPLE_LIBRARY
from onboard_helpers import V, onboard

from pipeline.fsck import main as fsck_main
from pipeline.sql.cli import main as sql_main
from pipeline.store import Store, StoreError

TABLES = ["meshes", "views", "captions", "errors", "runs"]


@pytest.fixture(scope="module")
def built(tmp_path_factory, offline_models):
    root = tmp_path_factory.mktemp("integrity")
    lib, store = root / "lib", root / "store"
    shutil.copytree(SAMPLE_LIBRARY / "011_banana", lib / "banana")
    shutil.copytree(SAMPLE_LIBRARY / "006_mustard_bottle", lib / "mustard")
    onboard(lib, store, offline_models, batch_size=1)  # several commits per table
    (lib / "broken.obj").write_text("")
    onboard(lib, store, offline_models, batch_size=1)  # an errors row, a second runs row
    return lib, store


def _copy(built, tmp_path):
    lib, store = built
    shutil.copytree(store, tmp_path / "store")
    return lib, tmp_path / "store"


def test_each_table_opens_with_deltalake_and_polars(built):
    import polars as pl
    from deltalake import DeltaTable

    _, store = built
    s = Store.open(store)
    expected = {"meshes": 3, "views": 2 * V, "captions": 2 * V, "errors": 1, "runs": 2}
    for table, n in expected.items():
        assert DeltaTable(str(store / table)).to_pyarrow_table().num_rows == n, table
        assert pl.scan_delta(str(store / table)).select(pl.len()).collect().item() == n, table
        assert DeltaTable(str(store / table)).to_pandas().shape[0] == n
    datasets = [d for table in ("text_embeddings", "image_embeddings") for d in s.datasets(table)]
    assert len(datasets) == 3  # captions (MiniLM); views: the descriptor and the learned encoder
    for dataset in datasets:
        df = pl.scan_delta(str(store / dataset)).collect()
        assert df.height == 2 * V and set(df["view_index"]) == set(range(V))
        assert df["embedding"].list.len().unique().to_list() == [
            s.read(dataset).column("embedding").type.list_size
        ]
    import duckdb

    con = duckdb.connect()
    con.register("captions", DeltaTable(str(store / "captions")).to_pyarrow_dataset())
    assert con.execute("SELECT count(DISTINCT mesh_id) FROM captions").fetchall()[0][0] == 2


def _data_file(store, table="captions"):
    return Store.open(store).parts(table)[0]


def _truncate(store):
    f = _data_file(store)
    f.write_bytes(f.read_bytes()[:100])
    return f


def _delete(store):
    f = _data_file(store)
    f.unlink()
    return f


def _foreign(store):
    f = _data_file(store)
    shutil.copy(_data_file(store, "runs"), f)
    return f


def _damage_log(store):
    f = store / "captions" / "_delta_log" / f"{1:020d}.json"
    f.write_text('{"add": {"path": "x.parquet", "size"')
    return f


def _empty_log(store):
    f = store / "captions" / "_delta_log" / f"{0:020d}.json"
    f.write_text("")
    return f


def _missing_log(store):
    f = store / "captions" / "_delta_log" / f"{0:020d}.json"  # not the latest: that one is undetectable
    f.unlink()
    return f


CASES = {
    "truncated file": _truncate,
    "deleted file": _delete,
    "file of another table": _foreign,
    "damaged log entry": _damage_log,
    "empty log entry": _empty_log,
    "missing log entry": _missing_log,
}


@pytest.mark.parametrize("case", list(CASES))
def test_corruption_gives_one_line_errors_and_fsck_finds_it(case, built, tmp_path, capsys, offline_models):
    lib, store = _copy(built, tmp_path)
    before = {p: p.read_bytes() for p in store.rglob("*") if p.is_file()}
    bad = CASES[case](store)
    name = bad.name

    # sql
    assert sql_main([str(store), "-c", "SELECT count(*) FROM captions_all"]) == 2
    err = capsys.readouterr().err.strip()
    assert err.count("\n") == 0 and name in err and "pipeline.fsck" in err, err

    # query
    from pipeline.query.api import Retriever

    with pytest.raises(StoreError) as exc:
        Retriever.open(store, models=offline_models, preload=False, use_cache=False)
    assert name in str(exc.value) and "\n" not in str(exc.value)

    # onboard
    with pytest.raises(StoreError) as exc:
        onboard(lib, store, offline_models)
    assert name in str(exc.value) and "\n" not in str(exc.value)

    # fsck names it and changes nothing
    assert fsck_main([str(store)]) == 1
    out = capsys.readouterr().out
    assert name in out and "restore" in out
    after = {p: p.read_bytes() for p in store.rglob("*") if p.is_file() and p != bad}
    assert all(after[p] == before[p] for p in after if p in before and not p.name.startswith("_lock"))


def test_fsck_clean_store_and_orphans(built, tmp_path, capsys):
    _, store = _copy(built, tmp_path)
    assert fsck_main([str(store), "--runs"]) == 0
    out = capsys.readouterr().out
    assert "ok" in out
    shutil.copy(_data_file(store), store / "captions" / "part-00000-orphan-c000.zstd.parquet")
    assert fsck_main([str(store)]) == 0
    assert "no commit names" in capsys.readouterr().out
