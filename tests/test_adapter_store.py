"""The per-store query adapter end to end: onboarding embeds probes and fits it, a rerun keeps it, a query
applies it only when it was fitted on exactly the store's models, and the open-set verdict keeps the plain
scores (pipeline/adapter, pipeline/query/steps/learned.py)."""

from __future__ import annotations

import shutil

import numpy as np
import pyarrow as pa
import pytest
from conftest import SAMPLE_LIBRARY
from onboard_helpers import onboard
from PIL import Image
from query_helpers import render_query_view

from pipeline import schemas
from pipeline.adapter.probes import ProbeConfig
from pipeline.adapter.table import matrix_of
from pipeline.query import Retriever
from pipeline.store import Store, utcnow

NAMES = ["003_cracker_box", "005_tomato_soup_can", "006_mustard_bottle", "011_banana"]


def render_cfg():
    from pipeline.mesh.settings import RenderConfig

    return RenderConfig(resolution=192)


@pytest.fixture(scope="module")
def query_photo(tmp_path_factory):
    out = tmp_path_factory.mktemp("adapter_query")
    mesh = next((SAMPLE_LIBRARY / "006_mustard_bottle").rglob("*.obj"))
    img, mask = render_query_view(mesh)
    img.save(out / "q.png")
    Image.fromarray(mask).save(out / "m.png")
    return str(out / "q.png"), str(out / "m.png")


def library(root, names):
    for n in names:
        shutil.copytree(SAMPLE_LIBRARY / n, root / n)
    return root


def adapter_rows(store) -> list[dict]:
    s = Store.open(store)
    return s.read("adapters").to_pylist() if s.dataset("adapters") is not None else []


def ask(store, models, photo, **changes):
    with Retriever.open(store, profile="offline", models=models, settings_changes=changes or None) as r:
        return r.query(photo[0], "the mustard bottle", mask=photo[1], top=4)


def test_onboarding_fits_the_adapter_and_queries_rank_with_it(tmp_path, offline_models, query_photo):
    lib = library(tmp_path / "lib", NAMES)
    store = tmp_path / "store"
    onboard(lib, store, models=offline_models, render=render_cfg())
    s = Store.open(store)
    (probes,) = s.datasets("probe_embeddings")
    t = s.read(probes)
    assert t.num_rows == 4 * ProbeConfig().per_mesh and set(t.column("mesh_id").to_pylist()) == set(
        s.read("meshes").column("mesh_id").to_pylist()
    )
    (row,) = adapter_rows(store)
    assert row["n_models"] == 4 and row["n_probes"] == 24 and row["dim"] == 384
    matrix = matrix_of(row)
    assert matrix.shape == (384, 384) and not np.allclose(matrix, np.eye(384))

    onboard(lib, store, models=offline_models, render=render_cfg())  # nothing changed: nothing refitted
    assert len(adapter_rows(store)) == 1

    on = ask(store, offline_models, query_photo)
    off = ask(store, offline_models, query_photo, adapter=False)
    assert on.adapted and not off.adapted and on.to_dict()["adapted"] is True
    assert on.best.name == "006_mustard_bottle" and off.best.name == "006_mustard_bottle"
    # the candidates' learned cosine is the plain one either way; the ranking score is the adapted fusion
    assert on.best.learned_score == pytest.approx(off.best.learned_score, abs=1e-6)
    assert on.best.score != pytest.approx(off.best.score, abs=1e-6)
    if [c.name for c in on.candidates[:2]] == [c.name for c in off.candidates[:2]]:
        # same top two: the verdict reads the same plain features, so the same confidence
        assert on.confidence == pytest.approx(off.confidence, abs=1e-9)
    assert not any("adapter" in n for n in on.notes)


def test_a_run_that_stops_before_the_fit_leaves_the_adapter_unused(
    tmp_path, offline_models, query_photo, monkeypatch
):
    lib = library(tmp_path / "lib", NAMES[:3])
    store = tmp_path / "store"
    onboard(lib, store, models=offline_models, render=render_cfg())
    assert ask(store, offline_models, query_photo).adapted

    shutil.copytree(SAMPLE_LIBRARY / NAMES[3], lib / NAMES[3])

    def stop(*a, **k):
        raise KeyboardInterrupt

    monkeypatch.setattr("pipeline.adapter.table.refresh", stop)
    with pytest.raises(KeyboardInterrupt):
        onboard(lib, store, models=offline_models, render=render_cfg())
    monkeypatch.undo()
    # the new mesh's rows are committed, the adapter was fitted on three models: not used, and said so
    res = ask(store, offline_models, query_photo)
    assert not res.adapted and res.best.name == "006_mustard_bottle"
    assert any("fitted on other models" in n for n in res.notes)

    onboard(lib, store, models=offline_models, render=render_cfg())  # finishes: refits on four
    assert sorted(r["n_models"] for r in adapter_rows(store)) == [3, 4]
    assert ask(store, offline_models, query_photo).adapted


def test_a_damaged_adapter_row_is_not_used(tmp_path, offline_models, query_photo):
    lib = library(tmp_path / "lib", NAMES[:2] + NAMES[2:3])
    store = tmp_path / "store"
    onboard(lib, store, models=offline_models, render=render_cfg())
    (row,) = adapter_rows(store)
    bad = {**row, "matrix": row["matrix"][:100], "run_id": row["run_id"] + "z", "created_at": utcnow()}
    with Store.open(store, writable=True) as s:
        runs = s.read("runs").sort_by([("run_id", "descending")]).slice(0, 1).to_pylist()
        # queries read the store as of its latest run (pipeline.snapshot): commit the row with a run record
        s.commit(
            {
                "adapters": pa.Table.from_pylist([bad], schema=schemas.ADAPTERS),
                "runs": pa.Table.from_pylist([{**runs[0], "run_id": bad["run_id"]}], schema=schemas.RUNS),
            },
            bad["run_id"],
        )
    res = ask(store, offline_models, query_photo)
    assert not res.adapted and any("damaged" in n for n in res.notes)
    onboard(lib, store, models=offline_models, render=render_cfg())  # nothing else changed: it refits
    assert len(adapter_rows(store)) == 3 and ask(store, offline_models, query_photo).adapted


def test_probes_off_means_no_adapter(tmp_path, offline_models, query_photo):
    lib = library(tmp_path / "lib", NAMES[:3])
    store = tmp_path / "store"
    onboard(lib, store, models=offline_models, render=render_cfg(), probes=ProbeConfig(per_mesh=0))
    s = Store.open(store)
    assert s.datasets("probe_embeddings") == [] and s.dataset("adapters") is None
    res = ask(store, offline_models, query_photo)
    assert not res.adapted and not any("adapter" in n for n in res.notes)
