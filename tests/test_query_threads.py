"""The Python API under concurrency: N threads share one Retriever (no "connection is busy"), and a
reopened Retriever sees meshes committed after the first one opened."""

from __future__ import annotations

from concurrent.futures import ThreadPoolExecutor

import numpy as np
from query_helpers import fake_models, make_fake_store, object_image

from pipeline.query import Retriever


def photo(colour: str, w: int, h: int):
    img = object_image(colour, w, h, pad=30)
    return img, np.abs(np.asarray(img, np.int16) - 205).sum(axis=2) > 30


QUERIES = [
    ("red", 44, 52, "the red can", "red_can"),
    ("yellow", 30, 72, "the yellow bottle", "yellow_bottle"),
    ("blue", 82, 40, "the blue box", "blue_box"),
    ("green", 40, 50, "the green can", "green_can"),
]


def test_many_threads_share_one_retriever(tmp_path):
    store = make_fake_store(tmp_path / "store")
    with Retriever.open(store, models=fake_models(), use_cache=False) as r:

        def ask(i: int) -> str:
            colour, w, h, prompt, _ = QUERIES[i % len(QUERIES)]
            img, mask = photo(colour, w, h)
            result = r.query(img, prompt, mask=mask, top=2)
            r.candidate_views([result.best.mesh_id])  # the shared store connection too
            return result.best.name

        with ThreadPoolExecutor(max_workers=8) as pool:
            names = list(pool.map(ask, range(64)))
        assert names == [QUERIES[i % len(QUERIES)][4] for i in range(64)]
        assert len(r.text_filter._all) >= 1


def test_reopened_sees_new_commits_and_shares_models(tmp_path):
    from serve_helpers import add_fake_mesh

    store = make_fake_store(tmp_path / "store")
    with Retriever.open(store, models=fake_models(), use_cache=False) as r:
        assert not r.is_stale() and r.n_meshes == 4
        add_fake_mesh(store, "purple_thing", (120, 40, 160), 40, 60)
        assert r.is_stale()
        with r.reopened() as r2:
            assert r2.n_meshes == 5 and not r2.is_stale()
            assert r2.model("text_encoder") is r.model("text_encoder")
            assert "purple_thing" in [r2.mesh(m)["name"] for m in r2.mesh_ids]
