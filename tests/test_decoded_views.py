"""One onboarding batch decodes each rendered view once, however many stages read it
(pipeline.onboard.stages.decoded), and keeps nothing once the batch is committed."""

from __future__ import annotations

import io

import numpy as np
from conftest import copy_ycb
from onboard_helpers import content, onboard
from PIL import Image

import pipeline.mesh.render as render
from pipeline.onboard.stages import decoded
from pipeline.store import Store


def _png(value: int) -> bytes:
    buf = io.BytesIO()
    Image.fromarray(np.full((8, 8, 3), value, np.uint8)).save(buf, format="PNG")
    return buf.getvalue()


def test_shared_only_inside_a_batch_scope(monkeypatch):
    a, b = _png(10), _png(200)
    assert decoded.decoded_view(a) is not decoded.decoded_view(a)  # outside a scope: no cache
    with decoded.batch_scope():
        first = decoded.decoded_view(a)
        assert decoded.decoded_view(bytes(a)) is first  # keyed by content, not by the bytes object
        assert np.asarray(decoded.decoded_view(b))[0, 0, 0] == 200  # other bytes, other image
        with decoded.batch_scope():  # nested: the outer scope still owns the images
            assert decoded.decoded_view(a) is first
        assert decoded.cached() == 2
    assert decoded.cached() == 0
    monkeypatch.setattr(decoded, "CAPACITY", 3)
    with decoded.batch_scope():
        for v in range(5):
            decoded.decoded_view(_png(v))
        assert decoded.cached() == 3  # bounded: the oldest go first


def test_an_onboarding_batch_decodes_each_view_once(tmp_path, offline_models, monkeypatch):
    """Caption, both image encoders and the local features read every view: one decode each, and the
    store's rows are those of a run that decodes in every stage."""
    lib = copy_ycb(tmp_path / "lib", ["061_foam_brick"])
    calls = []
    real = render.decode_png
    monkeypatch.setattr(render, "decode_png", lambda data: calls.append(len(data)) or real(data))
    onboard(lib, tmp_path / "shared", offline_models)
    n_views = Store.open(tmp_path / "shared").read("views").num_rows
    assert n_views > 0 and len(calls) == n_views, (len(calls), n_views)
    assert decoded.cached() == 0  # nothing held after the run

    monkeypatch.setattr(decoded, "batch_scope", _no_sharing)
    calls.clear()
    onboard(lib, tmp_path / "each", offline_models)
    assert len(calls) > 2 * n_views  # the old way: every stage decodes again
    assert content(tmp_path / "shared") == content(tmp_path / "each")


class _no_sharing:
    def __enter__(self) -> None:
        return None

    def __exit__(self, *exc) -> None:
        return None
