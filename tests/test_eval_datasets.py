"""Query sets: JSONL and CSV files, BOP folders, and resolving what a query names to library meshes."""

from __future__ import annotations

import json

import numpy as np
import pytest
from PIL import Image

from pipeline.evaluate.bop import load_bop
from pipeline.evaluate.datasets import Query, QueryFileError, load_queries, write_queries
from pipeline.evaluate.library import Library, MeshRef, load_class_map

LIB = Library(
    [
        MeshRef("id-mustard", "006_mustard_bottle/textured.obj", "/lib", "006_mustard_bottle", "obj"),
        MeshRef("id-cup-a", "065-a_cups/textured.obj", "/lib", "065-a_cups", "obj"),
        MeshRef("id-cup-b", "065-b_cups/textured.obj", "/lib", "065-b_cups", "obj"),
        MeshRef("id-hope2", "hope/hope_000002.ply", "/lib", "hope_000002", "ply"),
    ]
)


def _image(path, size=(64, 48)):
    path.parent.mkdir(parents=True, exist_ok=True)
    Image.fromarray(np.zeros((size[1], size[0], 3), np.uint8)).save(path)
    return path


def test_jsonl_round_trip_with_relative_paths(tmp_path):
    _image(tmp_path / "images" / "a.png")
    _image(tmp_path / "masks" / "a.png")
    rows = [
        {
            "query_id": "a",
            "image": "images/a.png",
            "mask": "masks/a.png",
            "prompt": "the cup",
            "expected": ["065-a_cups/textured.obj", "id-cup-b"],
            "label": "065",
            "box": [1, 2, 30, 40],
        },
        {"image": "images/a.png", "prompt": "the mustard", "expected_mesh_id": "id-mustard", "scene": "s1"},
    ]
    (tmp_path / "q.jsonl").write_text("\n".join(json.dumps(r) for r in rows) + "\n# comment\n")
    qs = load_queries(tmp_path / "q.jsonl")
    assert [q.query_id for q in qs] == ["a", "q-2"]
    assert qs[0].box == (1.0, 2.0, 30.0, 40.0) and qs[0].label == "065"
    assert qs[0].mask == str((tmp_path / "masks" / "a.png").resolve())
    assert qs[1].expected == ["id-mustard"] and qs[1].meta == {"scene": "s1"}
    moved = tmp_path / "copy" / "q.jsonl"
    write_queries(qs, moved)
    again = load_queries(moved)
    assert [q.to_json() for q in again] == [q.to_json() for q in qs]


def test_csv_with_box_columns_and_joined_expected(tmp_path):
    _image(tmp_path / "x.png")
    (tmp_path / "q.csv").write_text(
        "query_id,image,prompt,x0,y0,x1,y1,expected,label\n"
        "c1,x.png,the cups,0,0,10,12,065-a_cups|065-b_cups,065\n"
        "c2,x.png,the mustard,,,,,006_mustard_bottle,\n"
    )
    qs = load_queries(tmp_path / "q.csv")
    assert qs[0].box == (0.0, 0.0, 10.0, 12.0)
    assert qs[0].expected == ["065-a_cups", "065-b_cups"]
    assert qs[1].box is None and qs[1].label is None


@pytest.mark.parametrize(
    ("row", "message"),
    [
        ({"prompt": "p", "expected": "x"}, "missing 'image'"),
        ({"image": "x.png", "expected": "x"}, "missing 'prompt'"),
        ({"image": "x.png", "prompt": "p"}, "missing 'expected'"),
        ({"image": "nope.png", "prompt": "p", "expected": "x"}, "image not found"),
        ({"image": "x.png", "prompt": "p", "expected": "x", "box": [5, 5, 1, 9]}, "x1 > x0"),
    ],
)
def test_bad_rows_name_the_file_and_line(tmp_path, row, message):
    _image(tmp_path / "x.png")
    (tmp_path / "q.jsonl").write_text(json.dumps(row) + "\n")
    with pytest.raises(QueryFileError, match=message) as err:
        load_queries(tmp_path / "q.jsonl")
    assert "q.jsonl:1" in str(err.value)


def test_library_resolves_ids_paths_names_and_classes(tmp_path):
    assert LIB.resolve("id-mustard") == {"id-mustard"}
    assert LIB.resolve("006_mustard_bottle/textured.obj") == {"id-mustard"}
    assert LIB.resolve("/lib/006_mustard_bottle/textured.obj") == {"id-mustard"}
    assert LIB.resolve("ycb/006_mustard_bottle/textured.obj") == {"id-mustard"}
    assert LIB.resolve("065-b_cups") == {"id-cup-b"}
    assert LIB.resolve("nothing") == set()
    assert LIB.with_label("065") == {"id-cup-a", "id-cup-b"}
    (tmp_path / "classes.json").write_text(json.dumps({"hope_000002": "sauce", "id-mustard": "sauce"}))
    lib = Library(LIB.meshes, class_map=load_class_map(tmp_path / "classes.json"))
    assert lib.with_label("sauce") == {"id-hope2", "id-mustard"}
    (tmp_path / "classes.csv").write_text("mesh,label\n065-a_cups,cup\n")
    assert load_class_map(tmp_path / "classes.csv") == {"065-a_cups": "cup"}


def _bop_scene(root, n_images=2):
    scene = root / "000001"
    gt, info = {}, {}
    for im in range(n_images):
        _image(scene / "rgb" / f"{im:06d}.png")
        gt[str(im)] = [
            {"obj_id": 2, "cam_R_m2c": [1, 0, 0, 0, 1, 0, 0, 0, 1], "cam_t_m2c": [0, 0, 500]},
            {"obj_id": 2, "cam_R_m2c": [1, 0, 0, 0, 1, 0, 0, 0, 1], "cam_t_m2c": [0, 0, 600]},
        ]
        info[str(im)] = [
            {"bbox_visib": [4, 5, 10, 20], "visib_fract": 0.8},
            {"bbox_visib": [-1, -1, -1, -1], "visib_fract": 0.0},
        ]
        mask = np.zeros((48, 64), np.uint8)
        mask[5:25, 4:14] = 255
        (scene / "mask_visib").mkdir(parents=True, exist_ok=True)
        Image.fromarray(mask).save(scene / "mask_visib" / f"{im:06d}_000000.png")
    (scene / "scene_gt.json").write_text(json.dumps(gt))
    (scene / "scene_gt_info.json").write_text(json.dumps(info))
    return scene


def test_bop_folder_by_object_naming(tmp_path):
    _bop_scene(tmp_path / "test")
    qs = load_bop(tmp_path / "test", library=LIB)
    assert len(qs) == 2  # the invisible second instance of each image is skipped
    q = qs[0]
    assert q.query_id == "000001-000000-000000"
    assert q.box == (4.0, 5.0, 14.0, 25.0)
    assert q.mask.endswith("mask_visib/000000_000000.png")
    assert LIB.resolve(q.expected[0]) == {"id-hope2"}
    assert q.prompt == "the hope 000002"
    # via load_queries, a single scene folder, an objects file with a prompt, and a cap per object
    (tmp_path / "objects.json").write_text(
        json.dumps({"2": {"mesh": "hope/hope_000002.ply", "prompt": "the bbq sauce", "label": "sauce"}})
    )
    qs = load_queries(
        tmp_path / "test" / "000001", library=LIB, objects=tmp_path / "objects.json", max_per_object=1
    )
    assert len(qs) == 1 and qs[0].prompt == "the bbq sauce" and qs[0].label == "sauce"


def test_bop_without_a_matching_mesh_is_a_clear_error(tmp_path):
    _bop_scene(tmp_path / "test", 1)
    lib = Library([m for m in LIB.meshes if m.mesh_id != "id-hope2"])
    with pytest.raises(QueryFileError, match="--bop-objects"):
        load_bop(tmp_path / "test", library=lib)
    with pytest.raises(QueryFileError, match="not a BOP folder"):
        load_bop(tmp_path)


def test_query_json_is_plain():
    q = Query("q", "/x.png", "p", ["e"], box=(0, 0, 1, 1))
    assert json.loads(json.dumps(q.to_json()))["box"] == [0, 0, 1, 1]
