"""The synthetic query generator: exact masks, novel viewpoints, seeded determinism, prompts and labels."""

from __future__ import annotations

import json
import math
from pathlib import Path

import numpy as np
import pytest
from PIL import Image

from pipeline.evaluate.library import class_of, read_folder_meshes
from pipeline.evaluate.prompts import prompt_for, readable_name
from pipeline.evaluate.synth import SynthConfig, generate, mesh_rng, sample_views

SMALL = {"width": 160, "height": 120}
TOY = {
    "001_red_box": ("box", (220, 30, 30)),
    "002_blue_can": ("cylinder", (30, 60, 220)),
    "003_yellow_ball": ("sphere", (230, 210, 30)),
}


def make_toy_library(root: Path, names=tuple(TOY)) -> Path:
    """Tiny coloured primitives as PLY files (load in milliseconds, unlike the textured YCB scans)."""
    import trimesh

    for name in names:
        kind, colour = TOY[name]
        mesh = {
            "box": lambda: trimesh.creation.box(extents=(0.06, 0.1, 0.2)),
            "cylinder": lambda: trimesh.creation.cylinder(radius=0.035, height=0.1, sections=32),
            "sphere": lambda: trimesh.creation.icosphere(subdivisions=2, radius=0.04),
        }[kind]()
        mesh.visual.vertex_colors = np.tile([*colour, 255], (len(mesh.vertices), 1)).astype(np.uint8)
        (root / name).mkdir(parents=True, exist_ok=True)
        mesh.export(root / name / "mesh.ply")
    return root


@pytest.fixture(scope="module")
def two_meshes(tmp_path_factory):
    root = make_toy_library(tmp_path_factory.mktemp("toy"), ("001_red_box", "002_blue_can"))
    meshes = read_folder_meshes(root)
    assert [m.name for m in meshes] == ["001_red_box", "002_blue_can"]
    return meshes


def _load(out: Path) -> list[dict]:
    return [json.loads(line) for line in (out / "queries.jsonl").read_text().splitlines()]


def test_masks_are_exact_and_boxes_match(tmp_path, two_meshes):
    cfg = SynthConfig(per_mesh=2, seed=3, backgrounds=("solid",), **SMALL)
    queries = generate(two_meshes, tmp_path, cfg)
    assert len(queries) == 4
    for q in queries:
        img = np.asarray(Image.open(q.image).convert("RGB"))
        mask = np.asarray(Image.open(q.mask)) > 0
        assert img.shape[:2] == mask.shape == (120, 160)
        assert mask.any() and not mask.all()
        # a solid background: every pixel outside the mask has one colour, the object differs from it
        outside = img[~mask]
        assert (outside == outside[0]).all()
        assert (img[mask] != outside[0]).any(axis=1).mean() > 0.9
        ys, xs = np.nonzero(mask)
        assert q.box == (xs.min(), ys.min(), xs.max() + 1, ys.max() + 1)


def test_same_seed_same_queries_other_seed_differs(tmp_path, two_meshes):
    cfg = SynthConfig(per_mesh=2, seed=7, backgrounds=("gradient", "noise"), **SMALL)
    a, b, c = tmp_path / "a", tmp_path / "b", tmp_path / "c"
    generate(two_meshes, a, cfg)
    generate(two_meshes, b, cfg)
    generate(two_meshes, c, SynthConfig(per_mesh=2, seed=8, backgrounds=("gradient", "noise"), **SMALL))
    qa, qb, qc = _load(a), _load(b), _load(c)
    assert [q["meta"] for q in qa] == [q["meta"] for q in qb]
    for q in qa:
        for key in ("image", "mask"):
            assert (a / q[key]).read_bytes() == (b / q[key]).read_bytes()
    assert [q["meta"]["azimuth_deg"] for q in qa] != [q["meta"]["azimuth_deg"] for q in qc]


def test_a_mesh_queries_do_not_depend_on_the_other_meshes(two_meshes):
    cfg = SynthConfig(per_mesh=3, seed=1)
    alone = sample_views(cfg, mesh_rng(cfg.seed, two_meshes[0].source_path))
    again = sample_views(cfg, mesh_rng(cfg.seed, two_meshes[0].source_path))
    other = sample_views(cfg, mesh_rng(cfg.seed, two_meshes[1].source_path))
    assert alone == again
    assert alone != other


def test_viewpoints_avoid_the_onboarding_views():
    from pipeline.mesh.cameras import view_directions

    cfg = SynthConfig(per_mesh=200, seed=0, min_view_separation_deg=12.0)
    onboard = np.stack([d for _, _, d in view_directions(cfg.onboarding)])
    for v in sample_views(cfg, np.random.default_rng(0)):
        az, el = math.radians(v.azimuth_deg), math.radians(v.elevation_deg)
        d = np.array([math.cos(el) * math.cos(az), math.cos(el) * math.sin(az), math.sin(el)])
        assert math.degrees(math.acos(min(1.0, float(np.max(onboard @ d))))) >= 12.0 - 1e-6
        assert cfg.elevation_deg[0] <= v.elevation_deg <= cfg.elevation_deg[1]
        assert cfg.fill[0] <= v.fill <= cfg.fill[1]


def test_prompts_and_class_labels_from_mesh_names():
    assert readable_name("006_mustard_bottle") == "mustard bottle"
    assert readable_name("065-a_cups") == "cups"
    assert prompt_for("006_mustard_bottle") == "the mustard bottle"
    assert prompt_for("011_banana", "a photo of a {name} ({raw})") == "a photo of a banana (011_banana)"
    assert prompt_for("hope_000002", names={"hope_000002": "bbq sauce bottle"}) == "the bbq sauce bottle"
    assert class_of("065-a_cups") == "065"
    assert class_of("hope_000002") == "hope_000002"
    assert class_of("073-b_lego_duplo", r"^\d+-?[a-z]?") == "073-b"


def test_photo_backgrounds_need_a_folder():
    assert "photo" not in SynthConfig().backgrounds  # dropped without --photo-dir
    with pytest.raises(ValueError, match="background"):
        SynthConfig(backgrounds=("sky",))


def test_mask_growth_is_chosen_per_set(tmp_path):
    """``--mask-grow``: the harder set's query masks grow, stay exact or shrink; the images do not change."""
    from pipeline.evaluate.synth_cli import main

    lib = make_toy_library(tmp_path / "lib", ("001_red_box",))
    base = ["--library", str(lib), "--per-mesh", "2", "--seed", "5", "--size", "160x120", "--hard"]
    base += ["--backgrounds", "noise", "--no-progress"]
    sets = {}
    for name, grow in (("grown", "3,3"), ("exact", "0,0"), ("shrunk", "-2,-2")):  # "=" lets "-2" be a value
        assert main([*base, "--out", str(tmp_path / name), f"--mask-grow={grow}"]) == 0
        sets[name] = _load(tmp_path / name)
    assert main([*base, "--out", str(tmp_path / "default")]) == 0
    assert {q["meta"]["mask_grow_px"] for q in _load(tmp_path / "default")} <= set(range(5))

    def pixels(name: str, q: dict) -> int:
        return int((np.asarray(Image.open(tmp_path / name / q["mask"])) > 0).sum())

    for grown, exact, shrunk in zip(sets["grown"], sets["exact"], sets["shrunk"], strict=True):
        assert (grown["meta"]["mask_grow_px"], exact["meta"]["mask_grow_px"]) == (3, 0)
        assert shrunk["meta"]["mask_grow_px"] == -2
        assert (tmp_path / "grown" / grown["image"]).read_bytes() == (
            tmp_path / "exact" / exact["image"]
        ).read_bytes()
        assert pixels("grown", grown) > pixels("exact", exact) > pixels("shrunk", shrunk) > 0
        assert exact["box"] == grown["box"]  # ranges of one width draw alike: the box is the visible object's


@pytest.mark.parametrize(
    "args, message",
    [(["--hard", "--mask-grow", "4,1"], "LO <= HI"), (["--mask-grow", "0,0"], "needs --hard"),
     (["--hard", "--mask-grow", "0,99"], "99")],
)  # fmt: skip
def test_mask_growth_refuses_bad_ranges(tmp_path, capsys, args, message):
    from pipeline.evaluate.synth_cli import main

    lib = make_toy_library(tmp_path / "lib", ("001_red_box",))
    try:
        code = main(["--library", str(lib), "--out", str(tmp_path / "out"), "--no-progress", *args])
    except SystemExit as exc:  # argparse's own refusals
        code = exc.code
    assert code == 2
    err = capsys.readouterr().err
    assert message in err and len(err.strip().splitlines()) == 1
    assert not (tmp_path / "out" / "queries.jsonl").exists()
