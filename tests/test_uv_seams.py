"""UV seams: a vertex that two texture charts share keeps each chart's coordinates, in the renders and in
the metric export. Loading OBJ files in their vertex order gave such a vertex one chart's coordinates for
every face, so scanned meshes rendered with dark cracks along every seam (docs/results.md, section 9)."""

from __future__ import annotations

from pathlib import Path

import numpy as np
from conftest import need_shared
from PIL import Image

# a unit quad of two triangles; vertices 1 and 3 lie on the seam between two charts of the texture
OBJ = """mtllib quad.mtl
usemtl tex
v 0 0 0
v 1 0 0
v 1 1 0
v 0 1 0
vt 0.05 0.05
vt 0.45 0.05
vt 0.45 0.45
vt 0.55 0.55
vt 0.95 0.95
vt 0.55 0.95
f 1/1 2/2 3/3
f 1/4 3/5 4/6
"""
# the file's own coordinates of each face corner
CORNERS = np.array([[[0.05, 0.05], [0.45, 0.05], [0.45, 0.45]], [[0.55, 0.55], [0.95, 0.95], [0.55, 0.95]]])
RED, GREEN = (220, 30, 30), (30, 200, 30)


def _quad(tmp_path: Path) -> Path:
    """The quad, with a texture whose lower-left chart is red, upper-right chart green, the rest black."""
    tex = np.zeros((64, 64, 3), np.uint8)
    tex[32:, :32] = RED  # v < 0.5, u < 0.5 (image rows run downwards)
    tex[:32, 32:] = GREEN  # v > 0.5, u > 0.5
    Image.fromarray(tex).save(tmp_path / "quad.png")
    (tmp_path / "quad.mtl").write_text("newmtl tex\nKd 1 1 1\nmap_Kd quad.png\n")
    path = tmp_path / "quad.obj"
    path.write_text(OBJ)
    return path


def _corner_uvs(geom) -> np.ndarray:
    return np.asarray(geom.visual.uv)[np.asarray(geom.faces)]


def test_loaded_faces_keep_each_charts_coordinates(tmp_path):
    from pipeline.mesh.load import load_mesh

    mesh = load_mesh(str(_quad(tmp_path)), "obj", max_faces=100)
    (geom,) = mesh.geometries
    assert np.allclose(_corner_uvs(geom), CORNERS, atol=1e-6)
    assert len(geom.vertices) == 6  # the two seam vertices once per chart
    assert (mesh.n_faces, mesh.n_vertices) == (2, 4)  # counted as the file has them


def test_rendered_quad_shows_both_charts_and_no_black(tmp_path):
    """Seen face on, each half of the quad has its own chart's colour; in vertex order one half sampled
    across the black between the charts."""
    from pipeline.mesh.load import load_mesh
    from pipeline.mesh.render import Renderer
    from pipeline.mesh.settings import RenderConfig

    mesh = load_mesh(str(_quad(tmp_path)), "obj", max_faces=100, up="y")  # y up: the quad faces +z -> -y
    cfg = RenderConfig(resolution=64, elevations_deg=(0.0,), views_per_ring=4)
    renderer = Renderer(cfg)
    try:
        views = renderer.render(mesh)
    finally:
        renderer.close()
    bg = np.array(cfg.background)
    face_on = max(views, key=lambda v: int((np.abs(v.image.astype(int) - bg).sum(axis=2) > 30).sum()))
    obj = face_on.image[np.abs(face_on.image.astype(int) - bg).sum(axis=2) > 30].astype(int)
    assert len(obj) > 500, "the quad should fill much of a face-on view"
    red = (obj[:, 0] > 2 * obj[:, 1]) & (obj[:, 0] > 60)
    green = (obj[:, 1] > 2 * obj[:, 0]) & (obj[:, 1] > 60)
    dark = obj.max(axis=1) < 40
    assert red.mean() > 0.3 and green.mean() > 0.3, (red.mean(), green.mean())
    assert dark.mean() < 0.02, dark.mean()


def test_metric_export_keeps_each_charts_coordinates(tmp_path):
    import trimesh

    from pipeline.query.export import _rewrite

    src = _quad(tmp_path)
    dest = tmp_path / "out"
    dest.mkdir()
    files = _rewrite(src, "obj", 1000.0, dest)
    reloaded = trimesh.load(str(files[0]), file_type="obj", process=False)
    assert np.allclose(_corner_uvs(reloaded), CORNERS, atol=1e-5)
    assert np.allclose(np.asarray(reloaded.vertices).max(axis=0)[:2], [1000.0, 1000.0])


def test_bop_export_keeps_each_charts_coordinates(tmp_path):
    """The BOP layout's binary PLY (texture_u / texture_v per vertex) splits the seam vertices too."""
    import trimesh

    from pipeline.query.export import _load, write_ply

    dest = tmp_path / "models"
    dest.mkdir()
    files = write_ply(_load(_quad(tmp_path), "obj"), 1000.0, dest / "obj_000001.ply")
    reloaded = trimesh.load(str(files[0]), process=False)
    assert np.allclose(_corner_uvs(reloaded), CORNERS, atol=1e-5)


def test_ycb_scan_renders_without_seam_cracks():
    """On a real scan (431 of the baseball's 16,384 faces had another chart's coordinates before) no face
    samples the black between charts: every face's texels are painted."""
    from pipeline.mesh.load import load_mesh

    path = need_shared() / "055_baseball" / "textured.obj"
    mesh = load_mesh(str(path), "obj", max_faces=10**6)
    (geom,) = mesh.geometries
    tex = np.asarray(geom.visual.material.image.convert("RGB"))
    h, w = tex.shape[:2]
    centre = _corner_uvs(geom).mean(axis=1)
    px = np.clip((centre[:, 0] * w).astype(int), 0, w - 1)
    py = np.clip(((1 - centre[:, 1]) * h).astype(int), 0, h - 1)
    black = tex[py, px].max(axis=1) < 10
    assert black.mean() < 0.01, f"{black.mean():.1%} of the faces sample the black between charts"
