"""Open-set answers end to end on hand-made stores: ``accepted`` / ``confidence`` in the Python API, the JSON,
the batch JSONL, the CLI and the service; the open-set split (a store's tables without some meshes) is the
same as a store onboarded without them."""

from __future__ import annotations

import io
import json

import numpy as np
import pytest
from PIL import Image
from query_helpers import FAKE_LIBRARY, fake_models, make_fake_store, object_image

from pipeline.evaluate.openset_split import without_meshes
from pipeline.query import QueryError, Retriever
from pipeline.query.accept import AcceptModel, Calibration
from pipeline.query.batch import run_batch
from pipeline.query.output import format_result

VARIANTS = ("two-stage", "image-only", "text-only")


def write_calibration(path, cut: float = 0.95):
    """P(right) > 0.5 exactly when the top-1 score exceeds ``cut`` (a steep logistic on the score)."""
    m = AcceptModel(("score",), (0.0,), (1.0,), (200.0,), -200.0 * cut, threshold=0.5)
    keys = {r: (s.key() if s else None) for r, s in _offline_roles().items()}
    keys["learned_encoder"] = None  # the fake stores hold no learned embeddings: queries do not fuse
    return Calibration("offline", keys, dict.fromkeys(VARIANTS, m)).write(path)


def _offline_roles():
    from pipeline.profiles import get_profile

    return get_profile("offline").roles()


@pytest.fixture(scope="module")
def stores(tmp_path_factory):
    root = tmp_path_factory.mktemp("openset")
    full = make_fake_store(root / "full")
    lib = {k: v for k, v in FAKE_LIBRARY.items() if k not in ("red_can", "blue_box")}
    return full, make_fake_store(root / "without", lib), root


@pytest.fixture(scope="module")
def calibration(stores):
    return write_calibration(stores[2] / "calibration.json")


def red_can():
    img = object_image("red", 44, 52, pad=30)
    return img, np.abs(np.asarray(img, np.int16) - 205).sum(axis=2) > 30


def open_retriever(store, calibration, **changes):
    changes = {"accept_model": str(calibration), **changes}
    return Retriever.open(store, models=fake_models(), use_cache=False, settings_changes=changes)


def test_api_and_json_carry_accepted_and_confidence(stores, calibration):
    full, without, _ = stores
    img, mask = red_can()
    with open_retriever(full, calibration) as r:
        hit = r.query(img, "the red can", mask=mask, top=1)
    with open_retriever(without, calibration) as r:
        miss = r.query(img, "the red can", mask=mask, top=3)
    assert hit.best.name == "red_can" and hit.accepted is True and hit.confidence > 0.5
    assert miss.best.name != "red_can" and miss.accepted is False and miss.confidence < 0.5
    assert miss.candidates  # the closest candidates are still listed
    for res in (hit, miss):
        d = json.loads(res.to_json())
        assert d["accepted"] is res.accepted and d["confidence"] == res.confidence
        assert d["accept_threshold"] == 0.5 and d["acceptance"]["variant"] == "two-stage"
        assert set(d["acceptance"]["features"]) >= {"score", "margin", "fallback"}
    assert "answer: accepted, red_can matches" in format_result(hit)
    assert "NOT accepted: no model in the library matches" in format_result(miss)


def test_accept_threshold_moves_the_operating_point(stores, calibration):
    full, without, _ = stores
    img, mask = red_can()
    with open_retriever(without, calibration) as r:
        emb = r.embed(r.make_roi(img, "the red can", mask=mask), "the red can")
        default = r.rank(emb)
        loose = r.rank(emb, accept_threshold=0.0)
        assert loose.accepted is True and loose.confidence == default.confidence
        assert loose.accept_threshold == 0.0
        for bad in (-0.1, 1.1, float("nan")):
            with pytest.raises(QueryError, match="accept threshold"):
                r.rank(emb, accept_threshold=bad)
    with open_retriever(full, calibration, accept_threshold=1.0) as r:  # the settings' default
        assert r.query(img, "the red can", mask=mask).accept_threshold == 1.0


def test_every_mode_is_judged_and_a_missing_variant_says_so(stores, calibration, tmp_path):
    full, _, _ = stores
    img, mask = red_can()
    with open_retriever(full, calibration) as r:
        emb = r.embed(r.make_roi(img, "the red can", mask=mask), "the red can")
        for mode in VARIANTS:
            assert isinstance(r.rank(emb, mode=mode).accepted, bool)
    only = Calibration.from_json(json.loads(calibration.read_text()))
    only = Calibration(only.profile, only.models, {"text-only": only.variants["text-only"]})
    with open_retriever(full, only.write(tmp_path / "only.json")) as r:
        res = r.query(img, "the red can", mask=mask)
    assert res.accepted is None and res.confidence is None
    assert "no acceptance calibration for two-stage" in res.to_dict()["acceptance"]["note"]
    assert "answer: not judged" in format_result(res)


def test_a_calibration_of_other_models_is_not_applied(stores, calibration, tmp_path):
    full, _, _ = stores
    d = json.loads(calibration.read_text())
    d["models"]["view_encoder"] = "offline:some-other-encoder"
    (tmp_path / "other.json").write_text(json.dumps(d))
    img, mask = red_can()
    with open_retriever(full, tmp_path / "other.json") as r:
        res = r.query(img, "the red can", mask=mask)
    assert res.accepted is None and "re-calibrate" in res.to_dict()["acceptance"]["note"]
    with pytest.raises(QueryError, match="not found"):
        open_retriever(full, tmp_path / "missing.json")


def test_batch_lines_carry_the_verdict(stores, calibration, tmp_path):
    _, without, _ = stores
    img, mask = red_can()
    img.save(tmp_path / "can.png")
    Image.fromarray(mask).save(tmp_path / "can_mask.png")
    lines = [
        {"id": "a", "image": "can.png", "prompt": "the red can", "mask": "can_mask.png"},
        {"id": "b", "image": "can.png", "prompt": "the red can", "mask": "can_mask.png"},
    ]
    (tmp_path / "q.jsonl").write_text("\n".join(json.dumps(x) for x in lines) + "\n")
    out = io.StringIO()
    with open_retriever(without, calibration) as r:
        ok, failed = run_batch(r, tmp_path / "q.jsonl", out, progress=False, accept_threshold=0.0)
    assert (ok, failed) == (2, 0)
    rows = [json.loads(x) for x in out.getvalue().splitlines()]
    assert all(row["accepted"] is True and row["accept_threshold"] == 0.0 for row in rows)
    assert all(0.0 <= row["confidence"] < 0.5 for row in rows)


def test_cli_json_and_text(stores, calibration, tmp_path, monkeypatch, capsys):
    import pipeline.models.registry as registry
    from pipeline.query.cli import main

    models = fake_models()
    monkeypatch.setattr(registry, "create_model", lambda role, spec, **kw: models[role])
    _, without, _ = stores
    img, mask = red_can()
    img.save(tmp_path / "can.png")
    Image.fromarray(mask).save(tmp_path / "can_mask.png")
    base = ["--store", str(without), "--image", str(tmp_path / "can.png"), "--prompt", "the red can"]
    base += ["--mask", str(tmp_path / "can_mask.png"), "--no-cache", "--accept-model", str(calibration)]
    assert main([*base, "--json"]) == 0
    d = json.loads(capsys.readouterr().out)
    assert d["accepted"] is False and 0.0 <= d["confidence"] < 0.5 and d["candidates"]
    assert main([*base, "--accept-threshold", "0"]) == 0
    assert "answer: accepted" in capsys.readouterr().out
    assert main(base) == 0
    assert "no model in the library matches this object" in capsys.readouterr().out
    with pytest.raises(SystemExit):
        main([*base, "--accept-threshold", "2"])
    assert "--accept-threshold" in capsys.readouterr().err


def test_service_answers_carry_the_verdict(stores, calibration):
    pytest.importorskip("httpx", reason="httpx not installed (FastAPI's TestClient needs it)")
    from fastapi.testclient import TestClient

    from pipeline.serve.app import create_app
    from pipeline.serve.service import QueryService, ServiceLimits

    _, without, _ = stores
    img, mask = red_can()
    buf = io.BytesIO()
    img.save(buf, format="PNG")
    r = open_retriever(without, calibration)
    service = QueryService(r, ServiceLimits(reload_interval=0, workers=1))
    files = {"image": ("photo.png", buf.getvalue(), "image/png")}
    with TestClient(create_app(service)) as c:
        d = c.post("/query", files=files, data={"prompt": "the red can", "box": "30,30,74,82"}).json()
        assert d["accepted"] is False and 0.0 <= d["confidence"] < 0.5
        d = c.post(
            "/query", files=files, data={"prompt": "the red can", "box": "30,30,74,82", "accept_threshold": 0}
        )
        assert d.json()["accepted"] is True
        bad = c.post(
            "/query", files=files, data={"prompt": "the red can", "box": "30,30,74,82", "accept_threshold": 3}
        )
        assert bad.status_code == 422
        import base64

        item = {"image_b64": base64.b64encode(buf.getvalue()).decode(), "prompt": "the red can"}
        item["box"] = [30, 30, 74, 82]
        batch = c.post("/query/batch", json={"queries": [item], "accept_threshold": 0.0}).json()
        assert batch["results"][0]["accepted"] is True
        assert "not accepted" in c.get("/").text.lower()  # the page shows a rejected answer as such
    service.close()


# ---------------------------------------------------------------------------- the open-set split
def _ranking(res):
    cands = [(c.mesh_id, c.text_score, c.image_score, c.best_view) for c in res.candidates]
    return cands, res.used_fallback, res.n_stage1, res.decided_by, res.verdict.features


@pytest.mark.parametrize(
    "setting",
    [
        {},
        {"threshold": 1.5, "fallback_k": 2},  # nothing passes tau: the caption fallback
        {"threshold": 1.5, "fallback_k": 1, "fallback_unit": "meshes"},
        {"threshold": -1.0},  # everything passes
        {"mode": "text-only"},
        {"mode": "image-only"},
    ],
)
def test_leaving_meshes_out_equals_a_store_built_without_them(stores, calibration, setting):
    full, without, _ = stores
    queries = [("red", 44, 52), ("green", 40, 52), ("yellow", 30, 66), ("blue", 80, 40)]
    with open_retriever(full, calibration) as rf, open_retriever(without, calibration) as rw:
        sub = without_meshes(rf, ["id-red_can", "id-blue_box"])
        assert sub.mesh_ids == rw.mesh_ids
        for colour, w, h in queries:
            img = object_image(colour, w, h, pad=20)
            prompt = f"the {colour} object"
            emb = rf.embed(rf.make_roi(img, prompt, box=(20, 20, 20 + w, 20 + h), roi_mode="bbox"), prompt)
            assert _ranking(sub.rank(emb, top=10, **setting)) == _ranking(rw.rank(emb, top=10, **setting))
        with pytest.raises(ValueError, match="none of the meshes"):
            without_meshes(rf, ["id-nothing"])
        with pytest.raises(ValueError, match="empty"):
            without_meshes(rf, rf.mesh_ids)


def test_a_calibration_fitted_on_fused_scores_does_not_judge_an_unfused_store(stores, tmp_path):
    """The fake stores hold no learned embeddings, so their queries do not fuse: a calibration recorded
    with the learned encoder fused does not apply there (``accepted`` null, with the note)."""
    from pipeline.profiles import get_profile
    from pipeline.query.accept import learned_identity

    m = AcceptModel(("score",), (0.0,), (1.0,), (200.0,), -200.0 * 0.95, threshold=0.5)
    keys = {r: (s.key() if s else None) for r, s in _offline_roles().items()}
    keys["learned_encoder"] = learned_identity(get_profile("offline").learned_encoder)
    path = Calibration("offline", keys, dict.fromkeys(VARIANTS, m)).write(tmp_path / "fused.json")
    img, mask = red_can()
    with open_retriever(stores[0], path) as r:
        res = r.query(img, "the red can", mask=mask, top=1)
    assert res.accepted is None and res.confidence is None
    assert "learned_encoder" in res.to_dict()["acceptance"]["note"]
