"""Query inputs: photos of every awkward kind, boxes, masks and prompts, and the ROI built from them."""

from __future__ import annotations

import numpy as np
import pytest
from PIL import Image

from pipeline.query.errors import QueryError
from pipeline.query.images import clean_prompt, load_mask, load_photo, parse_box
from pipeline.query.roi import border_segment, make_roi

GRAY = (205, 205, 205)


def scene(w=120, h=90, box=(30, 20, 80, 70), colour=(200, 30, 30)) -> Image.Image:
    """A red rectangle on a plain blue-gray background."""
    arr = np.zeros((h, w, 3), np.uint8)
    arr[:] = (90, 110, 140)
    x0, y0, x1, y1 = box
    arr[y0:y1, x0:x1] = colour
    return Image.fromarray(arr)


def no_models(role):
    return None


# ---------------------------------------------------------------- photos
def test_rgb_photo_from_path(tmp_path):
    p = tmp_path / "a.jpg"
    scene().save(p)
    photo = load_photo(p)
    assert photo.image.mode == "RGB" and photo.image.size == (120, 90) and photo.scale == 1.0


@pytest.mark.parametrize("mode", ["L", "1", "P", "CMYK", "LA", "RGBA", "I;16", "I", "F"])
def test_any_mode_becomes_rgb(mode):
    img = scene().convert("L") if mode in ("I;16", "I", "F") else scene()
    if mode == "I;16":
        img = Image.fromarray((np.asarray(img, np.uint16) * 257).astype(np.uint16))
    elif mode in ("I", "F"):
        img = img.convert(mode)
    else:
        img = img.convert(mode)
    photo = load_photo(img)
    assert photo.image.mode == "RGB" and photo.image.size == (120, 90)


def test_16_bit_png_keeps_its_contrast(tmp_path):
    arr = np.zeros((40, 40), np.uint16)
    arr[10:30, 10:30] = 60000
    p = tmp_path / "deep.png"
    Image.fromarray(arr).save(p)
    rgb = np.asarray(load_photo(p).image)
    assert rgb[20, 20, 0] > 200 and rgb[0, 0, 0] == 0  # not clipped to white, not crushed to black


def test_transparent_pixels_become_gray():
    rgba = np.zeros((20, 20, 4), np.uint8)
    rgba[5:15, 5:15] = (255, 0, 0, 255)
    rgb = np.asarray(load_photo(Image.fromarray(rgba, "RGBA")).image)
    assert tuple(rgb[0, 0]) == GRAY and tuple(rgb[10, 10]) == (255, 0, 0)


def test_huge_photo_is_downscaled_and_boxes_follow(tmp_path):
    big = scene(4000, 3000, box=(1000, 1000, 3000, 2000))
    photo = load_photo(big, max_side=1000)
    assert photo.image.size == (1000, 750) and photo.scale == pytest.approx(0.25)
    roi = make_roi(photo, "the red box", box=(900, 900, 3100, 2100), model=no_models, box_segmenter="border")
    assert roi.mask.shape == (3000, 4000)  # the mask is in the photo's own pixels
    x0, y0, x1, y1 = roi.box
    assert abs(x0 - 1000) <= 8 and abs(x1 - 3000) <= 8 and abs(y0 - 1000) <= 8 and abs(y1 - 2000) <= 8


def test_array_inputs():
    photo = load_photo(np.asarray(scene()))
    assert photo.image.size == (120, 90)
    with pytest.raises(QueryError, match="shape"):
        load_photo(np.zeros((4, 4, 7), np.uint8))


@pytest.mark.parametrize(
    ("make", "message"),
    [
        (lambda p: None, "image not found"),
        (lambda p: p.write_bytes(b"this is not an image at all"), "not an image"),
        (lambda p: p.write_bytes(b""), "not an image"),
        (lambda p: p.mkdir(), "not a file"),
    ],
)
def test_bad_photo_files(tmp_path, make, message):
    p = tmp_path / "photo.png"
    make(p)
    with pytest.raises(QueryError, match=message) as exc:
        load_photo(p)
    assert "\n" not in str(exc.value)


def test_truncated_photo(tmp_path):
    p = tmp_path / "cut.jpg"
    scene(400, 300).save(p, quality=95)
    p.write_bytes(p.read_bytes()[:1500])
    with pytest.raises(QueryError, match="truncated|corrupt|unreadable"):
        load_photo(p)


def test_tiny_photo():
    with pytest.raises(QueryError, match="too small"):
        load_photo(scene(8, 8, box=(1, 1, 4, 4)))


# ---------------------------------------------------------------- boxes, masks, prompts
@pytest.mark.parametrize("text", ["1,2,3", "a,b,c,d", "1,2,3,4,5", "5,5,1,9", "1,1,nan,4", ""])
def test_bad_box_text(text):
    with pytest.raises(QueryError, match="box"):
        parse_box(text)


def test_box_outside_or_too_small():
    photo = load_photo(scene())
    with pytest.raises(QueryError, match="outside"):
        make_roi(photo, "x y", box=(500, 500, 600, 600), model=no_models)
    with pytest.raises(QueryError, match="too small"):
        make_roi(photo, "x y", box=(10, 10, 12, 60), model=no_models)


def test_partly_outside_box_is_clipped():
    photo = load_photo(scene())
    roi = make_roi(photo, "the red box", box=(-50, -50, 100, 80), roi_mode="bbox", model=no_models)
    assert roi.box == (0.0, 0.0, 100.0, 80.0) and roi.image.size == (100, 80)


def test_mask_must_match_the_photo(tmp_path):
    photo = load_photo(scene())
    p = tmp_path / "m.png"
    Image.new("L", (60, 45), 255).save(p)
    with pytest.raises(QueryError, match="mask is 60x45 but the image is 120x90"):
        load_mask(p, photo)
    Image.new("L", (120, 90), 0).save(p)
    with pytest.raises(QueryError, match="empty"):
        load_mask(p, photo)


@pytest.mark.parametrize("kind", ["L255", "L1", "1", "RGBA-cutout", "P"])
def test_mask_encodings(tmp_path, kind):
    photo = load_photo(scene())
    m = np.zeros((90, 120), bool)
    m[20:70, 30:80] = True
    p = tmp_path / "m.png"
    if kind == "L255":
        Image.fromarray(m.astype(np.uint8) * 255).save(p)
    elif kind == "L1":
        Image.fromarray(m.astype(np.uint8)).save(p)
    elif kind == "1":
        Image.fromarray(m).save(p)
    elif kind == "RGBA-cutout":
        rgba = np.zeros((90, 120, 4), np.uint8)
        rgba[..., :3] = 255
        rgba[..., 3] = m * 255
        Image.fromarray(rgba, "RGBA").save(p)
    else:
        Image.fromarray(m.astype(np.uint8)).convert("P").save(p)
    assert np.array_equal(load_mask(p, photo), m)


@pytest.mark.parametrize(
    ("prompt", "message"),
    [
        ("", "empty"),
        ("   \n\t", "empty"),
        ("!!! 123 ???", "no words"),
        ("x" * 400, "too long"),
        (None, "must be text"),
    ],
)
def test_bad_prompts(prompt, message):
    with pytest.raises(QueryError, match=message):
        clean_prompt(prompt)


def test_prompt_is_normalised():
    assert clean_prompt("  the\tyellow\n mustard bottle ") == "the yellow mustard bottle"


# ---------------------------------------------------------------- ROI
def test_mask_roi_is_object_on_gray_cropped():
    photo = load_photo(scene())
    m = np.zeros((90, 120), bool)
    m[20:70, 30:80] = True
    m[20:30, 30:40] = False  # a notch: background there must be gray in the ROI
    roi = make_roi(photo, "the red box", mask=m, model=no_models)
    arr = np.asarray(roi.image)
    assert roi.source == "mask" and roi.image.size == (50, 50) and roi.box == (30.0, 20.0, 80.0, 70.0)
    assert tuple(arr[0, 0]) == GRAY and tuple(arr[25, 25]) == (200, 30, 30)
    assert roi.crop_mask.shape == (50, 50) and not roi.crop_mask[0, 0]


def test_bbox_mode_is_the_raw_crop():
    photo = load_photo(scene())
    roi = make_roi(photo, "the red box", box=(20, 10, 90, 80), roi_mode="bbox", model=no_models)
    arr = np.asarray(roi.image)
    assert roi.image.size == (70, 70) and tuple(arr[0, 0]) == (90, 110, 140)


def test_box_without_segmenter_splits_object_from_border_colour():
    photo = load_photo(scene())
    roi = make_roi(photo, "the red box", box=(20, 10, 90, 80), model=no_models, box_segmenter="border")
    assert roi.box == (30.0, 20.0, 80.0, 70.0)
    assert any("border colour" in n for n in roi.notes)


def cluttered_scene(seed=0):
    """A red ellipse on a busy checkerboard-and-noise background (no uniform border to key on)."""
    rng = np.random.default_rng(seed)
    ys, xs = np.mgrid[0:120, 0:160]
    board = (((xs // 16) + (ys // 16)) % 2).astype(np.float32)
    arr = np.stack([90 + 120 * board, 70 + 100 * board, 40 + 80 * board], -1) + rng.normal(
        0, 12, (120, 160, 3)
    )
    obj = ((xs - 80) / 30.0) ** 2 + ((ys - 60) / 22.0) ** 2 <= 1
    arr[obj] = (220, 40, 40) + rng.normal(0, 8, (int(obj.sum()), 3))
    return Image.fromarray(np.clip(arr, 0, 255).astype(np.uint8)), obj


def test_box_without_segmenter_uses_grabcut_on_clutter():
    img, obj = cluttered_scene()
    photo = load_photo(img)
    box = (40, 30, 121, 91)
    roi = make_roi(photo, "the red thing", box=box, model=no_models)
    assert any("GrabCut" in n for n in roi.notes)
    iou = (roi.mask & obj).sum() / (roi.mask | obj).sum()
    assert iou > 0.85
    border = border_segment(img, box)
    border_iou = 0.0 if border is None else (border & obj).sum() / (border | obj).sum()
    assert iou > border_iou
    again = make_roi(photo, "the red thing", box=box, model=no_models)
    assert np.array_equal(again.mask, roi.mask)  # deterministic
    with pytest.raises(QueryError, match="unknown box segmenter"):
        make_roi(photo, "x", box=box, model=no_models, box_segmenter="magic")


def test_border_segment_gives_up_on_busy_boxes():
    rng = np.random.default_rng(0)
    noisy = Image.fromarray(rng.integers(0, 255, (60, 60, 3), dtype=np.uint8))
    assert border_segment(noisy, (0, 0, 60, 60)) is None


class FakeDetector:
    model_id = "fake"

    def __init__(self, found):
        self.found = found

    def detect(self, image, prompt):
        return self.found


class FakeSegmenter:
    model_id = "fake"

    def segment(self, image, box):
        m = np.zeros((image.height, image.width), bool)
        x0, y0, x1, y1 = (int(v) for v in box)
        m[y0 + 5 : y1 - 5, x0 + 5 : x1 - 5] = True
        return m


def test_detector_then_segmenter():
    photo = load_photo(scene())
    models = {"detector": FakeDetector([((25.0, 15.0, 85.0, 75.0), 0.8)]), "segmenter": FakeSegmenter()}
    roi = make_roi(photo, "the red box", model=models.get)
    assert roi.source == "detector" and roi.detector_score == 0.8 and roi.box == (30.0, 20.0, 80.0, 70.0)


def test_no_detection_and_no_detector():
    photo = load_photo(scene())
    with pytest.raises(QueryError, match="no object matching 'the red box' was detected"):
        make_roi(photo, "the red box", model={"detector": FakeDetector([])}.get)
    with pytest.raises(QueryError, match="no object detector.*--box"):
        make_roi(photo, "the red box", model=no_models, profile="offline")
