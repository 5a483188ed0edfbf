"""The paper profile's query path with tiny random GroundingDINO, SAM, CLIP and DINOv2 models.

The models are built in the test (``tests/tiny_models.py``) and go through the same factory and
``--model ROLE=DIR`` overrides as the real ones. Random weights rank nothing meaningfully, so the store is
written from the query's own vectors where a test needs a known answer: that checks the wiring (which
encoder feeds which stage) exactly.
"""

from __future__ import annotations

import json

import numpy as np
import pytest
from query_helpers import object_image

pytest.importorskip("transformers")

from pipeline.models.registry import ModelSpec, create_model  # noqa: E402
from pipeline.query import QueryError, Retriever  # noqa: E402
from pipeline.query.images import load_photo  # noqa: E402
from pipeline.query.roi import cut_out  # noqa: E402

CPU = {"device": "cpu"}


@pytest.fixture(scope="module")
def tiny(tmp_path_factory):
    import tiny_models

    root = tmp_path_factory.mktemp("tiny_query")
    clip = str(tiny_models.build_clip(root / "clip"))
    return {
        "text_encoder": clip,
        "clip_image_encoder": clip,
        "view_encoder": str(tiny_models.build_dinov2(root / "dinov2")),
        "detector": str(tiny_models.build_grounding_dino(root / "gdino")),
        "segmenter": str(tiny_models.build_sam(root / "sam")),
    }


@pytest.fixture(scope="module")
def photo(tmp_path_factory):
    d = tmp_path_factory.mktemp("paper_photo")
    img = object_image("red", 40, 52, pad=20)
    mask = np.abs(np.asarray(img, np.int16) - 205).sum(axis=2) > 30
    img.save(d / "can.png")
    from PIL import Image

    Image.fromarray(mask).save(d / "mask.png")
    return d, img, mask


@pytest.fixture(scope="module")
def store(tiny, photo, tmp_path_factory):
    """Three models; model "target" holds the query ROI's own CLIP and DINOv2 vectors."""
    from query_helpers import make_store

    from pipeline.profiles import get_profile

    _, img, mask = photo
    roi, _, _ = cut_out(load_photo(img).image, mask)
    prof = get_profile("paper", tiny)
    clip_text = create_model("text_encoder", ModelSpec("clip_text", tiny["text_encoder"], CPU))
    clip_image = create_model("clip_image_encoder", ModelSpec("clip_image", tiny["clip_image_encoder"], CPU))
    dino = create_model("view_encoder", ModelSpec("dinov2", tiny["view_encoder"], CPU))
    others = [object_image("blue", 70, 30), object_image("green", 30, 30)]
    meshes = {
        "target": {
            "name": "target",
            "captions": np.vstack([clip_text.encode_text(["a blue box"]), clip_image.encode_image([roi])]),
            "views": np.vstack([dino.encode_image(others[:1]), dino.encode_image([roi])]),
        },
        "decoy-1": {
            "name": "decoy-1",
            "captions": clip_text.encode_text(["a red mug"]),
            "views": dino.encode_image(others),
        },
        "decoy-2": {
            "name": "decoy-2",
            "captions": clip_text.encode_text(["a green can"]),
            "views": dino.encode_image(others[1:]),
        },
    }
    models = {r: (s.key() if s else None) for r, s in prof.roles().items()}
    return make_store(tmp_path_factory.mktemp("paper_store") / "s", meshes, profile="paper", models=models)


def test_known_answer_through_both_stages(store, tiny, photo):
    _, img, mask = photo
    with Retriever.open(store, profile="paper", model_overrides=tiny, device="cpu") as r:
        assert r.strategy.space == "image" and set(r.load_seconds) == {"clip_image_encoder", "view_encoder"}
        text = r.query(img, "the red can", mask=mask, mode="text-only", top=3)
        assert text.candidates[0].name == "target" and text.candidates[0].text_score == pytest.approx(
            1.0, abs=1e-4
        )
        image = r.query(img, "the red can", mask=mask, mode="image-only", top=3)
        assert image.candidates[0].name == "target" and image.candidates[0].image_score == pytest.approx(
            1.0, abs=1e-4
        )
        assert image.candidates[0].best_view == 1
        both = r.query(img, "the red can", mask=mask, threshold=0.999, fallback_k=10)
        assert both.candidates[0].name == "target" and both.n_stage1 == 1 and not both.used_fallback
        assert both.threshold == 0.999
        assert r.settings.threshold == 0.37  # the paper's tau by default


def test_detector_and_segmenter_path(store, tiny, photo):
    _, img, _ = photo
    detector = create_model(
        "detector",
        ModelSpec("grounding_dino", tiny["detector"], {"box_threshold": 0.0, "text_threshold": 0.0, **CPU}),
    )
    with Retriever.open(
        store, profile="paper", model_overrides=tiny, device="cpu", models={"detector": detector}
    ) as r:
        result = r.query(img, "the red can", top=3)
        assert (
            result.query["roi"]["source"] == "detector" and result.query["roi"]["detector_score"] is not None
        )
        assert "segmenter" in r.load_seconds  # SAM was built through the factory on first use
        assert 1 <= len(result.candidates) <= 3
        bbox = r.query(img, "the red can", roi_mode="bbox", top=1)
        assert bbox.query["roi"]["roi_mode"] == "bbox"
        strict = create_model(
            "detector",
            ModelSpec(
                "grounding_dino", tiny["detector"], {"box_threshold": 1.0, "text_threshold": 1.0, **CPU}
            ),
        )
        r.models.adapters["detector"] = strict
        with pytest.raises(QueryError, match="no object matching 'the red can' was detected"):
            r.query(img, "the red can")


def test_cli_paper_profile_with_model_overrides(store, tiny, photo, capsys):
    from pipeline.query.cli import main

    d, _, _ = photo
    argv = [
        "--store",
        str(store),
        "--image",
        str(d / "can.png"),
        "--prompt",
        "the red can",
        "--box",
        "10,10,70,80",
    ]
    argv += ["--profile", "paper", "--device", "cpu", "--json", "--mode", "image-only"]
    for role, path in tiny.items():
        argv += ["--model", f"{role}={path}"]
    assert main(argv) == 0
    data = json.loads(capsys.readouterr().out)
    assert data["query"]["profile"] == "paper" and data["query"]["roi"]["source"] == "box"
    assert len(data["candidates"]) == 3 and data["candidates"][0]["text_score"] is None
    wrong = [
        a.replace(f"view_encoder={tiny['view_encoder']}", f"view_encoder={tiny['clip_image_encoder']}")
        for a in argv
    ]
    assert main(wrong) == 2
    assert "onboarded with view_encoder dinov2:" in capsys.readouterr().err
