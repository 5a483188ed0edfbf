"""The Hugging Face adapters, loaded through ``create_model`` from tiny random models of the real architectures."""

from __future__ import annotations

import numpy as np
import pytest
from PIL import Image

pytest.importorskip("torch")
pytest.importorskip("transformers")

from pipeline.models.protocols import Captioner, Detector, ImageEncoder, Segmenter, TextEncoder  # noqa: E402
from pipeline.models.registry import ModelLoadError, ModelSpec, create_model  # noqa: E402

try:  # tests/ on sys.path (pytest's default rootdir-less import) or the repository root
    import tiny_models
except ImportError:  # pragma: no cover
    from tests import tiny_models

CPU = {"device": "cpu"}


def _image(seed: int, size: tuple[int, int] = (80, 48), mode: str = "RGB") -> Image.Image:
    rng = np.random.default_rng(seed)
    w, h = size
    img = Image.fromarray(rng.integers(0, 256, (h, w, 3), dtype=np.uint8))
    return img.convert(mode)


@pytest.fixture(scope="session")
def tiny_dirs(tmp_path_factory):
    root = tmp_path_factory.mktemp("tiny_hf")
    return {name: str(build(root / name)) for name, build in tiny_models.BUILDERS.items()}


@pytest.fixture(scope="session")
def clip_text(tiny_dirs):
    return create_model("text_encoder", ModelSpec("clip_text", tiny_dirs["clip"], {"max_length": 77, **CPU}))


@pytest.fixture(scope="session")
def clip_image(tiny_dirs):
    return create_model(
        "clip_image_encoder", ModelSpec("clip_image", tiny_dirs["clip"], {**CPU, "batch_size": 2})
    )


@pytest.fixture(scope="session")
def dinov2(tiny_dirs):
    return create_model("view_encoder", ModelSpec("dinov2", tiny_dirs["dinov2"], {**CPU, "batch_size": 2}))


@pytest.fixture(scope="session")
def llava(tiny_dirs):
    return create_model("captioner", ModelSpec("llava", tiny_dirs["llava"], {"max_new_tokens": 5, **CPU}))


@pytest.fixture(scope="session")
def detector(tiny_dirs):
    options = {"box_threshold": 0.0, "text_threshold": 0.0, **CPU}
    return create_model("detector", ModelSpec("grounding_dino", tiny_dirs["grounding_dino"], options))


@pytest.fixture(scope="session")
def segmenter(tiny_dirs):
    return create_model("segmenter", ModelSpec("sam", tiny_dirs["sam"], CPU))


def _assert_rows(x: np.ndarray, n: int, dim: int) -> None:
    assert isinstance(x, np.ndarray) and x.dtype == np.float32
    assert x.shape == (n, dim)
    np.testing.assert_allclose(np.linalg.norm(x, axis=1), 1.0, atol=1e-5)


def test_clip_text_encoder(clip_text, tiny_dirs):
    assert isinstance(clip_text, TextEncoder)
    assert clip_text.model_id == tiny_dirs["clip"] and clip_text.dim == 16  # top-level projection_dim
    texts = ["a red mug", "the blue box", "a " * 200 + "bottle"]  # the last one is truncated at 77 tokens
    a = clip_text.encode_text(texts)
    _assert_rows(a, 3, 16)
    np.testing.assert_allclose(clip_text.encode_text(texts), a, atol=1e-6)  # deterministic
    single = np.concatenate([clip_text.encode_text([t]) for t in texts])
    np.testing.assert_allclose(single, a, atol=1e-5)  # padding does not change a row
    assert not np.allclose(a[0], a[1])
    assert clip_text.encode_text([]).shape == (0, 16)


def test_clip_text_truncation(tiny_dirs):
    short = create_model("text_encoder", ModelSpec("clip_text", tiny_dirs["clip"], {"max_length": 8, **CPU}))
    assert short.max_length == 8
    base = "a red mug and more"
    np.testing.assert_allclose(
        short.encode_text([base + " x"]), short.encode_text([base + " y z"]), atol=1e-6
    )


def test_clip_image_encoder(clip_image):
    assert isinstance(clip_image, ImageEncoder) and clip_image.dim == 16
    images = [_image(i) for i in range(3)] + [_image(9, mode="L")]  # batch 2 -> two chunks; grey converted
    x = clip_image.encode_image(images)
    _assert_rows(x, 4, 16)
    np.testing.assert_allclose(clip_image.encode_image(images[:1]), x[:1], atol=1e-5)
    assert clip_image.encode_image([]).shape == (0, 16)


def test_clip_image_registered_as_image_encoder(tiny_dirs):
    enc = create_model("image_encoder", ModelSpec("clip_image", tiny_dirs["clip"], CPU))
    _assert_rows(enc.encode_image([_image(1)]), 1, 16)


def test_dinov2_encoder(dinov2, tiny_dirs):
    assert isinstance(dinov2, ImageEncoder) and dinov2.dim == 32 and dinov2.model_id == tiny_dirs["dinov2"]
    images = [_image(i, size=(40 + 8 * i, 36)) for i in range(3)]
    x = dinov2.encode_image(images)
    _assert_rows(x, 3, 32)
    np.testing.assert_allclose(dinov2.encode_image(images), x, atol=1e-6)
    np.testing.assert_allclose(dinov2.encode_image(images[2:]), x[2:], atol=1e-5)


def test_dinov2_mean_pooling_includes_cls(dinov2):
    import torch

    img = _image(4)
    enc = dinov2.processor(images=[img], return_tensors="pt")
    with torch.inference_mode():
        hidden = dinov2.model(**enc).last_hidden_state
    expected = hidden.mean(dim=1)[0].numpy()
    np.testing.assert_allclose(dinov2.encode_image([img])[0], expected / np.linalg.norm(expected), atol=1e-5)
    via_image_role = create_model("image_encoder", ModelSpec("dinov2", dinov2.model_id, CPU))
    np.testing.assert_allclose(via_image_role.encode_image([img]), dinov2.encode_image([img]), atol=1e-6)


def test_llava_captioner(llava, tiny_dirs):
    assert isinstance(llava, Captioner) and llava.model_id == tiny_dirs["llava"] and llava.max_new_tokens == 5
    assert llava.format_prompt("What is this?") == "USER: <image>\nWhat is this? ASSISTANT:"
    images = [_image(i) for i in range(3)]
    caps = llava.caption(images, "What is this?")
    assert isinstance(caps, list) and len(caps) == 3 and all(isinstance(c, str) for c in caps)
    assert all("ASSISTANT" not in c and "What is this" not in c for c in caps)  # prompt stripped
    assert llava.caption(images, "What is this?") == caps  # greedy -> deterministic
    one_by_one = [llava.caption([im], "What is this?")[0] for im in images]
    assert one_by_one == caps  # batching (left padding) is neutral
    assert llava.caption([], "What is this?") == []


def test_llava_without_chat_template(tmp_path):
    path = tiny_models.build_llava(tmp_path / "llava_plain", chat_template=False)
    cap = create_model(
        "captioner", ModelSpec("llava", str(path), {"max_new_tokens": 3, **CPU, "batch_size": 1})
    )
    assert cap.format_prompt("Describe it.") == "USER: <image>\nDescribe it. ASSISTANT:"
    out = cap.caption([_image(0), _image(1)], "Describe it.")
    assert len(out) == 2 and all(isinstance(c, str) for c in out)


def test_grounding_dino_detector(detector):
    assert isinstance(detector, Detector)
    img = _image(0, size=(80, 48))
    dets = detector.detect(img, "A Red Mug")
    assert dets, "thresholds 0.0 should keep every query"
    scores = [s for _, s in dets]
    assert scores == sorted(scores, reverse=True)
    for (x0, y0, x1, y1), score in dets:
        assert 0.0 <= x0 <= x1 <= 80 and 0.0 <= y0 <= y1 <= 48
        assert isinstance(score, float) and 0.0 <= score <= 1.0
    assert detector.detect(img, "a red mug.") == dets  # prompt normalised: lower case, trailing dot


def test_grounding_dino_thresholds(tiny_dirs):
    strict = create_model("detector", ModelSpec("grounding_dino", tiny_dirs["grounding_dino"], CPU))
    assert (strict.box_threshold, strict.text_threshold) == (0.3, 0.25)
    dets = strict.detect(_image(0), "a red mug")
    assert all(score > 0.3 for _, score in dets)


def test_sam_segmenter(segmenter):
    assert isinstance(segmenter, Segmenter)
    img = _image(0, size=(80, 48))
    mask = segmenter.segment(img, (10.0, 8.0, 50.0, 40.0))
    assert isinstance(mask, np.ndarray) and mask.dtype == bool and mask.shape == (48, 80)
    np.testing.assert_array_equal(segmenter.segment(img, (10.0, 8.0, 50.0, 40.0)), mask)
    tall = segmenter.segment(_image(1, size=(30, 70)), (0, 0, 30, 70))
    assert tall.shape == (70, 30)


def test_explicit_dtype_option(tiny_dirs):
    import torch

    enc = create_model("view_encoder", ModelSpec("dinov2", tiny_dirs["dinov2"], {**CPU, "dtype": "bf16"}))
    assert enc.dtype == torch.bfloat16 and next(enc.model.parameters()).dtype == torch.bfloat16
    x = enc.encode_image([_image(0)])
    _assert_rows(x, 1, 32)


def test_missing_directory_is_one_line_error(tmp_path):
    missing = tmp_path / "no-such-model"
    with pytest.raises(ModelLoadError) as err:
        create_model("captioner", ModelSpec("llava", str(missing), CPU))
    msg = str(err.value)
    assert "\n" not in msg
    assert msg.startswith(f"cannot load captioner '{missing}'")
    assert "--model captioner=DIR" in msg and "--profile offline" in msg


def test_empty_directory_is_one_line_error(tmp_path):
    with pytest.raises(ModelLoadError) as err:
        create_model("detector", ModelSpec("grounding_dino", str(tmp_path), CPU))
    assert "\n" not in str(err.value) and "cannot load detector" in str(err.value)


def test_hub_id_offline_is_one_line_error(monkeypatch):
    monkeypatch.setenv("HF_HUB_OFFLINE", "1")
    with pytest.raises(ModelLoadError) as err:
        create_model("segmenter", ModelSpec("sam", "facebook/sam-vit-huge", CPU))
    msg = str(err.value)
    assert "\n" not in msg and "cannot load segmenter 'facebook/sam-vit-huge'" in msg
    assert "--profile offline" in msg


def test_unknown_option_is_a_load_error(tiny_dirs):
    with pytest.raises(ModelLoadError, match="unknown option"):
        create_model("view_encoder", ModelSpec("dinov2", tiny_dirs["dinov2"], {"bogus": 1}))
