"""Readers and compaction: consistent snapshots, reader leases that ``compact`` spares, expired leases,
and reloading after a file vanished (Retriever and service, 200 after one retry or 503)."""

from __future__ import annotations

import json
import time
from pathlib import Path

import pytest
from query_helpers import fake_models, make_fake_store
from serve_helpers import add_fake_mesh

from pipeline import compact
from pipeline.leases import KEEPER, LEASE_DIR, Lease, live_leases, read_leases
from pipeline.query import Retriever
from pipeline.query.errors import StoreUnavailable
from pipeline.snapshot import consistent_versions
from pipeline.store import Store


def needed_files(store_path, versions: dict[str, int]) -> set[Path]:
    """The data files that the table ``versions`` reference."""
    from deltalake import DeltaTable

    out = set()
    for dataset, v in versions.items():
        for uri in DeltaTable(str(Path(store_path) / dataset), version=v).file_uris():
            out.add(Path(uri.removeprefix("file://")))
    return out


def latest_versions(store_path) -> dict[str, int]:
    with Store.open(store_path) as s:
        return s.versions()


def run_compact(store_path, capsys) -> str:
    assert compact.main([str(store_path), "--retention-hours", "0"]) == 0
    return capsys.readouterr().out


@pytest.fixture()
def store(tmp_path):
    path = make_fake_store(tmp_path / "store")
    add_fake_mesh(path, "extra", (200, 40, 200), 40, 40, features=True)  # two files per table to merge
    return path


def open_retriever(store, **kw) -> Retriever:
    return Retriever.open(store, models=fake_models(), use_cache=False, **kw)


def test_compact_with_retention_0_spares_an_open_retriever(store, capsys):
    r = open_retriever(store)
    (lease,) = read_leases(store)
    assert lease.kind == "retriever" and lease.versions == {d: [v] for d, v in r.versions.items()}
    need = needed_files(store, r.versions)
    out = run_compact(store, capsys)
    assert "kept for live readers: retriever" in out, out
    assert all(p.exists() for p in need)
    assert r.candidate_views(["id-extra"]) and r.generation == 0  # answered from the leased files
    assert r.verifier.store.read("view_features").num_rows == 2
    r.close()
    assert read_leases(store) == []
    out = run_compact(store, capsys)
    assert "kept for live readers" not in out
    now = needed_files(store, consistent_versions(store))
    assert not any(p.exists() for p in need - now)  # once released, the old files go


def test_expired_leases_are_ignored_and_removed(store, capsys):
    lease = Lease(store, "retriever", ttl=30)
    lease.held = [consistent_versions(store)]
    lease.renew()  # written once, never renewed: a reader killed without closing
    body = json.loads(lease.path.read_text())
    lease.path.write_text(json.dumps({**body, "heartbeat": time.time() - 60}))
    assert live_leases(store) == [] and len(read_leases(store)) == 1
    need = needed_files(store, lease.held[0])
    out = run_compact(store, capsys)
    assert "kept for live readers" not in out
    assert f"expired reader lease retriever {lease.id}" in out
    assert not lease.path.exists()
    assert not all(p.exists() for p in need)  # the expired lease protected nothing


def test_unreadable_or_unwritable_leases_do_not_stop_readers(store, caplog):
    (store / LEASE_DIR).mkdir()
    (store / LEASE_DIR / "junk.json").write_text("{not json")
    assert read_leases(store) == []
    (store / LEASE_DIR / "junk.json").unlink()
    (store / LEASE_DIR).rmdir()
    (store / LEASE_DIR).write_text("a file where the lease folder should be")
    r = open_retriever(store)
    assert not r.lease.writable and "cannot write the reader lease" in caplog.text
    assert r.n_meshes == 5 and r.candidate_views(["id-extra"])
    r.close()


def test_the_keeper_renews_the_heartbeat(store):
    lease = Lease(store, "retriever", ttl=0.4)
    lease.hold(consistent_versions(store))
    first = read_leases(store)[0].heartbeat
    deadline = time.monotonic() + 10
    while read_leases(store)[0].heartbeat == first and time.monotonic() < deadline:
        time.sleep(0.05)
    assert read_leases(store)[0].heartbeat > first and live_leases(store)
    lease.release()
    assert lease not in KEEPER._leases and not lease.path.exists()


def test_a_reader_sees_one_run_at_a_time(store):
    add_fake_mesh(store, "half", (10, 10, 250), 40, 40, features=True, finish=False)  # still committing
    r = open_retriever(store)
    assert "half" not in [r.mesh(m)["name"] for m in r.mesh_ids]
    latest = latest_versions(store)
    assert r.versions["meshes"] == latest["meshes"] - 1 and r.versions["runs"] == latest["runs"]
    assert r.store.version("view_features") == latest["view_features"] - 1  # pinned though not yet read
    r.close()


def batched_first_run(path) -> Path:
    """A store whose only run committed ``meshes`` in two batches (a first onboarding of many meshes):
    compaction merges its files while ``runs`` (one file, nothing superseded) has nothing to compact."""
    fake = make_fake_store(path.with_name(path.name + "-src"))
    with Store.open(fake) as src:
        tables = {d: src.read(d) for d in src.all_datasets() if src.delta(d) is not None}
    run_id = tables["runs"].column("run_id")[0].as_py()
    meshes, runs = tables.pop("meshes"), tables.pop("runs")
    with Store.open(path, create=True, writable=True) as s:
        s.commit({"meshes": meshes.slice(0, 2)}, run_id)
        s.commit({"meshes": meshes.slice(2), **tables}, run_id)
        s.commit({"runs": runs}, run_id)
    return path


@pytest.mark.parametrize("flags", [["--retention-hours", "0"], ["--no-vacuum"]])
def test_compaction_moves_readers_on_when_runs_had_nothing_to_compact(tmp_path, capsys, flags):
    """Readers pin each table as of the newest ``runs`` commit: compaction commits ``runs`` last, or new
    readers would stay on the versions it tombstoned (and, after the vacuum, find their files gone)."""
    path = batched_first_run(tmp_path / "store")
    with Store.open(path) as s:
        rows = s.read("runs").to_pylist()
    assert compact.main([str(path), *flags]) == 0
    out = capsys.readouterr().out
    assert consistent_versions(path) == latest_versions(path)  # the compacted tables, not the old ones
    assert "runs: 1 files -> 1" in out and "rewritten last" in out, out
    with Store.open(path) as s:
        assert s.read("runs").to_pylist() == rows and len(s.files("meshes")) == 1
    r = open_retriever(path)
    assert r.n_meshes == 4 and len(r.candidate_views(["id-red_can"])) == 2 and r.generation == 0
    r.close()
    assert compact.main([str(path), *flags]) == 0
    assert "rewritten" not in capsys.readouterr().out  # nothing compacted: no commit


def test_retriever_reloads_in_place_when_a_file_vanished(store, capsys):
    r = open_retriever(store, lease=False)  # nothing protects it: compaction deletes its files
    old = dict(r.versions)
    run_compact(store, capsys)
    assert not all(p.exists() for p in needed_files(store, old))
    views = r.candidate_views(["id-extra"])
    assert len(views) == 2 and r.generation == 1
    assert r.versions == consistent_versions(store) != old
    r.close()


def test_rank_alone_reloads_when_verification_meets_a_vanished_file(store, capsys):
    """``Retriever.rank`` (what sweeps and the evaluation call with a stored embedding) recovers like
    ``query``: verification reads ``view_features`` after compaction deleted the files it pinned."""
    from serve_helpers import enable_features
    from test_serve import red_can

    enable_features(store)
    add_fake_mesh(store, "more", (20, 200, 200), 40, 40, features=True)  # view_features: files to merge
    r = open_retriever(store, lease=False)
    assert r.verifier.available
    img, mask, _ = red_can()
    emb = r.embed(r.make_roi(img, "the red can", mask=mask), "the red can")
    old = dict(r.versions)
    run_compact(store, capsys)
    assert not all(p.exists() for p in needed_files(store, old))
    out = r.rank(emb, verify=True).to_dict()
    assert out["candidates"][0]["name"] == "red_can" and r.generation == 1
    assert r.versions == consistent_versions(store) != old
    r.close()


def test_retriever_raises_store_unavailable_when_the_newest_snapshot_fails_too(store, capsys):
    r = open_retriever(store, lease=False)
    run_compact(store, capsys)
    for p in needed_files(store, consistent_versions(store)):
        if "/views/" in str(p):
            p.unlink()  # damage the newest snapshot as well
    with pytest.raises(StoreUnavailable) as exc:
        r.candidate_views(["id-extra"])
    assert "\n" not in str(exc.value) and "is missing" in str(exc.value)
    r.close()


def test_vanished_file_is_recognised_whichever_layer_reports_it():
    from pipeline.query.errors import QueryError
    from pipeline.query.recover import vanished_file
    from pipeline.store import corrupt

    gone = corrupt(
        "/s", "store file /s/view_features/part-0.parquet is missing (table view_features, version 1)"
    )
    assert vanished_file(gone)
    assert vanished_file(FileNotFoundError(2, "No such file or directory"))
    assert vanished_file(
        OSError("Failed to open local file '/s/views/p.parquet'. Detail: [errno 2] No such file or directory")
    )
    assert vanished_file(RuntimeError("Generic delta error: Object at location /s/views/p.parquet not found"))
    wrapped = RuntimeError("scan failed")
    wrapped.__cause__ = FileNotFoundError("p.parquet")
    assert vanished_file(wrapped)
    assert not vanished_file(QueryError("no such file or directory: photo.jpg"))  # the user's input
    assert not vanished_file(ValueError("vector widths do not match"))
    assert vanished_file(gone, "/s") and not vanished_file(
        FileNotFoundError(2, "gone", "/models/m.onnx"), "/s"
    )
    assert not vanished_file(
        corrupt("/s", "store file /s/views/p.parquet is damaged: 10 bytes, its Delta log says 20")
    )


def test_a_lost_file_of_the_newest_snapshot_is_damage_not_a_reload(store):
    r = open_retriever(store)
    for p in needed_files(store, r.versions):
        if "/views/" in str(p):
            p.unlink()  # nothing committed since: no newer snapshot can help
    with pytest.raises(StoreUnavailable, match="no newer snapshot") as exc:
        r.candidate_views(["id-extra"])
    assert "pipeline.fsck" in str(exc.value) and r.generation == 0
    r.close()


def test_the_sql_shell_holds_a_lease_for_its_session(store, monkeypatch, capsys):
    from pipeline.snapshot import pin_and_lease
    from pipeline.sql import cli as sql_cli

    seen = []
    real = sql_cli._hold_lease

    def spy(s, leases):
        real(s, leases)
        seen.append((read_leases(store), s.versions()))

    monkeypatch.setattr(sql_cli, "_hold_lease", spy)
    assert sql_cli.main([str(store), "-c", "SELECT count(*) AS n FROM meshes_all"]) == 0
    ((leases, versions),) = seen
    assert [lease.kind for lease in leases] == ["sql"] and leases[0].versions == {
        d: [v] for d, v in versions.items()
    }
    assert read_leases(store) == []  # released when the session ended
    with Store.open(store, as_of=0) as old:
        assert pin_and_lease(old, "sql") is None  # time travel reads old versions, unleased
