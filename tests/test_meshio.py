"""Formats, units, up axis, references and hashing of the mesh layer (no store)."""

from __future__ import annotations

import numpy as np
import pytest
import trimesh

from pipeline.mesh.cameras import framed_pose, view_directions
from pipeline.mesh.discover import DiscoveryError, content_hash, referenced_files, walk_library
from pipeline.mesh.load import MeshError, load_mesh
from pipeline.mesh.settings import RenderConfig


def _box(extents=(0.1, 0.2, 0.4)) -> trimesh.Trimesh:
    return trimesh.creation.box(extents=extents)


@pytest.mark.parametrize("fmt", ["ply", "stl", "off", "glb", "obj"])
def test_formats_load_and_normalise(tmp_path, fmt):
    path = tmp_path / f"box.{fmt}"
    _box().export(path)
    m = load_mesh(str(path), fmt, max_faces=1000)
    assert m.n_faces == 12
    pts = np.concatenate([g.vertices for g in m.geometries])
    assert np.allclose(np.linalg.norm(pts, axis=1).max(), 1.0, atol=1e-6)  # unit bounding sphere
    assert np.allclose((pts.min(0) + pts.max(0)) / 2, 0, atol=1e-6)  # centred
    assert m.units_guess == "m"
    if fmt != "glb":  # z-up formats keep their axes (glTF: see test_gltf_is_made_z_up)
        assert np.argmax(pts.max(0) - pts.min(0)) == 2


def test_gltf_is_made_z_up(tmp_path):
    tall_in_y = _box((0.1, 0.4, 0.1))  # a glTF asset that stands along +y
    tall_in_y.export(tmp_path / "a.glb")
    m = load_mesh(str(tmp_path / "a.glb"), "glb", max_faces=100)
    pts = np.concatenate([g.vertices for g in m.geometries])
    assert np.argmax(pts.max(0) - pts.min(0)) == 2


def test_millimetres_are_detected_and_normalised(tmp_path):
    _box((50.0, 80.0, 200.0)).export(tmp_path / "mm.ply")
    m = load_mesh(str(tmp_path / "mm.ply"), "ply", max_faces=100)
    assert m.units_guess == "mm" and m.scale_to_unit == pytest.approx(1 / np.linalg.norm([25, 40, 100]))


def test_vertex_colours_survive(tmp_path):
    box = _box()
    box.visual.vertex_colors = np.tile([200, 30, 30, 255], (len(box.vertices), 1))
    box.export(tmp_path / "red.ply")
    m = load_mesh(str(tmp_path / "red.ply"), "ply", max_faces=100)
    assert m.geometries[0].visual.kind == "vertex"
    assert tuple(m.geometries[0].visual.vertex_colors[0][:3]) == (200, 30, 30)


def test_references_and_hash(tmp_path):
    (tmp_path / "m.obj").write_text("mtllib m.mtl\nv 0 0 0\nv 1 0 0\nv 0 1 0\nf 1 2 3\n")
    (tmp_path / "m.mtl").write_text("newmtl a\nmap_Kd -s 1 1 1 tex.png \n")  # options and a trailing space
    (tmp_path / "tex.png").write_bytes(b"png")
    assert referenced_files(tmp_path / "m.obj", "obj") == ["m.mtl", "tex.png"]
    h1 = content_hash(str(tmp_path / "m.obj"), ["m.mtl", "tex.png"])
    (tmp_path / "tex.png").write_bytes(b"png2")
    assert content_hash(str(tmp_path / "m.obj"), ["m.mtl", "tex.png"]) != h1
    (tmp_path / "tex.png").unlink()
    with pytest.raises(DiscoveryError, match="missing texture 'tex.png'"):
        referenced_files(tmp_path / "m.obj", "obj")


def test_walk_skips_hidden_and_other_files(tmp_path):
    (tmp_path / ".cache").mkdir()
    (tmp_path / ".cache" / "x.obj").write_text("")
    (tmp_path / "a").mkdir()
    (tmp_path / "a" / "M.OBJ").write_text("")
    (tmp_path / "a" / "notes.txt").write_text("")
    assert [f.source_path for f in walk_library(tmp_path)] == ["a/M.OBJ"]


def test_nan_and_degenerate_rejected(tmp_path):
    (tmp_path / "n.obj").write_text("v 0 0 0\nv nan 0 0\nv 0 1 0\nf 1 2 3\n")
    with pytest.raises(MeshError, match="non-finite"):
        load_mesh(str(tmp_path / "n.obj"), "obj", max_faces=10)


def test_elevation_rings_per_profile_and_validated():
    from pipeline.onboard.config import OnboardConfig

    assert OnboardConfig(profile="paper").render.elevations_deg == (-15.0, 15.0)  # the paper's K = 8
    offline = OnboardConfig().render  # the default profile adds a +45 deg ring
    assert offline.elevations_deg == (-15.0, 15.0, 45.0)
    views = view_directions(offline)
    assert [round(e) for _, e, _ in views] == [-15] * 4 + [15] * 4 + [45] * 4
    assert [round(a) for a, _, _ in views[8:]] == [90, 180, 270, 0]  # ring 2: offset 2 x 45 deg
    assert offline.fingerprint() != RenderConfig().fingerprint()
    explicit = OnboardConfig(render=RenderConfig(resolution=64))  # an explicit RenderConfig is kept as is
    assert explicit.render.elevations_deg == (-15.0, 15.0)
    assert RenderConfig(elevations_deg=[10, 20]).elevations_deg == (10.0, 20.0)  # JSON lists become tuples
    for bad, msg in [((), "1 to 6"), ((0,) * 7, "1 to 6"), ((-15, 90), "-89..89"), ((float("nan"),), "-89")]:
        with pytest.raises(ValueError, match=msg):
            RenderConfig(elevations_deg=bad)


def test_views_layouts_and_framing():
    oscar = view_directions(RenderConfig())
    assert [round(e) for _, e, _ in oscar] == [-15] * 4 + [15] * 4
    assert sorted(round(a) for a, _, _ in oscar) == [0, 45, 90, 135, 180, 225, 270, 315]
    cap3d = view_directions(RenderConfig(cameras="cap3d"))
    assert len(cap3d) == 8
    # the reference's Blender script: views 4 and 5 keep view 3's elevation factor 0.7 (26.3 deg, not 8)
    elev = [round(e, 2) for _, e, _ in cap3d]
    assert elev == [8.05, 8.05, 24.09, 32.05, 26.33, 26.33, -24.09, -32.05]
    assert abs(cap3d[4][1] - np.degrees(np.arctan(0.7 / np.sqrt(2)))) < 1e-9
    pts = np.random.default_rng(0).normal(size=(500, 3)) * [1, 0.3, 0.2]
    pts /= np.linalg.norm(pts, axis=1).max()
    for _, _, d in oscar:
        pose = framed_pose(pts, d, 40.0, 0.9)
        cam = (pts - pose[:3, 3]) @ pose[:3, :3]
        t = np.tan(np.radians(20))
        x, y = cam[:, 0] / (-cam[:, 2] * t), cam[:, 1] / (-cam[:, 2] * t)
        assert max(np.abs(x).max(), np.abs(y).max()) == pytest.approx(0.9, abs=1e-3)
        assert abs(x.min() + x.max()) < 1e-2 and abs(y.min() + y.max()) < 1e-2
