"""End-to-end onboarding on real YCB meshes with the offline profile: tables, schemas, incremental runs."""

from __future__ import annotations

import json
import shutil

import numpy as np
import pyarrow.compute as pc
import pytest
from conftest import copy_ycb
from onboard_helpers import V, content, onboard

from pipeline import schemas
from pipeline.mesh.render import decode_png
from pipeline.store import Store

MESHES = ["005_tomato_soup_can", "011_banana", "061_foam_brick"]


@pytest.fixture(scope="module")
def built(tmp_path_factory, offline_models):
    root = tmp_path_factory.mktemp("ycb3")
    lib = copy_ycb(root / "lib", MESHES)
    store = root / "store"
    summary = onboard(lib, store, offline_models)
    return lib, store, summary


def test_tables_schemas_and_counts(built):
    _, store, summary = built
    assert summary.rendered == 3 and summary.failed == 0 and summary.added == 3
    s = Store.open(store)
    meshes = s.read("meshes")
    assert meshes.schema.equals(schemas.MESHES)
    assert meshes.num_rows == 3 and set(meshes.column("status").to_pylist()) == {"active"}
    assert sorted(meshes.column("name").to_pylist()) == sorted(MESHES)
    assert set(meshes.column("units_guess").to_pylist()) == {"m"}
    assert all(n == 16384 for n in meshes.column("n_faces").to_pylist())
    views = s.read("views")
    assert views.schema.equals(schemas.VIEWS) and views.num_rows == 3 * V
    assert s.read("captions").num_rows == 3 * V
    for table in ("text_embeddings", "image_embeddings"):
        (dataset,) = s.datasets(table)
        emb = s.read(dataset)
        assert emb.num_rows == 3 * V
        dim = emb.column("dim")[0].as_py()
        assert emb.schema.equals(schemas.embedding_schema(dim))
        vecs = np.stack(emb.column("embedding").to_numpy(zero_copy_only=False))
        assert np.allclose(np.linalg.norm(vecs, axis=1), 1.0, atol=1e-4)
    runs = s.read("runs")
    assert runs.num_rows == 1 and runs.column("status")[0].as_py() == "ok"


def test_view_features_stage(built):
    _, store, _ = built
    s = Store.open(store)
    feats = s.read("view_features")
    assert feats.schema.equals(schemas.VIEW_FEATURES) and feats.num_rows == 3 * V
    fp = json.loads(s.read("runs").column("config_json")[0].as_py())["fingerprints"]["features"]
    assert set(feats.column("fingerprint").to_pylist()) == {fp}
    n = feats.column("n_keypoints").to_numpy()
    assert (n >= 5).all() and (n <= 256).all() and n.max() > 100
    sizes = [len(b) for b in feats.column("descriptors").to_pylist()]
    assert sizes == [k * 128 for k in n.tolist()]


def test_feature_config_change_recomputes_only_features(tmp_path, offline_models):
    from pipeline.localfeat import FeatureConfig

    lib = copy_ycb(tmp_path / "lib", MESHES[:1])
    store = tmp_path / "store"
    onboard(lib, store, offline_models)
    before = content(store, lambda d: d.split("/")[0] not in ("runs", "view_features"))
    summary = onboard(lib, store, offline_models, features=FeatureConfig(max_keypoints=64))
    assert summary.rendered == 0 and summary.captioned == 0 and summary.skipped == 0
    assert content(store, lambda d: d.split("/")[0] not in ("runs", "view_features")) == before
    s = Store.open(store)
    assert s.read("view_features").num_rows == 2 * V
    runs = s.read("runs").sort_by("run_id").column("config_json").to_pylist()
    fp64 = json.loads(runs[-1])["fingerprints"]["features"]
    new = s.read("view_features", filter=pc.field("fingerprint") == fp64)
    assert new.num_rows == V and max(new.column("n_keypoints").to_pylist()) <= 64
    # detector "none": no features stage at all
    summary = onboard(lib, store, offline_models, features=FeatureConfig(detector="none"))
    assert summary.skipped == 1 and Store.open(store).read("view_features").num_rows == 2 * V


def test_views_layout_and_object_centred(built):
    _, store, _ = built
    views = Store.open(store).read("views")
    elev = sorted(set(views.column("elevation_deg").to_pylist()))
    assert elev == [-15.0, 15.0, 45.0]  # the offline profile's rings
    for row in views.to_pylist():
        img = np.asarray(decode_png(row["image"])).astype(int)
        assert img.shape == (512, 512, 3)
        fg = np.abs(img - 205).sum(axis=2) > 12
        frac = fg.mean()
        assert 0.02 < frac < 0.9, f"view {row['view_index']} looks blank or overfull ({frac:.3f})"
        ys, xs = np.nonzero(fg)
        cx, cy = (xs.min() + xs.max()) / 2, (ys.min() + ys.max()) / 2
        assert abs(cx - 256) < 12 and abs(cy - 256) < 12, "object not centred"
        # fitted framing: the object spans most of the frame in at least one direction
        assert max(xs.max() - xs.min(), ys.max() - ys.min()) > 0.75 * 512
        pose = np.array(row["camera_pose"]).reshape(4, 4)
        assert np.allclose(pose[:3, :3] @ pose[:3, :3].T, np.eye(3), atol=1e-6)


def test_captions_are_sentences(built):
    _, store, _ = built
    caps = Store.open(store).read("captions")
    texts = caps.column("caption").to_pylist()
    assert all(isinstance(t, str) and len(t.split()) >= 4 for t in texts)
    assert set(caps.column("prompt_style").to_pylist()) == {"attributes"}


def test_unchanged_rerun_does_no_work(built, offline_models, monkeypatch):
    lib, store, _ = built
    import pipeline.mesh.discover as discover

    def no_hash(*a, **k):
        raise AssertionError("unchanged files must not be re-hashed")

    monkeypatch.setattr(discover, "content_hash", no_hash)
    before = content(store)
    versions = Store.open(store).versions()
    summary = onboard(lib, store, offline_models)
    assert (summary.rendered, summary.captioned, summary.added, summary.removed, summary.failed) == (
        0,
        0,
        0,
        0,
        0,
    )
    assert summary.skipped == 3 and summary.hashed == 0
    assert content(store) == before
    after = Store.open(store).versions()  # a run with nothing to do commits only its runs row
    assert after == {**versions, "runs": versions["runs"] + 1}


def test_modified_added_removed_files(tmp_path, offline_models):
    lib = copy_ycb(tmp_path / "lib", MESHES[:2])
    store = tmp_path / "store"
    onboard(lib, store, offline_models)
    s = Store.open(store)
    old_ids = {r["name"]: r["mesh_id"] for r in s.read("meshes").to_pylist()}

    # modify one mesh (content changes -> new mesh_id), remove another, add a third
    obj = lib / MESHES[0] / "textured.obj"
    obj.write_text(obj.read_text().replace("v ", "v  ", 1))
    shutil.rmtree(lib / MESHES[1])
    copy_ycb(lib, [MESHES[2]])
    summary = onboard(lib, store, offline_models, allow_removal=True)  # 1 of 2 vanished: over the guard
    assert summary.added == 2 and summary.removed == 2 and summary.rendered == 2

    from pipeline.onboard.plan import mesh_state

    state = mesh_state(Store.open(store), str(lib.resolve())).to_pylist()
    active = {r["name"]: r["mesh_id"] for r in state if r["status"] == "active"}
    removed = {r["mesh_id"] for r in state if r["status"] == "removed"}
    assert set(active) == {MESHES[0], MESHES[2]}
    assert active[MESHES[0]] != old_ids[MESHES[0]]
    assert removed == {old_ids[MESHES[0]], old_ids[MESHES[1]]}

    # a texture change alone also changes the mesh_id (the hash covers referenced files)
    tex = lib / MESHES[2] / "texture_map.jpg"
    tex.write_bytes(tex.read_bytes() + b"\0")
    summary = onboard(lib, store, offline_models)
    assert summary.added == 1 and summary.removed == 1


def test_force_and_config_change_redo_only_their_stages(tmp_path, offline_models):
    lib = copy_ycb(tmp_path / "lib", MESHES[:1])
    store = tmp_path / "store"
    onboard(lib, store, offline_models)
    views_before = Store.open(store).read("views").num_rows

    # a new prompt style re-captions and re-embeds captions but does not re-render
    summary = onboard(lib, store, offline_models, prompt_style="comma")
    assert summary.rendered == 0 and summary.captioned == 1
    s = Store.open(store)
    assert s.read("views").num_rows == views_before
    assert sorted(set(s.read("captions").column("prompt_style").to_pylist())) == ["attributes", "comma"]
    (text_ds,) = s.datasets("text_embeddings")
    assert s.read(text_ds).num_rows == 2 * V

    # --force caption redoes captions (superseding rows with the same key), not rendering
    summary = onboard(lib, store, offline_models, prompt_style="comma", force=("caption",))
    assert summary.rendered == 0 and summary.captioned == 1
    s = Store.open(store)
    assert s.read("captions").num_rows == 3 * V
    assert s.read_latest("captions").num_rows == 2 * V

    summary = onboard(lib, store, offline_models, prompt_style="comma", force=("render",))
    assert summary.rendered == 1
    assert Store.open(store).read_latest("views").num_rows == V


def test_cap3d_camera_layout(tmp_path, offline_models):
    lib = copy_ycb(tmp_path / "lib", MESHES[:1])
    store = tmp_path / "store"
    from pipeline.mesh.settings import RenderConfig

    cfg = RenderConfig(cameras="cap3d", resolution=128, extra_bg_view=True)
    assert cfg.fingerprint() != RenderConfig(cameras="cap3d", resolution=128).fingerprint()
    assert RenderConfig().fingerprint() == RenderConfig(extra_bg_view=False).fingerprint()
    onboard(lib, store, offline_models, render=cfg)
    s = Store.open(store)
    views = s.read("views").sort_by("view_index")
    assert views.num_rows == 9  # the 8 Cap3D views + the extra background view
    assert pc.max(views.column("width")).as_py() == 128
    elev = views.column("elevation_deg").to_pylist()
    assert min(elev) < -20 and max(elev) > 20  # cap3d has views below and above the object
    rows = views.to_pylist()
    assert rows[8]["camera_pose"] == rows[0]["camera_pose"]  # view 0's camera ...
    bg = np.asarray(decode_png(rows[8]["image"]))
    assert bg[0, 0].tolist() == [0, 0, 0] and np.asarray(decode_png(rows[0]["image"]))[0, 0].tolist() == [
        205,
        205,
        205,
    ]  # ... on black instead of gray
    assert sorted(s.read("captions").column("view_index").to_pylist()) == list(range(8))  # not captioned
    (img_ds,) = s.datasets("image_embeddings")
    assert sorted(s.read(img_ds).column("view_index").to_pylist()) == list(range(9))  # a stage-2 view
