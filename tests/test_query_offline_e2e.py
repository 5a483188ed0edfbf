"""End to end with the offline profile: onboard a few real YCB meshes, render each from a viewpoint that
is not one of its onboarding views, and query with that render and its mask: the mesh must come first."""

from __future__ import annotations

import json

import pytest
from conftest import copy_ycb
from onboard_helpers import onboard
from query_helpers import render_query_view

from pipeline.query import Retriever
from pipeline.query.fusion import FusionWeights

#: two look-alike cups (colour tells them apart), a mug, two boxes and a bottle
YCB_NAMES = ["065-a_cups", "065-b_cups", "025_mug", "004_sugar_box", "008_pudding_box", "021_bleach_cleanser"]


@pytest.fixture(scope="module")
def ycb_store(tmp_path_factory, offline_models):
    root = tmp_path_factory.mktemp("ycb_query")
    library = copy_ycb(root / "library", YCB_NAMES)
    onboard(library, root / "store", models=offline_models, render=_render_config())
    return root / "store", library


def _render_config():
    from pipeline.mesh.settings import RenderConfig

    return RenderConfig(resolution=192)  # smaller renders keep the test fast; same layout as the default


@pytest.fixture(scope="module")
def queries(ycb_store, tmp_path_factory):
    """name -> (photo path, mask path) of a novel view (azimuth 20, elevation 8) of each mesh."""
    from PIL import Image

    _, library = ycb_store
    out = tmp_path_factory.mktemp("ycb_photos")
    photos = {}
    for name in YCB_NAMES:
        img, mask = render_query_view(
            library / name / "google_16k" / "textured.obj" if False else _mesh(library, name)
        )
        img.save(out / f"{name}.png")
        Image.fromarray(mask).save(out / f"{name}_mask.png")
        photos[name] = (out / f"{name}.png", out / f"{name}_mask.png")
    return photos


def _mesh(library, name):
    return next(p for p in sorted((library / name).rglob("*.obj")))


def prompt_of(name: str) -> str:
    return "the " + " ".join(name.split("_")[1:])


def test_novel_view_with_mask_returns_the_mesh_first(ycb_store, queries, offline_models):
    store, _ = ycb_store
    with Retriever.open(store, profile="offline", models=offline_models) as r:
        assert r.n_meshes == len(YCB_NAMES)
        ranks = {}
        for name, (photo, mask) in queries.items():
            result = r.query(str(photo), prompt_of(name), mask=str(mask), top=len(YCB_NAMES))
            ranks[name] = [c.name for c in result.candidates].index(name) + 1
            assert (
                result.candidates[0].text_score is not None and result.candidates[0].image_score is not None
            )
    assert ranks == {name: 1 for name in YCB_NAMES}


def test_local_feature_verification(ycb_store, queries, offline_models):
    store, _ = ycb_store
    # the plain fusion's arithmetic (the store's query adapter, which ranks by the adapted cosine with its
    # own weights, is off here: tests/test_adapter_store.py)
    plain = {"adapter": False}
    with Retriever.open(store, profile="offline", models=offline_models, settings_changes=plain) as r:
        assert r.tables.adapter is not None and r.settings.verify and r.verifier.available
        photo, mask = queries["004_sugar_box"]
        roi = r.make_roi(str(photo), "the sugar box", mask=str(mask))
        emb = r.embed(roi, "the sugar box")
        assert emb.local is not None and len(emb.local) > 50
        on = r.rank(emb, "image-only", top=len(YCB_NAMES))
        best = on.candidates[0]
        assert best.name == "004_sugar_box" and best.inliers >= 15
        # image-only fusion: the learned and descriptor weights rescaled to sum to 1, then the inlier bonus
        s = r.settings
        wl, wd = FusionWeights.of(s).learned, s.fuse_desc
        base = (wl * best.learned_score + wd * best.image_score) / (wl + wd)
        # (its weight is fuse_verify_weight when fusing, verify_weight without the learned encoder)
        bonus = r.verifier.cfg.bonus(best.inliers, s.fuse_verify_weight)
        assert bonus > 0 and best.score == pytest.approx(base + bonus, abs=1e-5)
        assert "verify_ms" in on.timings and emb.inliers  # cached on the embedding
        assert max(c.inliers for c in on.candidates[1:]) < best.inliers
        off = r.rank(emb, "image-only", top=len(YCB_NAMES), verify=False)
        assert all(c.inliers is None for c in off.candidates)
        assert all(c.score is not None and c.learned_score is not None for c in off.candidates)  # fused
    with Retriever.open(
        store, profile="offline", models=offline_models, settings_changes={"verify": False, **plain}
    ) as r:
        emb = r.embed(r.make_roi(str(photo), "the sugar box", mask=str(mask)), "the sugar box")
        assert emb.local is None
    with Retriever.open(
        store, profile="offline", models=offline_models, settings_changes={"fuse_verify_weight": 0.0, **plain}
    ) as r:
        emb = r.embed(r.make_roi(str(photo), "the sugar box", mask=str(mask)), "the sugar box")
        best = r.rank(emb, "image-only", top=3).candidates[0]
        assert best.inliers >= 15 and best.score == pytest.approx(base, abs=1e-5)  # no bonus at weight 0


def test_a_query_background_other_than_the_renders_is_refused(ycb_store, offline_models):
    """The ROI is pasted on the query setting's background; the encoders read the views' background as
    "not the object", so another colour is refused in one line instead of ranking a whole-ROI object."""
    from pipeline.query import QueryError

    store, _ = ycb_store
    with pytest.raises(QueryError) as exc:
        Retriever.open(
            store, profile="offline", models=offline_models, settings_changes={"background": (0, 0, 0)}
        )
    msg = str(exc.value)
    assert "\n" not in msg and "(0, 0, 0)" in msg and "(205, 205, 205)" in msg and str(store) in msg
    with Retriever.open(
        store, profile="offline", models=offline_models, settings_changes={"background": [205, 205, 205]}
    ) as r:  # the same colour spelled as a list is the same background
        assert r.n_meshes == len(YCB_NAMES)


def test_cli_end_to_end_with_explain_and_export(
    ycb_store, queries, offline_models, monkeypatch, capsys, tmp_path
):
    import pipeline.models.registry as registry
    from pipeline.query.cli import main

    monkeypatch.setattr(registry, "create_model", lambda role, spec, **kw: offline_models[role])
    store, library = ycb_store
    photo, mask = queries["025_mug"]
    argv = ["--store", str(store), "--image", str(photo), "--prompt", "the red mug", "--mask", str(mask)]
    argv += [
        "--json",
        "--explain",
        str(tmp_path / "sheet.png"),
        "--export",
        str(tmp_path / "export"),
        "--top",
        "3",
    ]
    assert main(argv) == 0
    data = json.loads(capsys.readouterr().out)
    assert data["candidates"][0]["name"] == "025_mug" and data["query"]["profile"] == "offline"
    assert (tmp_path / "sheet.png").stat().st_size > 10_000
    exported = {p.rsplit("/", 1)[-1] for p in data["exported_files"]}
    mesh_files = {p.name for p in (library / "025_mug").rglob("*") if p.is_file()}
    assert exported == mesh_files | {"model_info.json"}  # the mesh with its materials, plus the hand-off info
    box_argv = [
        "--store",
        str(store),
        "--image",
        str(photo),
        "--prompt",
        "the red mug",
        "--box",
        "10,10,250,250",
    ]
    assert main(box_argv) == 0
    out = capsys.readouterr().out
    assert (
        "GrabCut" in out
        and out.splitlines()[
            out.splitlines().index(next(x for x in out.splitlines() if x.lstrip().startswith("rank"))) + 1
        ].split()[1]
        == "025_mug"
    )
