"""The stage-1 index: same answers as the exact path, incremental sync, no churn on compaction, exact
fallback with a note when it cannot be used, fsck, and ``--stage1``."""

from __future__ import annotations

import numpy as np
import pyarrow as pa
import pytest
from query_helpers import embedding_table, make_store, unit

from pipeline.index.choose import IndexUnavailable, open_index, open_stage1
from pipeline.index.layout import index_dir, read_manifest
from pipeline.index.sync import status, sync, text_dataset
from pipeline.query.library import StoreTables, latest_onboarding
from pipeline.query.stage1 import TextFilter
from pipeline.store import Store

DIM = 16
RUN = "20250101T000000000000Z-aaaaaa"


def clustered(n_mesh: int, seed: int = 0) -> dict[str, dict]:
    rng = np.random.default_rng(seed)
    topics = rng.standard_normal((max(4, n_mesh // 20), DIM))
    meshes = {}
    for i in range(n_mesh):
        centre = topics[rng.integers(len(topics))] + 0.5 * rng.standard_normal(DIM)
        meshes[f"m{i:05d}"] = {
            "name": f"m{i}",
            "captions": unit(centre + 0.4 * rng.standard_normal((8, DIM))),
            "views": unit(rng.standard_normal((2, 4))),
        }
    return meshes


@pytest.fixture
def store_path(tmp_path):
    return make_store(tmp_path / "store", clustered(300))


def tables_of(store):
    return StoreTables(store, latest_onboarding(store), use_cache=False)


def snapshot(store, exhaustive: bool = True):
    snap = open_index(store, tables_of(store))
    if exhaustive:  # every list probed: the index must then give exactly the exact path's answer
        snap.index.nprobe = snap.index.nlist
        snap.probe_delta = None  # the fixed nprobe, not the tau-following depth
    return snap


def queries(n: int = 24, seed: int = 1) -> np.ndarray:
    """Perturbed captions of the fixture's models."""
    x = np.concatenate([m["captions"] for m in clustered(300).values()])
    rng = np.random.default_rng(seed)
    base = x[rng.integers(len(x), size=n)]
    return unit(base + 0.3 * rng.standard_normal(base.shape)).astype(np.float32)


def commit(path, meshes: dict[str, dict], run_id: str):
    from pipeline import schemas

    rows, ids, idx, vecs = [], [], [], []
    from datetime import datetime, timezone

    for mid, m in meshes.items():
        rows.append(
            {
                "mesh_id": mid,
                "source_path": f"{m['name']}/model.obj",
                "library_root": "/library",
                "name": m["name"],
                "format": "obj",
                "status": m.get("status", "active"),
                "seen_at": datetime(2025, 1, 2, tzinfo=timezone.utc),
                "run_id": run_id,
            }
        )
        for i, v in enumerate(m.get("captions", [])):
            ids.append(mid)
            idx.append(i)
            vecs.append(v)
    with Store.open(path, writable=True) as store:
        ds, fp, enc = text_dataset(store, latest_onboarding(store))
        tables = {"meshes": pa.Table.from_pylist(rows, schema=schemas.MESHES)}
        if vecs:
            tables[ds] = embedding_table(ids, idx, vecs, enc, fp, run_id)
        store.commit(tables, run_id)


def answers_equal(a, b):
    assert a.mesh_idx.tolist() == b.mesh_idx.tolist()
    assert a.used_fallback == b.used_fallback
    np.testing.assert_allclose(a.scores, b.scores, atol=1e-5)


def test_index_equals_exact_on_tau_sets_and_fallbacks(store_path):
    with Store.open(store_path) as store:
        exact = TextFilter(tables_of(store).captions)
        snap = snapshot(store)
        qs = queries()
        for q in qs:
            s = np.sort(exact.caption_scores(q)[1])[::-1]
            for tau in (float(s[5] + s[6]) / 2, float(s[60] + s[61]) / 2, 1.5):
                for unit_ in ("captions", "meshes"):
                    answers_equal(snap.run(q, tau, 10, unit_), exact.run(q, tau, 10, unit_))
            answers_equal(snap.run(q, None, 5, "meshes"), exact.run(q, None, 5, "meshes"))


def test_model_scores_are_the_best_caption_per_model_on_either_filter(store_path):
    """The fusion's text terms (``model_scores``): each model's best caption cosine, from the exact filter
    and, unchanged, from the index's filter (which reads its exact table for them); a wrong width is refused."""
    with Store.open(store_path) as store:
        tables = tables_of(store)
        exact = TextFilter(tables.captions)
        indexed = open_stage1(store, tables, "index")
        assert indexed.engine == "index"
        for q in queries(3):
            rows_mesh, rows = exact.caption_scores(q)
            models, best = exact.model_scores(q)
            want = {int(m): float(rows[rows_mesh == m].max()) for m in np.unique(rows_mesh)}
            assert dict(zip(models.tolist(), best.tolist(), strict=True)) == pytest.approx(want, abs=1e-6)
            im, ib = indexed.model_scores(q)
            np.testing.assert_array_equal(im, models)
            np.testing.assert_allclose(ib, best, atol=1e-6)
        with pytest.raises(ValueError, match="dims"):
            exact.model_scores(np.ones(DIM + 1, np.float32))
        indexed.close()


def test_default_probe_keeps_top1(store_path):
    with Store.open(store_path) as store:
        exact = TextFilter(tables_of(store).captions)
        snap = snapshot(store, exhaustive=False)
        same = [snap.run(q, 1.5, 10).mesh_idx[0] == exact.run(q, 1.5, 10).mesh_idx[0] for q in queries()]
    assert np.mean(same) >= 0.9


def test_manifest_records_version_encoder_and_fingerprint(store_path):
    with Store.open(store_path) as store:
        ds, fp, enc = text_dataset(store, latest_onboarding(store))
        rep = sync(store, ds, fp, enc)
        man = read_manifest(index_dir(store.root, ds, fp))
        assert rep.action == "build"
        assert (man["delta_version"], man["encoder_id"], man["fingerprint"]) == (store.version(ds), enc, fp)
        assert sync(store, ds, fp, enc).action == "none"


def test_commit_adds_and_force_replaces_without_rebuild(store_path):
    with Store.open(store_path) as store:
        ds, fp, enc = text_dataset(store, latest_onboarding(store))
        gen = sync(store, ds, fp, enc).manifest["generation"]
    new = {"new-mesh": {"name": "new", "captions": unit(np.tile(np.eye(DIM)[3], (8, 1)))}}
    commit(store_path, new, "20250102T000000000000Z-bbbbbb")
    redo = {"m00007": {"name": "m7", "captions": unit(np.tile(np.eye(DIM)[5], (8, 1)))}}
    commit(store_path, redo, "20250103T000000000000Z-cccccc")  # a --force re-run of one mesh
    with Store.open(store_path) as store:
        rep = sync(store, ds, fp, enc)
        assert (rep.action, rep.added, rep.removed) == ("sync", 16, 8)
        assert rep.manifest["generation"] == gen  # the IVF base was not rewritten
        tables = tables_of(store)
        snap = snapshot(store)
        exact = TextFilter(tables.captions)
        ids = tables.meshes.column("mesh_id").to_pylist()
        for axis, mid in ((3, "new-mesh"), (5, "m00007")):
            q = np.eye(DIM, dtype=np.float32)[axis]
            r = snap.run(q, 0.99, 10)
            assert ids[r.mesh_idx[0]] == mid and r.scores[0] == pytest.approx(1.0, abs=1e-5)
            answers_equal(r, exact.run(q, 0.99, 10))
        for q in queries():
            answers_equal(snap.run(q, 1.5, 10), exact.run(q, 1.5, 10))


def test_removed_mesh_is_not_returned(store_path):
    with Store.open(store_path) as store:
        ds, fp, enc = text_dataset(store, latest_onboarding(store))
        sync(store, ds, fp, enc)
        q = clustered(300)["m00012"]["captions"][0].astype(np.float32)
    commit(store_path, {"m00012": {"name": "m12", "status": "removed"}}, "20250102T000000000000Z-dddddd")
    with Store.open(store_path) as store:
        tables = tables_of(store)
        snap = snapshot(store)
        exact = TextFilter(tables.captions)
        assert "m00012" not in tables.meshes.column("mesh_id").to_pylist()
        answers_equal(snap.run(q, 0.5, 10), exact.run(q, 0.5, 10))
        answers_equal(snap.run(q, 1.5, 10), exact.run(q, 1.5, 10))


def test_compaction_causes_no_churn(store_path):
    from pipeline.compact import compact_dataset

    for k in range(3):  # small files re-embedding meshes m00000..m00002: compaction drops superseded rows
        commit(store_path, clustered(3, seed=10 + k), f"2025010{2 + k}T000000000000Z-eeeee{k}")
    with Store.open(store_path) as store:
        ds, fp, enc = text_dataset(store, latest_onboarding(store))
        before = sync(store, ds, fp, enc).manifest
    with Store.open(store_path, writable=True) as store:
        out = compact_dataset(store, ds, "20250109T000000000000Z-ffffff")
        assert out["files_after"] < out["files_before"]
    with Store.open(store_path) as store:
        rep = sync(store, ds, fp, enc)
        assert (rep.action, rep.added, rep.removed) == ("sync", 0, 0)
        assert rep.manifest["n_slots"] == before["n_slots"]
        assert rep.manifest["files"] != before["files"]
        assert status(store, ds, fp, enc)[0] == "fresh"


def test_damaged_index_falls_back_with_note_and_fsck_reports(store_path):
    from pipeline.fsck import fsck

    with Store.open(store_path) as store:
        ds, fp, enc = text_dataset(store, latest_onboarding(store))
        man = sync(store, ds, fp, enc).manifest
    directory = index_dir(store_path, ds, fp)
    (directory / man["base"]["faiss"]).write_bytes(b"not an index")
    report = fsck(store_path)
    assert any("stage-1 index" in p and "damaged" in p for p in report.problems)
    with Store.open(store_path) as store:
        tables = tables_of(store)
        f = open_stage1(store, tables, "index")  # the open rebuilds a damaged index...
        assert f.engine == "index"
    (directory / read_manifest(directory)["base"]["arrays"]["mesh_code"]).write_bytes(b"junk")
    import pipeline.index.sync as sync_mod

    with Store.open(store_path) as store, pytest.MonkeyPatch.context() as mp:
        mp.setattr(sync_mod, "sync", lambda *a, **k: (_ for _ in ()).throw(OSError("read-only")))
        tables = tables_of(store)
        f = open_stage1(store, tables, "index")  # ...but when it cannot, the exact path answers
        assert f.engine == "exact" and "damaged" in f.notes[0] and "exact path" in f.notes[0]
        exact = TextFilter(tables.captions)
        q = queries(1)[0]
        answers_equal(f.run(q, 0.5, 10), exact.run(q, 0.5, 10))


def test_stale_index_falls_back_and_fsck_notes_it(store_path, monkeypatch):
    from pipeline.fsck import fsck

    with Store.open(store_path) as store:
        ds, fp, enc = text_dataset(store, latest_onboarding(store))
        sync(store, ds, fp, enc)
    commit(
        store_path,
        {"late": {"name": "late", "captions": unit(np.ones((8, DIM)))}},
        "20250102T000000000000Z-gggggg",
    )
    assert any("stage-1 index" in n and "stale" in n for n in fsck(store_path).notes)
    import pipeline.index.sync as sync_mod

    monkeypatch.setattr(sync_mod, "sync", lambda *a, **k: (_ for _ in ()).throw(OSError("read-only")))
    with Store.open(store_path) as store:
        with pytest.raises(IndexUnavailable, match="stale"):
            open_index(store, tables_of(store))
        f = open_stage1(store, tables_of(store), "index")
        assert f.engine == "exact" and "stale" in f.notes[0]


def test_stage1_option_on_retriever_and_cli(store_path):
    from query_helpers import fake_models

    from pipeline.cli_common import OneLineParser, add_read_model_args
    from pipeline.query.api import Retriever
    from pipeline.query.errors import QueryError

    models = fake_models()
    kw = {"models": models, "use_cache": False, "preload": False}
    with Retriever.open(store_path, settings_changes={"stage1": "index"}, **kw) as r:
        assert r.text_filter.engine == "index"
    with Retriever.open(store_path, settings_changes={"stage1": "auto"}, **kw) as r:
        assert r.text_filter.engine == "exact"  # 2,400 rows: far below the auto threshold
    with pytest.raises(QueryError, match="stage-1 mode"):
        Retriever.open(store_path, settings_changes={"stage1": "fast"}, **kw)
    p = OneLineParser()
    add_read_model_args(p)
    assert p.parse_args(["--stage1", "index"]).stage1 == "index"
    with pytest.raises(SystemExit):
        p.parse_args(["--stage1", "fast"])


def test_drift_past_the_bound_retrains(store_path):
    with Store.open(store_path) as store:
        ds, fp, enc = text_dataset(store, latest_onboarding(store))
        gen = sync(store, ds, fp, enc).manifest["generation"]
    rng = np.random.default_rng(5)
    far = {  # captions unlike anything the lists were trained on
        f"far{i}": {
            "name": f"far{i}",
            "captions": unit(rng.standard_normal((8, DIM)) * 0.05 + (i % DIM == 0)),
        }
        for i in range(8)
    }
    commit(store_path, far, "20250102T000000000000Z-hhhhhh")
    with Store.open(store_path) as store:
        rep = sync(store, ds, fp, enc)
        assert rep.action == "retrain" and "drift" in rep.reason
        assert rep.manifest["generation"] == gen + 1 and rep.manifest["drift"]["added_rows"] == 0
        exact = TextFilter(tables_of(store).captions)
        snap = snapshot(store)
        for q in queries(8):
            answers_equal(snap.run(q, 1.5, 10), exact.run(q, 1.5, 10))


def test_retriever_result_carries_the_fallback_note(store_path, monkeypatch):
    from query_helpers import fake_models

    import pipeline.index.sync as sync_mod
    from pipeline.query.api import Retriever
    from pipeline.query.results import QueryEmbedding

    monkeypatch.setattr(sync_mod, "sync", lambda *a, **k: (_ for _ in ()).throw(OSError("read-only")))
    kw = {"models": fake_models(), "use_cache": False, "preload": False}
    with Retriever.open(
        store_path, settings_changes={"stage1": "index", "prompt_weight": 0.0, "verify": False}, **kw
    ) as r:
        assert r.text_filter.engine == "exact"
        emb = QueryEmbedding(queries(1)[0], unit(np.ones(4)).astype(np.float32))
        for mode in ("two-stage", "text-only"):
            out = r.rank(emb, mode=mode, threshold=0.5).to_dict()
            assert out["notes"] and "missing" in out["notes"][0] and "exact path" in out["notes"][0]
            assert out["candidates"]


def _clustered(rng, n_models: int, dim: int, per: int = 8):
    """Caption-like unit rows: topics, models around them, ``per`` captions around each model."""
    topics = rng.standard_normal((max(1, n_models // 20), dim))
    model = topics[rng.integers(len(topics), size=n_models)] + 0.2 * rng.standard_normal((n_models, dim))
    x = np.repeat(model, per, 0) + 0.1 * rng.standard_normal((n_models * per, dim))
    return (x / np.linalg.norm(x, axis=1, keepdims=True)).astype(np.float32), np.repeat(np.arange(n_models), per)


def _calibration_index():
    """(rng, IVF40-SQ8 index over 4,000 clustered 32-d models x 8 captions, rows, mesh codes, live rows, eps)."""
    import faiss

    from pipeline.index import build as b

    rng = np.random.default_rng(0)
    x, mesh_code = _clustered(rng, 4000, 32)
    index = faiss.index_factory(32, "IVF40,SQ8", faiss.METRIC_INNER_PRODUCT)
    index.train(x)
    index.add(x)
    live = np.arange(len(x))
    eps, _ = b.measure_eps(index, x, live, rng)
    return rng, index, x, mesh_code, live, eps


def test_nprobe_is_calibrated_to_the_recall_target():
    """The build probes as many lists as its own sample queries need for the tau-set recall target: the
    steps below the chosen one miss it, and held-out queries see the same recall."""
    from pipeline.index import build as b

    rng, index, x, mesh_code, live, eps = _calibration_index()
    nprobe, rec = b.calibrate_nprobe(index, x, mesh_code, live, rng, eps, 4)
    recall = {int(k): v for k, v in rec["recall"].items()}
    assert rec["queries"] >= 60 and rec["target"] == b.RECALL_TARGET
    assert nprobe > 4 and recall[nprobe] >= b.RECALL_TARGET  # the formula's 4 lists were not enough
    assert all(v < b.RECALL_TARGET for k, v in recall.items() if k < nprobe)
    assert index.nprobe == 1  # the index is left as it was
    # held out: fresh queries, recall measured the same way at the chosen and at the formula's nprobe
    held = np.random.default_rng(1)
    q = b.sample_queries(x, live, held, 200)
    exact = (x @ q.T).reshape(4000, 8, -1).max(1)

    def recall_at(p):
        index.nprobe, found = p, []
        for i in range(len(q)):
            order = np.argsort(-exact[:, i])
            n = int(held.integers(1, 101))
            tau = (exact[order[n - 1], i] + exact[order[n], i]) / 2
            _, _, labels = index.range_search(q[i : i + 1], float(tau - eps))
            found.append(len(set(mesh_code[labels]) & set(order[:n])) / n)
        return float(np.mean(found))

    assert recall_at(nprobe) >= 0.99 > recall_at(4)


def test_calibration_leaves_tiny_indexes_alone():
    import faiss

    from pipeline.index import build as b

    x, mesh_code = _clustered(np.random.default_rng(0), 2, 8)
    index = faiss.index_factory(8, "IVF1,SQ8", faiss.METRIC_INNER_PRODUCT)
    index.train(x)
    index.add(x)
    assert b.calibrate_nprobe(index, x, mesh_code, np.arange(len(x)), np.random.default_rng(0), 0.01, 1)[0] == 1


def test_tau_following_probe_is_calibrated_and_searches_deeper_for_lower_tau():
    """The build's probe depth: every list whose centroid scores >= tau - delta. The smallest ladder step
    reaching the recall target is chosen (smaller ones miss it), held-out queries searched that way keep
    the recall, and a high tau probes fewer lists than a low one."""
    import faiss

    from pipeline.index import build as b
    from pipeline.index.snapshot import probe_lists

    rng, index, x, mesh_code, live, eps = _calibration_index()
    q, cases = b.calibration_cases(x, mesh_code, live, rng)
    probe, rec = b.calibrate_delta(index, x, mesh_code, q, cases, eps)
    assert probe is not None and probe["min_lists"] == b.MIN_LISTS
    recall = {float(k): v for k, v in rec["recall"].items()}
    assert recall[probe["delta"]] >= b.RECALL_TARGET
    assert all(v < b.RECALL_TARGET for k, v in recall.items() if k < probe["delta"])
    assert index.nprobe == 1  # left as it was
    held = np.random.default_rng(1)
    hq = b.sample_queries(x, live, held, 200)
    exact = (x @ hq.T).reshape(4000, 8, -1).max(1)
    centroids = b.centroids_of(index)
    ivf = faiss.extract_index_ivf(index)
    found, lists_at = [], {}
    for i in range(len(hq)):
        order = np.argsort(-exact[:, i])
        n = int(held.integers(1, 101))
        tau = float((exact[order[n - 1], i] + exact[order[n], i]) / 2)
        keys = probe_lists(centroids @ hq[i], tau, probe["delta"], probe["min_lists"])
        index.nprobe = len(keys)
        dis = (centroids[keys] @ hq[i])[None, :].astype(np.float32)
        _, _, labels = ivf.range_search_preassigned(hq[i : i + 1], tau - eps, keys[None, :], dis)
        found.append(len(set(mesh_code[labels]) & set(order[:n])) / n)
        lists_at[n] = len(keys)
    assert np.mean(found) >= 0.99
    few, many = min(lists_at), max(lists_at)
    assert lists_at[few] < lists_at[many]  # the 1-model tau-set searches fewer lists than the 100-model one


def test_snapshot_follows_tau_and_answers_exactly_when_every_list_is_reached(store_path):
    """The snapshot's tau search probes the lists the calibrated depth names: all of them when delta
    covers every centroid (then the answers are the exact path's), only the best ``min_lists`` when it
    covers none."""
    from pipeline.index.build import DELTA_LADDER

    with Store.open(store_path) as store:
        ds, fp, enc = text_dataset(store, latest_onboarding(store))
        man = sync(store, ds, fp, enc).manifest
        assert man["probe"]["delta"] in DELTA_LADDER and man["probe_calibration"]["queries"] > 0
        snap = snapshot(store, exhaustive=False)
        exact = TextFilter(tables_of(store).captions)
        nlist = snap.index.nlist
        for q in queries():
            tau = 0.6
            snap.probe_delta = 10.0
            assert len(snap.probed_lists(q, tau)[0]) == nlist
            answers_equal(snap.run(q, tau, 10, "meshes"), exact.run(q, tau, 10, "meshes"))
            snap.probe_delta = -10.0
            keys, dis = snap.probed_lists(q, tau)
            assert len(keys) == snap.min_lists and np.all(np.diff(dis) <= 0)


def test_fallback_through_the_tau_following_probe_finds_the_exact_top_k(store_path):
    """No tau (or nothing passes): the k-NN candidates come from a tau search at the k-th best coded score
    of the query's best lists minus eps; with every list reachable the answers are the exact path's, and
    with the calibrated depth the best model agrees on every fixture query."""
    with Store.open(store_path) as store:
        ds, fp, enc = text_dataset(store, latest_onboarding(store))
        sync(store, ds, fp, enc)
        snap = snapshot(store, exhaustive=False)
        exact = TextFilter(tables_of(store).captions)
        calibrated = snap.probe_delta
        for q in queries():
            for unit in ("captions", "meshes"):
                want = exact.run(q, None, 10, unit)
                snap.probe_delta = 10.0
                assert snap._knn_by_probe(snap.query_scores(q), 8 * 10 + 64) is not None  # the probe path
                answers_equal(snap.run(q, None, 10, unit), want)
                answers_equal(snap.run(q, 2.0, 10, unit), want)  # tau above every score: the fallback
                snap.probe_delta = calibrated
                assert snap.run(q, None, 10, unit).mesh_idx[0] == want.mesh_idx[0]


def near_copies(first: int, n: int, seed: int) -> dict[str, dict]:
    """``n`` new meshes whose captions are noisy copies of the fixture's (no drift: the lists still fit)."""
    rng = np.random.default_rng(seed)
    src = list(clustered(300).values())
    return {
        f"f{first + i:05d}": {
            "name": f"f{first + i}",
            "captions": unit(src[i]["captions"] + 0.05 * rng.standard_normal((8, DIM))),
        }
        for i in range(n)
    }


def test_large_delta_folds_into_the_base_and_later_commits_find_its_meshes(store_path):
    with Store.open(store_path) as store:
        ds, fp, enc = text_dataset(store, latest_onboarding(store))
        gen = sync(store, ds, fp, enc).manifest["generation"]
    commit(store_path, near_copies(0, 60, 1), "20250102T000000000000Z-iiiiii")
    with Store.open(store_path) as store:
        rep = sync(store, ds, fp, enc)
        assert (rep.action, rep.added) == ("sync", 480) and len(rep.manifest["delta"]["meshes"]) == 60
    commit(store_path, near_copies(60, 70, 2), "20250103T000000000000Z-jjjjjj")
    with Store.open(store_path) as store:
        rep = sync(store, ds, fp, enc)
        assert rep.action == "fold", rep.reason
        man = rep.manifest
        assert man["generation"] == gen + 1 and man["delta"]["rows"] == 0 and man["delta"]["meshes"] == []
        assert man["base"]["n_meshes"] == 430 and man["base"]["n_slots"] == 3440
    # a --force re-run of a mesh that reached the base through the delta replaces its slots
    redo = {"f00005": {"name": "f5", "captions": unit(np.tile(np.eye(DIM)[7], (8, 1)))}}
    commit(store_path, redo, "20250104T000000000000Z-kkkkkk")
    with Store.open(store_path) as store:
        rep = sync(store, ds, fp, enc)
        assert (rep.action, rep.added, rep.removed) == ("sync", 8, 8)
        assert rep.manifest["delta"]["meshes"] == []  # f00005 was found in the base, not added again
        tables = tables_of(store)
        snap, exact = snapshot(store), TextFilter(tables.captions)
        ids = tables.meshes.column("mesh_id").to_pylist()
        r = snap.run(np.eye(DIM, dtype=np.float32)[7], 0.99, 10)
        assert ids[r.mesh_idx[0]] == "f00005"
        for q in queries(12):
            answers_equal(snap.run(q, 1.5, 10), exact.run(q, 1.5, 10))
            answers_equal(snap.run(q, 0.6, 10), exact.run(q, 0.6, 10))


def test_index_of_an_older_format_is_reported_and_rebuilt(store_path):
    import json

    with Store.open(store_path) as store:
        ds, fp, enc = text_dataset(store, latest_onboarding(store))
        sync(store, ds, fp, enc)
    path = index_dir(store_path, ds, fp) / "manifest.json"
    path.write_text(json.dumps({**json.loads(path.read_text()), "format": 1}))
    with Store.open(store_path) as store:
        state, detail = status(store, ds, fp, enc)
        assert state == "damaged" and "format 1" in detail and "reads 2" in detail
        rep = sync(store, ds, fp, enc)
        assert rep.action == "build" and "damaged manifest" in rep.reason
        assert status(store, ds, fp, enc)[0] == "fresh"


@pytest.mark.parametrize("bisect", [True, False])
def test_mesh_lookup_finds_base_ids_and_numbers_new_ones(monkeypatch, bisect):
    import pipeline.index.lookup as lookup

    monkeypatch.setattr(lookup, "BISECT_MAX", 10_000 if bisect else 0)
    base = pa.array(["m-b", "ä-unicode", "m-a", "", "m-c/é", "z"], pa.string())
    look = lookup.MeshLookup(base, lookup.sorted_order(base), ["d-new"])
    ids = pa.array(["m-a", "x-unseen", "d-new", "", "z", "x-unseen", "ä-unicode", "m-c/é", "y"])
    assert look.codes(ids).tolist() == [2, 7, 6, 3, 5, 7, 1, 4, 8]
    assert look.new == ["d-new", "x-unseen", "y"]
    assert look.base_codes(pa.array(["m-b", "nope", "m-c"])).tolist() == [0, -1, -1]
    assert look.codes(pa.array([], pa.string())).tolist() == []


def test_live_slots_prefers_an_alive_base_slot_then_the_latest_alive_delta_slot():
    from pipeline.index.sync import live_slots

    base_keys = np.array([30, 10, 20, 10, 40], np.int64)  # slots 0..4; key 10 twice (slot 1 dead)
    key_order = np.argsort(base_keys, kind="stable")
    d_keys = np.array([40, 50, 50, 60, 50], np.int64)  # slots 5..9
    d_order = np.argsort(d_keys, kind="stable")
    alive = np.ones(10, bool)
    alive[[1, 4, 8, 9]] = False  # key 40's base slot died (replaced in the delta); 50's latest is dead
    got = live_slots(
        np.array([10, 20, 40, 50, 60, 70, 30], np.int64),
        base_keys[key_order], key_order, d_keys[d_order], d_order, alive, 5,
    )
    assert got.tolist() == [3, 2, 5, 7, -1, -1, 0]


def test_rows_whose_file_left_the_table_die_and_a_resurfaced_older_row_rebuilds(store_path):
    from deltalake import DeltaTable

    with Store.open(store_path) as store:
        ds, fp, enc = text_dataset(store, latest_onboarding(store))
        sync(store, ds, fp, enc)
        v0 = store.version(ds)
    commit(store_path, {"gone-mesh": {"name": "gone", "captions": unit(np.tile(np.eye(DIM)[2], (8, 1)))}},
           "20250102T000000000000Z-llllll")
    with Store.open(store_path) as store:
        assert sync(store, ds, fp, enc).added == 8
    DeltaTable(str(store_path / ds)).restore(v0)  # the new mesh's file leaves the table
    with Store.open(store_path) as store:
        rep = sync(store, ds, fp, enc)
        assert (rep.action, rep.added, rep.removed) == ("sync", 0, 8)
        q = np.eye(DIM, dtype=np.float32)[2]
        answers_equal(snapshot(store).run(q, 0.9, 10), TextFilter(tables_of(store).captions).run(q, 0.9, 10))
        v1 = store.version(ds)
    redo = {"m00007": {"name": "m7", "captions": unit(np.tile(np.eye(DIM)[5], (8, 1)))}}
    commit(store_path, redo, "20250103T000000000000Z-mmmmmm")  # a --force re-run replaces m00007's slots
    with Store.open(store_path) as store:
        assert (sync(store, ds, fp, enc).removed) == 8
    DeltaTable(str(store_path / ds)).restore(v1)  # the re-run leaves: m00007's first run is latest again
    with Store.open(store_path) as store:
        rep = sync(store, ds, fp, enc)
        assert rep.action == "rebuild" and "older row" in rep.reason
        snap, exact = snapshot(store), TextFilter(tables_of(store).captions)
        for q in queries(8):
            answers_equal(snap.run(q, 1.5, 10), exact.run(q, 1.5, 10))


def test_a_failed_build_leaves_no_partial_file_and_the_old_index_serves(store_path, monkeypatch):
    import errno

    import pipeline.index.build as b

    with Store.open(store_path) as store:
        ds, fp, enc = text_dataset(store, latest_onboarding(store))
        sync(store, ds, fp, enc)
    directory = index_dir(store_path, ds, fp)
    real = b.vectors_of

    def full_disk(t):
        if len(list(directory.glob("*.partial"))):  # the new vector file is being written
            raise OSError(errno.ENOSPC, "No space left on device")
        return real(t)

    monkeypatch.setattr(b, "vectors_of", full_disk)
    with Store.open(store_path) as store:
        with pytest.raises(OSError, match="No space"):
            sync(store, ds, fp, enc, rebuild=True)
        assert not list(directory.glob("*.partial"))
        assert status(store, ds, fp, enc)[0] == "fresh"  # the manifest still names the old, whole files
        q = queries(1)[0]
        answers_equal(snapshot(store).run(q, 0.5, 10), TextFilter(tables_of(store).captions).run(q, 0.5, 10))


def test_a_build_first_removes_what_a_killed_writer_left(store_path):
    with Store.open(store_path) as store:
        ds, fp, enc = text_dataset(store, latest_onboarding(store))
        sync(store, ds, fp, enc)
    directory = index_dir(store_path, ds, fp)
    left = [directory / "vectors-000009.f32.partial", directory / "base-000009.faiss"]
    for p in left:
        p.write_bytes(b"x" * 1024)
    seen = {}
    import pipeline.index.build as b

    real = b.stream_rows

    def watch(*a, **k):  # while the new build streams its rows, the leftovers must already be gone
        seen["left"] = [p.name for p in left if p.exists()]
        yield from real(*a, **k)

    with Store.open(store_path) as store, pytest.MonkeyPatch.context() as mp:
        mp.setattr(b, "stream_rows", watch)
        assert sync(store, ds, fp, enc, rebuild=True).action == "build"
        assert seen["left"] == [] and not any(p.exists() for p in left)
        assert status(store, ds, fp, enc)[0] == "fresh"
