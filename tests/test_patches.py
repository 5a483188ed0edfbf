"""Patch agreement of the open-set verdict (pipeline.query.patches): object cells, the two features, the
per-view token cache, the runner-up lead, and the verdict's features on a real store."""

from __future__ import annotations

import io
import threading

import numpy as np
import pytest
from PIL import Image

from pipeline.query.accept import FEATURES
from pipeline.query.patches import (
    ALL_VIEWS,
    LEAD_FEATURES,
    PATCH_FEATURES,
    VIEWS,
    PatchMatcher,
    object_cells,
    patch_agreement,
    runner_up_lead,
    top_views,
    union_agreement,
)

GRAY = (205, 205, 205)


def _unit(x: np.ndarray) -> np.ndarray:
    return x / np.linalg.norm(x, axis=1, keepdims=True)


def test_object_cells_mark_the_patches_off_the_background():
    im = Image.new("RGB", (56, 56), GRAY)
    im.paste((200, 30, 30), (0, 0, 28, 28))  # four 14 px cells in the top-left corner
    im.paste((30, 30, 200), (42, 42, 56, 56))
    im.paste((30, 200, 30), (14, 28, 17, 31))  # 9 of a cell's 196 pixels: not the object's
    cells = object_cells(im, GRAY, 4)
    assert cells.shape == (16,)
    assert sorted(np.flatnonzero(cells)) == [0, 1, 4, 5, 15]
    # a faint difference (within the tolerance) is background; fewer than 4 object cells: all of them
    faint = Image.new("RGB", (56, 56), tuple(c + 5 for c in GRAY))
    assert object_cells(faint, GRAY, 4).all()


def test_patch_agreement_reads_part_by_part_likeness():
    rng = np.random.default_rng(0)
    parts = _unit(rng.normal(size=(6, 32)))
    same = patch_agreement(parts, parts[::-1])
    assert abs(same["patch_cover"] - 1.0) < 1e-6 and abs(same["patch_sim"] - 1.0) < 1e-6
    assert same["patch_mnn"] == 1.0 and abs(same["patch_low"] - 1.0) < 1e-6
    half = patch_agreement(parts, parts[:3])  # the view has a counterpart for half of the ROI's parts
    assert half["patch_cover"] < 0.8 and half["patch_sim"] > half["patch_cover"]  # all of the view's parts match
    assert half["patch_mnn"] == 0.5  # one to one: the three shared parts, not the other three
    assert half["patch_low"] < 0.5 < half["patch_cover"]  # the unmatched parts, which the mean dilutes
    other = patch_agreement(parts, _unit(rng.normal(size=(6, 32))))
    assert other["patch_cover"] < half["patch_cover"] and other["patch_low"] < half["patch_cover"]
    assert patch_agreement(None, parts) == dict.fromkeys(PATCH_FEATURES)
    assert patch_agreement(parts, parts[:0]) == dict.fromkeys(PATCH_FEATURES)
    assert set(PATCH_FEATURES) <= set(FEATURES)


def test_top_views_are_the_best_scored_views_that_exist():
    ids = np.array([0, 1, 2, 3, -1])
    scores = np.array([0.2, 0.9, -np.inf, 0.5, 0.99], np.float32)
    assert top_views(ids, scores, 2) == [1, 3]
    assert top_views(ids, scores, 9) == [1, 3, 0]
    assert top_views(ids[:0], scores[:0], 2) == []


class _Encoder:
    def __init__(self):
        self.calls = 0
        self.batches = []

    def object_patches_batch(self, images):
        self.calls += 1
        self.batches.append(len(images))
        return [_unit(np.asarray(im, np.float32).reshape(-1, 3)[:4] + 1.0).astype(np.float16) for im in images]


def _png(colour) -> bytes:
    buf = io.BytesIO()
    Image.new("RGB", (8, 8), colour).save(buf, "PNG")
    return buf.getvalue()


def test_matcher_encodes_each_view_once_and_bounds_its_cache():
    enc = _Encoder()
    asked = []

    def view_images(mesh_id, view_indices):
        asked.append((mesh_id, list(view_indices)))
        return {} if mesh_id == "none" else {v: _png((v * 20, 10, 10)) for v in view_indices}

    m = PatchMatcher(view_images, lambda: enc, cache_views=3)
    roi = _unit(np.ones((3, 3), np.float32))
    a = m.features(roi, "m1", [0])
    assert a["patch_cover"] is not None and m.features(roi, "m1", [0]) == a
    assert enc.calls == 1 and asked == [("m1", [0])]
    both = m.features(roi, "m1", [1, 0])  # view 0 cached, view 1 encoded: one batch of one
    assert enc.batches == [1, 1] and both["patch_cover"] >= a["patch_cover"]
    one = m.features(roi, "m1", [1])
    assert both == {k: max(a[k], one[k]) for k in PATCH_FEATURES}  # each feature its best view
    m.features(roi, "m1", [2, 3])  # one batch of two; the cache (3 views) drops the oldest, view 0
    assert enc.batches[-1] == 2 and asked[-1] == ("m1", [2, 3])  # one store read for both
    m.features(roi, "m1", [0])
    assert enc.calls == 4
    assert m.features(roi, "none", [0]) == dict.fromkeys(PATCH_FEATURES)  # a view without an image
    assert m.features(roi, "m1", []) == dict.fromkeys(PATCH_FEATURES)  # a mesh without views
    assert m.features(None, "m1", [0]) == dict.fromkeys(PATCH_FEATURES)  # an ROI without tokens
    # concurrent callers get the same answer
    out = []
    threads = [threading.Thread(target=lambda: out.append(m.features(roi, "m2", [3, 4]))) for _ in range(8)]
    for t in threads:
        t.start()
    for t in threads:
        t.join()
    assert len(out) == 8 and all(o == out[0] for o in out)


def test_matcher_reads_stored_tokens_before_encoding():
    """Tokens onboarding stored are read for the views that have them (one read per model, cached); only
    the others are read as PNGs and encoded, in one batch; a store without any encodes every view."""
    enc, asked, read = _Encoder(), [], []
    stored_tokens = {v: _unit(np.full((2, 3), v + 1.0, np.float32)).astype(np.float16) for v in (0, 1)}

    def stored(mesh_id, view_indices):
        read.append((mesh_id, list(view_indices)))
        return {v: stored_tokens[v] for v in view_indices if v in stored_tokens and mesh_id == "m1"}

    def view_images(mesh_id, view_indices):
        asked.append((mesh_id, list(view_indices)))
        return {v: _png((v * 20, 10, 10)) for v in view_indices}

    m = PatchMatcher(view_images, lambda: enc, stored=stored)
    roi = _unit(np.ones((3, 3), np.float32))
    got = m.view_tokens("m1", [1, 0])
    assert all(g is stored_tokens[v] for g, v in zip(got, [1, 0], strict=True))
    assert enc.calls == 0 and asked == [] and read == [("m1", [1, 0])]
    m.view_tokens("m1", [0, 1, 2])  # views 0 and 1 cached; view 2 has no stored tokens: encoded
    assert read[-1] == ("m1", [2]) and asked == [("m1", [2])] and enc.batches == [1]
    both = m.features(roi, "m1", [0, 1])
    want = {k: max(patch_agreement(roi, stored_tokens[v])[k] for v in (0, 1)) for k in PATCH_FEATURES}
    assert both == want
    m.features(roi, "m2", [0, 1])  # a model without stored tokens: encoded from its PNGs
    assert asked[-1] == ("m2", [0, 1]) and enc.batches[-1] == 2


def test_onboarding_stores_the_views_patch_tokens(tmp_path, offline_models, monkeypatch):
    """The ``patches`` stage stores every view's object patch tokens as the query would encode them, from
    the forward pass that embeds the views (no second encoder pass); the query reads them instead of
    encoding the top-1's views, with the same verdict features. A store that lost the table gets it back on
    the next run, by encoding the views, with no other stage redone."""
    import shutil

    from onboard_helpers import count, onboard

    from pipeline.mesh.settings import RenderConfig
    from pipeline.onboard.stages.patches import PatchStage
    from pipeline.query import Retriever
    from pipeline.query.patches import tokens_of
    from pipeline.store import Store

    enc = offline_models["learned_encoder"]
    passes = []
    real = type(enc).object_patches_batch

    def spy(self, images):
        passes.append(len(images))
        return real(self, images)

    monkeypatch.setattr(type(enc), "object_patches_batch", spy)
    store, img, mask = _three_model_store(tmp_path, offline_models)
    assert passes == []  # the tokens came from the embedding pass
    s = Store.open(store)
    rows = s.read_latest("view_patches").to_pylist()
    views = {(v["mesh_id"], v["view_index"]): v["image"] for v in s.read_latest("views").to_pylist()}
    assert len(rows) == len(views) > 0
    for row in rows[:4]:
        with Image.open(io.BytesIO(views[(row["mesh_id"], row["view_index"])])) as im:
            want = real(enc, [im.convert("RGB")])[0]
        got = tokens_of(row["tokens"], row["n_patches"], row["dim"])
        assert got.shape == want.shape and row["dim"] == 384
        assert np.abs(got.astype(np.float32) - want.astype(np.float32)).max() <= 1e-2
    with Retriever.open(store, profile="offline", models=offline_models) as r:
        r.ranking.patches.always = True
        monkeypatch.setattr(r.ranking.patches, "_view_images", lambda *a: pytest.fail("encoded a stored view"))
        from_store = r.query(img, "the mustard bottle", mask=mask)
    with Retriever.open(store, profile="offline", models=offline_models) as r:
        r.ranking.patches.always = True
        r.ranking.patches._stored = None  # noqa: SLF001 - as a store without the stage
        encoded = r.query(img, "the mustard bottle", mask=mask)
    assert [c.mesh_id for c in from_store.candidates] == [c.mesh_id for c in encoded.candidates]
    for k in PATCH_FEATURES + LEAD_FEATURES:
        assert from_store.verdict.features[k] == pytest.approx(encoded.verdict.features[k], abs=2e-3), k
    assert from_store.accepted == encoded.accepted

    def missing():  # the analysts' audit of what the current config's stages should have written
        from pipeline.db import connect
        from pipeline.sql.session import run_audit

        with Store.open(store) as st:
            columns, found = run_audit(connect(st), "missing_outputs")
        return sorted({dict(zip(columns, r, strict=True))["stage"] for r in found})

    assert missing() == []
    shutil.rmtree(store / "view_patches")  # a store from before the stage, or one whose table was lost
    assert missing() == ["patches"]
    with Retriever.open(store, profile="offline", models=offline_models) as r:  # the query encodes instead
        r.ranking.patches.always = True
        assert r.tables.view_patches(from_store.candidates[0].mesh_id, [0, 1]) == {}
        before = len(passes)
        fallback = r.query(img, "the mustard bottle", mask=mask)
        assert len(passes) > before and fallback.verdict.features == encoded.verdict.features
    n, calls, real_call = len(passes), [], PatchStage.__call__
    monkeypatch.setattr(PatchStage, "__call__", lambda self, t: (calls.append(t.num_rows), real_call(self, t))[1])
    onboard(tmp_path / "lib", store, models=offline_models, render=RenderConfig(resolution=192))
    assert sum(calls) == len(views) and sum(passes[n:]) == len(views)  # every view encoded here, once
    assert count(store, "view_patches") == len(views)
    assert count(store, "views") == len(views)  # nothing else redone
    assert missing() == []


def test_stored_tokens_survive_compaction_under_an_open_retriever(tmp_path, offline_models, monkeypatch, capsys):
    """``compact --retention-hours 0`` while a Retriever holds its snapshot: the query still reads the top-1's
    stored tokens (no encoder pass) from the leased files, and the compacted table keeps one model per
    Parquet row group (pipeline.store.BLOB_TABLES)."""
    import pyarrow.parquet as pq
    from onboard_helpers import onboard

    from pipeline import compact
    from pipeline.mesh.settings import RenderConfig
    from pipeline.query import Retriever
    from pipeline.store import Store

    store, img, mask = _three_model_store(tmp_path, offline_models)
    onboard(tmp_path / "lib", store, models=offline_models, render=RenderConfig(resolution=192), force=("patches",))
    assert len(Store.open(store).files("view_patches")) == 2  # two files to merge
    with Retriever.open(store, profile="offline", models=offline_models) as r:
        r.ranking.patches.always = True
        monkeypatch.setattr(r.ranking.patches, "_view_images", lambda *a: pytest.fail("encoded a stored view"))
        assert compact.main([str(store), "--retention-hours", "0"]) == 0
        assert "kept for live readers" in capsys.readouterr().out
        res = r.query(img, "the mustard bottle", mask=mask)
        assert res.verdict.features["patch_sim"] is not None and res.verdict.features["patch_second"] is not None
    (path, _), = Store.open(store).files("view_patches")
    f = pq.ParquetFile(path)
    ids = [f.read_row_group(g, columns=["mesh_id"]).column(0).to_pylist() for g in range(f.num_row_groups)]
    assert f.num_row_groups == 3 and all(len(set(g)) == 1 for g in ids)  # one model (8 views) per row group


def test_the_verdict_reads_the_top1_best_view_of_a_real_store(tmp_path, offline_models):
    """Onboarded with the offline models: a masked query's verdict carries the patch agreement of its ROI
    with the top-1's two best views by the learned cosine, computed from the stored PNGs, when asked for
    (``always``, as the open-set evaluation sets it) and then also in the open-set split; a calibration that
    reads no patch feature costs no encoder pass."""
    from pipeline.evaluate.openset_split import without_meshes
    from pipeline.query import Retriever

    store, img, mask = _three_model_store(tmp_path, offline_models)
    with Retriever.open(store, profile="offline", models=offline_models) as r:
        roi = r.make_roi(img, "the mustard bottle", mask=mask)
        emb = r.embed(roi, "the mustard bottle")
        assert emb.learned_patches is not None and emb.learned_patches.dtype == np.float16
        plain = r.rank(emb, top=3)
        model = r.ranking.calibration.variants.get(plain.verdict.variant)
        if not r.ranking.patches.wanted(model):  # the shipped calibration does not read them: not computed
            assert "patch_cover" not in plain.verdict.features and "patches_ms" not in plain.timings
        r.ranking.patches.always = True
        res = r.rank(emb, top=3)
        best = res.candidates[0]
        enc = r.model("learned_encoder")

        def direct(mesh_id):  # a model's best views by the learned cosine, and each one's patch agreement
            mesh = r.ranking.mesh_id.index(mesh_id)
            s = r.learned.score(emb.learned, np.array([mesh]), per_view=True)
            views = top_views(s.view_ids[0], s.view_scores[0], VIEWS)
            each = []
            for v in views:
                with Image.open(io.BytesIO(r.tables.view_images(mesh_id, [v])[v])) as view:
                    each.append(patch_agreement(emb.learned_patches, enc.object_patches(view.convert("RGB"))))
            return views, each

        views, each = direct(best.mesh_id)
        assert len(views) == VIEWS == 2
        want = {k: max(e[k] for e in each) for k in PATCH_FEATURES}
        got = {k: res.verdict.features[k] for k in PATCH_FEATURES}
        assert got == pytest.approx({k: round(v, 6) for k, v in want.items()}, abs=1e-6)
        assert 0.0 < got["patch_cover"] <= 1.0 and "patches_ms" in res.timings
        sims = [e["patch_sim"] for e in direct(res.candidates[1].mesh_id)[1]]  # the runner-up's own best views
        assert res.verdict.features["patch_second"] == pytest.approx(round(max(sims), 6), abs=1e-6)
        lead = res.verdict.features["patch_lead"]
        assert lead == pytest.approx(round(want["patch_sim"] - max(sims), 6), abs=1e-6)
        mesh = r.ranking.mesh_id.index(best.mesh_id)  # the ROI against every view of the top-1 at once
        s_all = r.learned.score(emb.learned, np.array([mesh]), per_view=True)
        every = top_views(s_all.view_ids[0], s_all.view_scores[0], 1024)
        pngs = r.tables.view_images(best.mesh_id, every)
        tokens = []
        for v in every:
            with Image.open(io.BytesIO(pngs[v])) as view:
                tokens.append(enc.object_patches(view.convert("RGB")))
        union = union_agreement(emb.learned_patches, tokens, want["patch_cover"])
        assert len(every) > VIEWS and union["patch_gain"] >= -1e-6
        for k, v in union.items():
            assert res.verdict.features[k] == pytest.approx(round(v, 6), abs=2e-6), k
        assert r.tables.view_images(best.mesh_id, [999]) == {}
        assert sorted(r.tables.view_images(best.mesh_id, views)) == sorted(views)
        sub = without_meshes(r, [best.mesh_id])  # the split answers from its own top-1, with the same cache
        assert sub.ranking.patches is r.ranking.patches
        other = sub.rank(emb, top=3)
        assert other.candidates[0].mesh_id != best.mesh_id
        assert other.verdict.features["patch_cover"] is not None


def test_patch_features_only_when_the_calibration_reads_them():
    """The encoder pass for the top-1's views runs only for a calibration that reads a patch feature (the
    shipped default ranking's does), or always when the open-set evaluation asks for every feature."""
    from pipeline.query.accept import AcceptModel, load_calibration

    def model(*features):
        n = len(features)
        return AcceptModel(features, (0.0,) * n, (1.0,) * n, (1.0,) * n, 0.0, 0.5)

    m = PatchMatcher(lambda mesh_id, views: {}, lambda: None)
    assert not m.wanted(None) and not m.wanted(model("score", "score_z"))
    assert m.wanted(model("score", "patch_sim")) and m.wanted(model("patch_cover"))
    assert not m.wanted_runner_up(model("score", "patch_sim")) and not m.wanted_runner_up(None)
    assert m.wanted(model("patch_lead")) and m.wanted_runner_up(model("score", "patch_lead"))
    assert m.wanted_runner_up(model("patch_second"))
    assert m.wanted(model("score", "patch_gain")) and m.wanted_union(model("patch_gain"))
    assert not m.wanted_union(model("score", "patch_sim")) and m.wanted_union(model("patch_union"))
    assert m.views_read(model("patch_sim")) == VIEWS and m.views_read(model("patch_gain")) == ALL_VIEWS
    m.always = True
    assert m.wanted(None) and m.wanted(model("score")) and m.wanted_runner_up(None)
    shipped = load_calibration("offline").variants["two-stage+verify"]  # since docs/results.md 12.4
    assert {"patch_sim", "patch_gain"} <= set(shipped.features)
    assert PatchMatcher(lambda *a: {}, lambda: None).views_read(shipped) == ALL_VIEWS


def test_union_agreement_gains_where_parts_match_from_different_views():
    """``patch_union`` takes each ROI patch's best match over every view; ``patch_gain`` is what that adds
    over the best single view's cover: nothing when one view explains every part, much when each part is
    explained by another view."""
    roi = np.eye(4, dtype=np.float32)  # four parts
    whole = roi.copy()  # one view shows all four
    halves = [roi[:2], roi[2:]]  # two views, two parts each
    one = patch_agreement(roi, whole)["patch_cover"]
    assert union_agreement(roi, [whole, None], one) == pytest.approx({"patch_union": 1.0, "patch_gain": 0.0})
    best = max(patch_agreement(roi, h)["patch_cover"] for h in halves)
    got = union_agreement(roi, halves, best)
    assert got["patch_union"] == pytest.approx(1.0) and got["patch_gain"] == pytest.approx(0.5)
    assert union_agreement(roi, halves, None)["patch_gain"] is None
    assert union_agreement(None, halves, 0.5) == dict.fromkeys(("patch_union", "patch_gain"))
    assert union_agreement(roi, [None], 0.5) == dict.fromkeys(("patch_union", "patch_gain"))


def test_runner_up_lead():
    """The runner-up's patch_sim and the top-1's lead over it (negative when the runner-up matches better);
    ``None`` where either side has no patch agreement."""
    top = {"patch_sim": 0.8, "patch_cover": 0.7}
    assert runner_up_lead(top, {"patch_sim": 0.6}) == pytest.approx({"patch_second": 0.6, "patch_lead": 0.2})
    assert runner_up_lead({"patch_sim": 0.5}, {"patch_sim": 0.6})["patch_lead"] == pytest.approx(-0.1)
    assert runner_up_lead(top, dict.fromkeys(PATCH_FEATURES)) == {"patch_second": None, "patch_lead": None}
    assert runner_up_lead(dict.fromkeys(PATCH_FEATURES), {"patch_sim": 0.6}) == {
        "patch_second": 0.6,
        "patch_lead": None,
    }
    assert set(LEAD_FEATURES) <= set(FEATURES)


def test_patch_pass_starts_beside_verification(tmp_path, offline_models, monkeypatch):
    """With a free side thread, the encoder pass over the pre-verification top-1's views starts before
    verification (steps/patch_prefetch.py); the verdict's features are those of the pass run in place, and
    when verification keeps that top-1 its views are encoded once. Without a free thread nothing starts."""
    import pipeline.query.overlap as overlap
    from pipeline.query import Retriever
    from pipeline.query.steps import patch_prefetch

    store, img, mask = _three_model_store(tmp_path, offline_models)
    with Retriever.open(store, profile="offline", models=offline_models) as r:
        r.ranking.patches.always = True
        roi = r.make_roi(img, "the mustard bottle", mask=mask)
        emb = r.embed(roi, "the mustard bottle")
        assert emb.local is not None
        monkeypatch.setattr(overlap, "overlapping", lambda: False)
        monkeypatch.setattr(patch_prefetch, "overlapping", lambda: False)
        in_place = r.rank(emb, top=3)
        r.ranking.patches.clear()

        started, reads = [], []
        real_run, real_read = patch_prefetch.run, r.ranking.patches._stored  # noqa: SLF001

        def spy_run(state):
            state = real_run(state)
            early = state.patch_prefetch
            mesh = None if early is None else state.ctx.mesh_id[int(state.mesh_idx[early[0]])]
            started.append((early, mesh))
            return state

        def spy_read(mesh_id, views):  # the matcher reads a model's stored tokens only where it has none cached
            reads.append(mesh_id)
            return real_read(mesh_id, views)

        monkeypatch.setattr(r.ranking.patches, "_stored", spy_read)
        assert overlap.beside_if_free(lambda: 1) is None  # no free side thread: nothing starts
        monkeypatch.setattr(overlap, "overlapping", lambda: True)
        monkeypatch.setattr(patch_prefetch, "overlapping", lambda: True)
        import pipeline.query.steps as steps

        lists = {
            k: tuple(type(s)(spy_run, s.options) if s.run is real_run else s for s in v)
            for k, v in steps.STEP_LISTS.items()
        }
        monkeypatch.setattr(steps, "STEP_LISTS", lists)
        early = r.rank(emb, top=3)
        (future, mesh), = started
        assert future is not None and future[1].done()
        assert early.verdict.features == in_place.verdict.features
        assert [c.mesh_id for c in early.candidates] == [c.mesh_id for c in in_place.candidates]
        # the early pass read the pre-verification top-1's view tokens, every view of it (the union
        # features, as `always` asks), once: the verdict's best two and its union found them cached
        assert reads.count(mesh) == 1 and reads[0] == mesh


def _three_model_store(tmp_path, offline_models):
    """A store of three sample models onboarded with the offline models, and a masked render of the
    mustard bottle to ask it (image, mask)."""
    import shutil

    from conftest import SAMPLE_LIBRARY
    from onboard_helpers import onboard
    from query_helpers import render_query_view

    from pipeline.mesh.settings import RenderConfig

    lib = tmp_path / "lib"
    for n in ("005_tomato_soup_can", "006_mustard_bottle", "011_banana"):
        shutil.copytree(SAMPLE_LIBRARY / n, lib / n)
    store = tmp_path / "store"
    onboard(lib, store, models=offline_models, render=RenderConfig(resolution=192))
    img, mask = render_query_view(next((lib / "006_mustard_bottle").rglob("*.obj")))
    return store, img, mask
