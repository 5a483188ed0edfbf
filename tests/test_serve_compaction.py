"""The service while the store changes under it: one consistent snapshot per reload, a retry after a
vanished file (or 503 with Retry-After), and a soak on the loopback while runs, a removal and compaction
with retention 0 happen."""

from __future__ import annotations

import socket
import threading
import time
from collections import Counter

import pytest
from query_helpers import fake_models, make_fake_store
from serve_helpers import add_fake_mesh, enable_features, remove_fake_mesh
from test_leases import needed_files
from test_serve import png, red_can

pytest.importorskip("fastapi", reason="fastapi not installed (the serve dependencies)")
httpx = pytest.importorskip("httpx", reason="httpx not installed")

from fastapi.testclient import TestClient  # noqa: E402

from pipeline import compact  # noqa: E402
from pipeline.query import Retriever  # noqa: E402
from pipeline.serve.app import create_app  # noqa: E402
from pipeline.serve.service import QueryService, ServiceLimits  # noqa: E402
from pipeline.snapshot import consistent_versions  # noqa: E402
from pipeline.store import Store  # noqa: E402


def make_service(store, lease: bool = True, **limits) -> QueryService:
    r = Retriever.open(store, models=fake_models(), use_cache=False, lease=lease)
    return QueryService(r, ServiceLimits(**{"reload_interval": 0, "workers": 2, **limits}))


def compact0(store) -> str:
    import contextlib
    import io

    out = io.StringIO()
    with contextlib.redirect_stdout(out):
        assert compact.main([str(store), "--retention-hours", "0"]) == 0
    return out.getvalue()


@pytest.fixture()
def store(tmp_path):
    path = make_fake_store(tmp_path / "store")
    add_fake_mesh(path, "extra", (200, 40, 200), 40, 40, features=True)
    return path


def test_a_reload_leaves_no_table_behind(store):
    service = make_service(store)
    add_fake_mesh(store, "next", (250, 120, 0), 40, 40, features=True)  # a new run: every table moves
    assert service.reload_if_changed()
    r = service.snapshot.retriever
    with Store.open(store) as s:
        latest = s.versions()
    assert r.versions == latest and r.store.versions() == latest
    assert r.store.version("view_features") == latest["view_features"]  # not read by any query yet
    add_fake_mesh(store, "half", (10, 10, 250), 40, 40, features=True, finish=False)  # still committing
    assert not service.reload_if_changed()  # nothing of a run is served before its runs commit
    assert service.snapshot.retriever.versions == latest
    service.close()


def test_a_reload_moves_the_stage1_index_and_the_cache_with_the_tables(store, monkeypatch):
    """Derived data of the query path (the stage-1 index, the embedding cache) moves with the pinned
    snapshot on a reload: it covers exactly the versions the tables are read at (the new run's, not a run
    still committing)."""
    import json

    from pipeline.query import library

    monkeypatch.setattr(library, "CACHE_MIN_ROWS", 1)  # the fake store is tiny: cache it all the same
    r = Retriever.open(store, models=fake_models(), settings_changes={"stage1": "index"})
    service = QueryService(r, ServiceLimits(reload_interval=0, workers=2))
    add_fake_mesh(store, "next", (250, 120, 0), 40, 40, features=True)
    add_fake_mesh(store, "half", (10, 10, 250), 40, 40, features=True, finish=False)  # still committing
    assert service.reload_if_changed()
    r = service.snapshot.retriever
    with Store.open(store) as s:
        latest = s.versions()
    pinned = consistent_versions(store)
    assert r.versions == r.store.versions() == pinned and pinned["runs"] == latest["runs"]
    tables = r.tables
    assert pinned[tables.text_dataset] == latest[tables.text_dataset] - 1  # not the half run's commit
    assert r.text_filter.engine == "index", r.text_filter.notes
    assert r.text_filter.snapshot.manifest["delta_version"] == pinned[tables.text_dataset]
    assert r.text_filter.n_rows == tables.captions.num_rows == 2 * r.n_meshes  # the new mesh's captions too
    assert "id-half" not in r.mesh_ids and r.n_meshes == 6
    for kind, dataset in (("caption", tables.text_dataset), ("view", tables.view_dataset)):
        (manifest,) = (store / "_cache" / "query").glob(f"{kind}-*/manifest.json")
        covered = {name for seg in json.loads(manifest.read_text())["segments"] for name in seg["sources"]}
        assert covered == {p.name for p in r.store.parts(dataset)}, kind
    assert tables.cache_stats["caption"]["read_files"] == 1  # only the new run's file was read
    new = r.mesh_ids.index("id-next")
    assert new in tables.captions.column("mesh_idx").to_pylist()
    assert new in tables.views.column("mesh_idx").to_pylist()
    service.close()


def test_a_vanished_file_reloads_and_retries_once(store):
    service = make_service(store, lease=False)  # unprotected: compaction deletes what it reads
    old = dict(service.snapshot.retriever.versions)
    compact0(store)
    assert not all(p.exists() for p in needed_files(store, old))
    with TestClient(create_app(service)) as c:
        r = c.get("/meshes/id-extra")
        assert r.status_code == 200 and len(r.json()["views"]) == 2
        stats = c.get("/stats").json()
    assert stats["retries"] == 1 and stats["reloads"] == 1 and stats["errors"] == 0
    assert service.snapshot.retriever.versions == consistent_versions(store)
    service.close()


def test_503_with_retry_after_when_the_newest_snapshot_fails_too(store, monkeypatch):
    service = make_service(store, lease=False)
    reopens = []
    reopened = Retriever.reopened
    monkeypatch.setattr(Retriever, "reopened", lambda self, **kw: reopens.append(1) or reopened(self, **kw))
    img, _, box = red_can()
    # one answer before the damage: its pose hand-off reads the views' cameras (sql/view_poses.sql, the
    # views table) once and keeps them, so later queries need no views file (the first one would)
    service.snapshot.retriever.query(img, "the red can", box=box)
    compact0(store)
    for p in needed_files(store, consistent_versions(store)):
        if "/views/" in str(p):
            p.unlink()  # the newest snapshot is damaged as well
    with TestClient(create_app(service), raise_server_exceptions=False) as c:
        r = c.get("/meshes/id-extra")
        assert r.status_code == 503 and r.headers["Retry-After"] == "2"
        msg = r.json()["error"]
        assert "\n" not in msg and "store changed" in msg and "is missing" in msg
        again = c.get("/meshes/id-extra")  # the same newest snapshot is not reopened for each request
        assert again.status_code == 503 and again.json()["error"] == msg and len(reopens) == 1
        assert c.get("/stats").json()["last_reload_error"]
        # queries that need no lost file still answer from the old snapshot
        q = c.post(
            "/query",
            files={"image": ("p.png", png(img), "image/png")},
            data={"prompt": "the red can", "box": box},
        )
        assert q.status_code == 200 and q.json()["candidates"][0]["name"] == "red_can"
    service.close()


# ---------------------------------------------------------------------------- soak
def free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


class Clients:
    """``n`` threads that alternate POST /query and GET /meshes/<id> until stopped; every answer checked."""

    def __init__(self, url: str, n: int, mesh_id: str) -> None:
        img, _, box = red_can()
        self.url, self.mesh_id, self.photo, self.box = url, mesh_id, png(img), box
        self.codes: Counter = Counter()
        self.bad: list[str] = []
        self.names: set[str] = set()
        self.stop = threading.Event()
        self.threads = [threading.Thread(target=self._run, daemon=True) for _ in range(n)]
        self._lock = threading.Lock()

    def _run(self) -> None:
        with httpx.Client(base_url=self.url, timeout=30) as c:
            i = 0
            while not self.stop.is_set():
                i += 1
                try:
                    if i % 2:
                        r = c.post(
                            "/query",
                            files={"image": ("p.png", self.photo, "image/png")},
                            data={"prompt": "the red can", "box": self.box, "roi": "bbox", "top": "10"},
                        )
                    else:
                        r = c.get(f"/meshes/{self.mesh_id}")
                except httpx.HTTPError as exc:  # a dropped connection is a failed answer too
                    with self._lock:
                        self.codes[0] += 1
                        self.bad.append(f"transport: {type(exc).__name__}: {exc}")
                    continue
                self._check(r, i % 2 == 1)

    def _check(self, r, is_query: bool) -> None:
        with self._lock:
            self.codes[r.status_code] += 1
            try:
                body = r.json()
            except ValueError:
                self.bad.append(f"{r.status_code}: not JSON: {r.text[:80]}")
                return
            if r.status_code != 200:
                self.bad.append(f"{r.status_code}: {body}")
            elif is_query:
                cands = body.get("candidates")
                if not cands or any(not isinstance(c.get("name"), str) for c in cands):
                    self.bad.append(f"malformed query answer {body}")
                else:
                    self.names.update(c["name"] for c in cands)
            elif len(body.get("views", ())) != 2 or body.get("mesh_id") != self.mesh_id:
                self.bad.append(f"malformed mesh answer {body}")

    def __enter__(self):
        for t in self.threads:
            t.start()
        return self

    def __exit__(self, *exc) -> None:
        self.stop.set()
        for t in self.threads:
            t.join(timeout=30)


def wait_for(pred, seconds: float = 30.0) -> bool:
    deadline = time.monotonic() + seconds
    while time.monotonic() < deadline:
        if pred():
            return True
        time.sleep(0.05)
    return pred()


def service_files_missing(store) -> list:
    """Data files of the versions the service's live leases hold that no longer exist."""
    from pipeline.leases import live_leases

    held = [
        (d, v)
        for lease in live_leases(store)
        if lease.kind == "service"
        for d, vs in lease.versions.items()
        for v in vs
    ]
    assert held, "the service holds no live lease"
    return [p for d, v in held for p in needed_files(store, {d: v}) if not p.exists()]


def test_soak_runs_removal_and_compaction_while_clients_query(store):
    import uvicorn

    service = make_service(store, reload_interval=0.1)
    service.start_polling()
    port = free_port()
    server = uvicorn.Server(
        uvicorn.Config(create_app(service), host="127.0.0.1", port=port, log_level="warning", lifespan="off")
    )
    thread = threading.Thread(target=server.run, daemon=True)
    thread.start()
    assert wait_for(lambda: server.started), "the server did not start"
    compactions, missing = [], []
    try:
        with Clients(f"http://127.0.0.1:{port}", 3, "id-red_can") as clients:
            for step in range(2):
                add_fake_mesh(store, f"new_{step}", (250, 30 + step, 30), 40, 50, features=True)
                compactions.append(compact0(store))
                missing += service_files_missing(store)
                assert wait_for(lambda s=step: f"new_{s}" in clients.names), f"new_{step} never served"
            remove_fake_mesh(store, "id-green_can")
            compactions.append(compact0(store))
            missing += service_files_missing(store)
            add_fake_mesh(store, "new_2", (250, 35, 30), 40, 50, features=True)
            compactions.append(compact0(store))
            missing += service_files_missing(store)
            assert wait_for(lambda: "new_2" in clients.names), "new_2 never served"
            assert wait_for(lambda: service.snapshot.retriever.versions == consistent_versions(store))
            clients.names.clear()
            n = sum(clients.codes.values())
            assert wait_for(lambda: sum(clients.codes.values()) > n + 6)
    finally:
        server.should_exit = True
        thread.join(timeout=30)
        service.close()
    total = sum(clients.codes.values())
    assert total > 20 and not [c for c in clients.codes if c >= 500], clients.codes
    assert clients.bad == [], clients.bad[:5]
    assert "green_can" not in clients.names and {"red_can", "new_0"} <= clients.names
    assert any("kept for live readers: service" in out for out in compactions), compactions
    # retention 0 removed nothing the live service read: no leased file gone, no answer needed the retry
    assert missing == [] and service.counts["retries"] == 0, (missing[:3], service.counts)
    assert service.counts["reloads"] >= 4


def test_a_query_whose_view_features_vanished_is_answered(store):
    """The failure of issue 22: verification reads ``view_features`` after compaction deleted its files."""
    enable_features(store)
    add_fake_mesh(store, "more", (20, 200, 200), 40, 40, features=True)  # view_features: 3 files to merge
    service = make_service(store, lease=False)
    assert service.snapshot.retriever.verifier.available
    compact0(store)
    img, _, box = red_can()
    with TestClient(create_app(service)) as c:
        r = c.post(
            "/query",
            files={"image": ("p.png", png(img), "image/png")},
            data={"prompt": "the red can", "box": box},
        )
        assert r.status_code == 200, r.text
        assert r.json()["candidates"][0]["name"] == "red_can"
        assert c.get("/stats").json()["retries"] == 1
    service.close()


def test_a_second_vanished_file_is_one_clear_error():
    """The retry runs once: a query that meets a vanished store file on the newest snapshot too gets
    StoreUnavailable in one line (both snapshots released, one retry counted)."""
    import threading
    import types

    from pipeline.query.errors import StoreUnavailable
    from pipeline.serve.service import QueryService

    released, calls = [], []

    class Snap:
        def __init__(self, n):
            self.retriever = types.SimpleNamespace(store=types.SimpleNamespace(root="/stores/s"), n=n)

        def release(self):
            released.append(self.retriever.n)

    snaps = iter([Snap(1), Snap(2)])
    svc = object.__new__(QueryService)
    svc._stats_lock, svc.counts = threading.Lock(), {"retries": 0}
    svc.acquire = lambda: next(snaps)
    svc.reload_after_failure = lambda snap, reason: calls.append(reason)

    def query(retriever):
        raise FileNotFoundError(2, "No such file", f"/stores/s/views/part-{retriever.n}.parquet")

    with pytest.raises(StoreUnavailable, match="newest snapshot failed too") as exc:
        svc._attempts(query, ())
    assert "\n" not in str(exc.value) and "part-2" in str(exc.value)
    assert released == [1, 2] and svc.counts["retries"] == 1 and len(calls) == 1 and "part-1" in calls[0]
