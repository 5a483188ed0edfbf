"""Open-set answers with the offline profile's shipped calibration on real data: a small library of real
YCB meshes, queried with a real photo's masked objects; an object the library lacks is not accepted at
the default operating point."""

from __future__ import annotations

import json

import pytest
from conftest import REPO, SHARED_DATA, copy_ycb, need_shared
from onboard_helpers import onboard

from pipeline.query import Retriever

#: the library: none of them is the mustard bottle or the banana of photo 000001
LIBRARY = ["003_cracker_box", "005_tomato_soup_can", "021_bleach_cleanser", "025_mug", "065-a_cups", "077_rubiks_cube"]


@pytest.fixture(scope="module")
def store(tmp_path_factory, offline_models):
    need_shared(SHARED_DATA / "photos" / "posecnn_demo")
    root = tmp_path_factory.mktemp("openset_real")
    library = copy_ycb(root / "library", LIBRARY)
    onboard(library, root / "store", models=offline_models)
    return root / "store"


def photo_query(query_id: str) -> dict:
    for line in (REPO / "data" / "queries" / "ycb_photos.jsonl").read_text().splitlines():
        q = json.loads(line)
        if q["query_id"] == query_id:
            q["image"] = q["image"].replace("$OSCAR_SHARED_DATA", str(SHARED_DATA))
            q["mask"] = str(REPO / "data" / "queries" / q["mask"])
            return q
    raise KeyError(query_id)


@pytest.mark.parametrize("query_id", ["posecnn-000001-006", "posecnn-000001-011"])
def test_an_object_the_library_lacks_is_not_accepted(store, offline_models, query_id):
    q = photo_query(query_id)
    with Retriever.open(store, models=offline_models, use_cache=False) as r:
        res = r.query(q["image"], q["prompt"], mask=q["mask"])
    assert res.candidates and res.accepted is False, res.to_dict()["acceptance"]
    assert 0.0 <= res.confidence < res.accept_threshold
