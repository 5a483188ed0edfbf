"""Exposure normalisation of the foreground before the learned encoder (pipeline.models.exposure)."""

from __future__ import annotations

import numpy as np
from PIL import Image

from pipeline.models.exposure import MIN_FOREGROUND, luminance, normalise_exposure

GRAY = (205, 205, 205)


def object_on_gray(colour, size=(40, 30), box=(8, 6, 30, 24)) -> Image.Image:
    a = np.full((size[1], size[0], 3), GRAY, np.uint8)
    x0, y0, x1, y1 = box
    a[y0:y1, x0:x1] = colour
    return Image.fromarray(a)


def plain_foreground(a: np.ndarray, fill=GRAY) -> np.ndarray:
    """The definition in plain float NumPy: R + G + B off ``fill`` by more than the tolerance."""
    return np.abs(a - np.asarray(fill, np.float32)).sum(-1) > 6


def foreground_median(im: Image.Image) -> float:
    a = np.asarray(im).astype(np.float32)
    return float(np.median(luminance(a[plain_foreground(a)])))


def test_foreground_lands_on_the_target_and_the_background_stays():
    dark = object_on_gray((40, 60, 20))
    out = np.asarray(normalise_exposure(dark, 110, GRAY))
    assert abs(foreground_median(Image.fromarray(out)) - 110) <= 1.0
    src = np.asarray(dark)
    bg = (src == np.array(GRAY)).all(-1)
    np.testing.assert_array_equal(out[bg], src[bg])
    # a scale, not a tone curve: the object's colour ratios are kept
    px = out[12, 15].astype(float)
    np.testing.assert_allclose(px / px[1], np.array([40, 60, 20]) / 60, atol=0.03)


def test_the_same_object_at_two_exposures_comes_out_alike():
    rng = np.random.default_rng(0)
    tex = rng.integers(20, 120, (18, 22, 3))
    a = np.full((30, 40, 3), GRAY, np.float32)
    a[6:24, 8:30] = tex
    dim = Image.fromarray(a.astype(np.uint8))
    a2 = a.copy()
    a2[6:24, 8:30] = np.clip(tex * 1.8, 0, 255)
    bright = Image.fromarray(a2.astype(np.uint8))
    x, y = (np.asarray(normalise_exposure(im, 110, GRAY)).astype(float) for im in (dim, bright))
    before = np.abs(np.asarray(dim, float) - np.asarray(bright, float))[6:24, 8:30].mean()
    after = np.abs(x - y)[6:24, 8:30].mean()
    assert after < 2.0 < before


def test_clipped_and_nearly_empty_images():
    white = normalise_exposure(object_on_gray((250, 250, 120)), 250, GRAY)
    assert np.asarray(white).max() <= 255
    # most of the object at level 30, a stripe at 60: a median of 30 scaled to 255 doubles the stripe past
    # the 8-bit range, so it must clip to exactly 255 (not wrap); the rest lands on 255 within the one level
    # the lookup table's truncation may take (30 x 255 / 30 is an exact boundary: the median's last bit
    # decides 254 or 255)
    a = np.asarray(object_on_gray((30, 30, 30))).copy()
    a[6:10, 8:30] = 60
    out = np.asarray(normalise_exposure(Image.fromarray(a), 255, GRAY)).astype(int)
    np.testing.assert_array_equal(out[6:10, 8:30], 255)
    assert (out[12:24, 8:30] >= 254).all() and out.max() <= 255
    speck = object_on_gray((10, 10, 10), box=(1, 1, 3, 3))  # 4 px < MIN_FOREGROUND
    assert 4 < MIN_FOREGROUND
    assert normalise_exposure(speck, 110, GRAY) is speck
    black = object_on_gray((0, 0, 0))  # a median of 0 is not a division by zero
    assert np.isfinite(np.asarray(normalise_exposure(black, 110, GRAY), float)).all()


def plain_reference(image: Image.Image, target: float, fill) -> np.ndarray:
    """The definition in plain float NumPy (:func:`plain_foreground`), scaled without OpenCV."""
    a = np.asarray(image.convert("RGB")).astype(np.float32)
    fg = plain_foreground(a, fill)
    if fg.sum() < MIN_FOREGROUND:
        return np.asarray(image)
    med = max(float(np.median(luminance(a[fg]))), 1.0)
    a[fg] = np.clip(a[fg] * (target / med), 0, 255)
    return a.astype(np.uint8)


def test_the_opencv_path_equals_the_plain_definition():
    rng = np.random.default_rng(1)
    for _ in range(20):
        a = np.full((37, 53, 3), GRAY, np.int16)
        # pixels a little off the background (around the tolerance), and an object
        a += rng.integers(-4, 5, a.shape).astype(np.int16) * (rng.random(a.shape[:2]) < 0.3)[..., None]
        a[5:30, 10:40] = rng.integers(0, 256, (25, 30, 3))
        im = Image.fromarray(np.clip(a, 0, 255).astype(np.uint8))
        for target in (1, 60, 110.5, 255):
            np.testing.assert_array_equal(np.asarray(normalise_exposure(im, target, GRAY)), plain_reference(im, target, GRAY))


def test_foreground_luminance():
    from pipeline.models.exposure import foreground_luminance

    assert abs(foreground_luminance(object_on_gray((100, 100, 100)), GRAY) - 100) < 0.01
    assert foreground_luminance(object_on_gray((10, 10, 10), box=(1, 1, 3, 3)), GRAY) is None
    dark = object_on_gray((40, 60, 20))
    assert abs(foreground_luminance(normalise_exposure(dark, 110, GRAY), GRAY) - 110) <= 1.0
