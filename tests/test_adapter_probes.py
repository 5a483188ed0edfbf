"""Probe queries made from stored views (pipeline/adapter/probes.py) and the onboarding stage that embeds them
(pipeline/onboard/stages/probe.py)."""

from __future__ import annotations

import numpy as np
import pyarrow as pa
import pytest
from PIL import Image

from pipeline.adapter.probes import ProbeConfig, chosen_views, object_mask, probe_roi
from pipeline.mesh.render import encode_png

GRAY = (205, 205, 205)


def view_with_ring(size=128):
    """A red ring (with a hole showing the gray) on the render gray, plus a speck of noise far away."""
    a = np.full((size, size, 3), GRAY, np.uint8)
    yy, xx = np.mgrid[:size, :size]
    r = np.hypot(yy - 60, xx - 64)
    a[(r < 40) & (r > 12)] = (200, 30, 30)
    a[5, 120] = (0, 0, 0)
    return a


def test_object_mask_is_the_largest_blob_with_holes_filled():
    m = object_mask(view_with_ring(), GRAY)
    assert m is not None and m[60, 64] and m[60, 30] and not m[5, 120] and not m[120, 5]
    assert object_mask(np.full((32, 32, 3), GRAY, np.uint8), GRAY) is None


def test_probe_roi_is_reproducible_and_differs_per_view():
    cfg = ProbeConfig()
    a = probe_roi(view_with_ring(), "mesh-a", 3, cfg, GRAY)
    b = probe_roi(view_with_ring(), "mesh-a", 3, cfg, GRAY)
    c = probe_roi(view_with_ring(), "mesh-a", 4, cfg, GRAY)
    assert isinstance(a, Image.Image) and a.mode == "RGB"
    assert np.array_equal(np.asarray(a), np.asarray(b))
    assert a.size != c.size or not np.array_equal(np.asarray(a), np.asarray(c))
    lo, hi = cfg.side_px
    assert lo - 2 <= max(a.size) <= hi + 2  # the object scaled into the configured range, cut to its box
    assert probe_roi(np.full((32, 32, 3), GRAY, np.uint8), "m", 0, cfg, GRAY) is None


def test_chosen_views_are_distinct_stable_and_capped():
    cfg = ProbeConfig(per_mesh=4)
    got = chosen_views("mesh-a", list(range(12)), cfg)
    assert (
        got == sorted(set(got))
        and len(got) == 4
        and got == chosen_views("mesh-a", list(range(12))[::-1], cfg)
    )
    assert chosen_views("mesh-a", [0, 1], cfg) == [0, 1]


def test_probe_config_checks():
    with pytest.raises(ValueError, match="probes per mesh"):
        ProbeConfig(per_mesh=-1)
    with pytest.raises(ValueError, match="side range"):
        ProbeConfig(side_px=(300, 100))
    assert not ProbeConfig(per_mesh=0).enabled


class MeanColour:
    """A stand-in learned encoder: the ROI's mean colour (query path: ``encode_roi``)."""

    dim = 3
    model_id = "fake-learned"

    def key(self):
        return "fake:learned"

    def encode_image(self, images):
        return np.array([np.asarray(im, np.float32).reshape(-1, 3).mean(axis=0) + 1 for im in images])

    encode_roi = encode_image


def test_stage_embeds_probes_and_turns_a_blank_mesh_into_an_errors_row():
    from pipeline.onboard.config import OnboardConfig
    from pipeline.onboard.stages.probe import ProbeStage

    cfg = OnboardConfig(probes=ProbeConfig(per_mesh=2))
    step = cfg.resolve().step("probe")
    rows = [
        {"mesh_id": "good", "view_index": i, "image": encode_png(view_with_ring()), "fingerprint": "fp-r"}
        for i in range(3)
    ] + [
        {
            "mesh_id": "blank",
            "view_index": i,
            "image": encode_png(np.full((64, 64, 3), GRAY, np.uint8)),
            "fingerprint": "fp-r",
        }
        for i in range(3)
    ]
    out = ProbeStage(cfg, "run-1", step, MeanColour())(pa.Table.from_pylist(rows))
    good = [r for r in out.to_pylist() if r["mesh_id"] == "good"]
    bad = [r for r in out.to_pylist() if r["mesh_id"] == "blank"]
    assert len(good) == 2 and all(r["error"] is None and r["source_fingerprint"] == "fp-r" for r in good)
    assert {r["view_index"] for r in good} == set(chosen_views("good", [0, 1, 2], cfg.probes))
    assert np.allclose(np.linalg.norm(np.array([r["embedding"] for r in good]), axis=1), 1.0)
    assert len(bad) == 1 and "no view shows the object" in bad[0]["error"]
