"""The labelled real-photo queries (data/queries) and the data-root paths they use."""

from __future__ import annotations

import json

import numpy as np
import pytest
from conftest import REPO, SHARED_DATA, need_shared
from PIL import Image

from pipeline.evaluate.datasets import QueryFileError, drop_mask, load_queries

PHOTOS = REPO / "data" / "queries" / "ycb_photos.jsonl"


def test_data_root_paths(tmp_path, monkeypatch):
    img = tmp_path / "root" / "photos" / "a.png"
    img.parent.mkdir(parents=True)
    Image.new("RGB", (8, 8)).save(img)
    q = tmp_path / "q.jsonl"
    q.write_text(
        json.dumps({"image": "$OSCAR_SHARED_DATA/photos/a.png", "prompt": "x", "expected": "m"}) + "\n"
    )
    monkeypatch.setenv("OSCAR_SHARED_DATA", str(tmp_path / "root"))
    assert load_queries(q)[0].image == str(img.resolve())
    monkeypatch.delenv("OSCAR_SHARED_DATA")
    with pytest.raises(QueryFileError, match="OSCAR_SHARED_DATA is not set"):
        load_queries(q)


def test_drop_mask_keeps_or_derives_the_box(tmp_path, monkeypatch):
    m = np.zeros((20, 30), np.uint8)
    m[5:10, 7:19] = 255
    Image.fromarray(m).save(tmp_path / "m.png")
    Image.new("RGB", (30, 20)).save(tmp_path / "i.png")
    rows = [
        {"image": "i.png", "prompt": "a", "expected": "m", "mask": "m.png"},
        {"image": "i.png", "prompt": "b", "expected": "m", "mask": "m.png", "box": [1, 2, 25, 18]},
    ]
    (tmp_path / "q.jsonl").write_text("".join(json.dumps(r) + "\n" for r in rows))
    a, b = (drop_mask(q) for q in load_queries(tmp_path / "q.jsonl"))
    assert a.mask is None and a.box == (7.0, 5.0, 19.0, 10.0)
    assert b.mask is None and b.box == (1.0, 2.0, 25.0, 18.0)


def test_labelled_photo_masks_are_small_binary_and_inside_their_boxes(monkeypatch):
    need_shared(SHARED_DATA / "photos")
    monkeypatch.setenv("OSCAR_SHARED_DATA", str(SHARED_DATA))
    queries = load_queries(PHOTOS)
    assert len(queries) == 21 and all(q.mask and q.box for q in queries)
    for q in queries:
        with Image.open(q.mask) as im:
            assert im.mode == "1" and im.size == (640, 480)
            m = np.asarray(im, dtype=bool)
        assert m.sum() > 1500, q.query_id
        x0, y0, x1, y1 = (int(v) for v in q.box)
        inside = m[max(0, y0 - 6) : y1 + 6, max(0, x0 - 6) : x1 + 6].sum()
        assert inside >= 0.97 * m.sum(), q.query_id  # the hand box holds the mask (a few pixels of slack)
    total = sum(p.stat().st_size for p in (REPO / "data" / "queries" / "masks").glob("*.png"))
    assert total < 200_000
