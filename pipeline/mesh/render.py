"""Headless rendering of a normalised mesh from the configured camera layout (pyrender over EGL)."""

from __future__ import annotations

import io
import os
from dataclasses import dataclass

import numpy as np

from pipeline.mesh.cameras import EXTRA_BG_COLOR, extra_bg_view, framed_pose, view_directions
from pipeline.mesh.load import LoadedMesh
from pipeline.mesh.settings import RenderConfig


def setup_headless_gl() -> None:
    """Select EGL (Mesa surfaceless on CPU machines, the NVIDIA driver on GPUs) and patch numpy for pyrender."""
    os.environ.setdefault("PYOPENGL_PLATFORM", "egl")
    os.environ.setdefault("EGL_PLATFORM", "surfaceless")
    if not hasattr(np, "infty"):
        np.infty = np.inf  # pyrender still uses the alias removed in NumPy 2


setup_headless_gl()  # before anything imports pyrender / PyOpenGL, which pick their platform at import


@dataclass
class RenderedView:
    view_index: int
    azimuth_deg: float
    elevation_deg: float
    camera_pose: np.ndarray
    image: np.ndarray  # HxWx3 uint8


class Renderer:
    """Long-lived offscreen renderer; reuse one per process (creating GL contexts is slow)."""

    def __init__(self, cfg: RenderConfig):
        setup_headless_gl()
        import pyrender

        self.cfg = cfg
        self._pyrender = pyrender
        self._renderer = pyrender.OffscreenRenderer(cfg.resolution, cfg.resolution)
        bg = [c / 255.0 for c in cfg.background] + [1.0]
        self._bg = bg
        self._scene = pyrender.Scene(bg_color=bg, ambient_light=[0.45, 0.45, 0.45])
        self._cam = self._scene.add(
            pyrender.PerspectiveCamera(yfov=np.radians(cfg.yfov_deg), znear=0.05, zfar=100.0), pose=np.eye(4)
        )
        self._light = self._scene.add(pyrender.DirectionalLight(intensity=2.6), pose=np.eye(4))

    def warm_up(self) -> None:
        """Render a small textured triangle once so shader compilation is not billed to the first mesh."""
        import trimesh
        from PIL import Image

        from pipeline.mesh.load import LoadedMesh

        tri = trimesh.Trimesh([[0, 0, 0], [1, 0, 0], [0, 1, 0]], [[0, 1, 2]], process=False)
        tri.visual = trimesh.visual.TextureVisuals(
            uv=[[0, 0], [1, 0], [0, 1]], image=Image.new("RGB", (4, 4), (200, 30, 30))
        )
        pts = np.asarray(tri.vertices, dtype=np.float64)
        self.render(LoadedMesh([tri], 3, 1, [0, 0, 0], [1, 1, 0], "m", 1.0, pts))

    def render(self, mesh: LoadedMesh) -> list[RenderedView]:
        """Render every view of ``mesh`` (already normalised to the unit sphere, z up)."""
        pyrender = self._pyrender
        nodes = []
        for g in mesh.geometries:
            pm = pyrender.Mesh.from_trimesh(g, smooth=_has_normals(g))
            for prim in pm.primitives:
                mat = prim.material
                if mat is not None and hasattr(mat, "metallicFactor"):
                    # OBJ materials default to fully metallic in pyrender, which renders textures dark
                    mat.metallicFactor = 0.0
                    mat.roughnessFactor = 0.9
            nodes.append(self._scene.add(pm))
        try:
            views = [
                self._view(mesh, i, az, el, direction)
                for i, (az, el, direction) in enumerate(view_directions(self.cfg))
            ]
            extra = extra_bg_view(self.cfg)
            if extra is not None:
                self._scene.bg_color = np.array([c / 255.0 for c in EXTRA_BG_COLOR] + [1.0])
                try:
                    views.append(self._view(mesh, *extra))
                finally:
                    self._scene.bg_color = np.array(self._bg)
            return views
        finally:
            for n in nodes:
                self._scene.remove_node(n)

    def _view(self, mesh: LoadedMesh, i: int, az: float, el: float, direction: np.ndarray) -> RenderedView:
        pose = framed_pose(mesh.sample_points, direction, self.cfg.yfov_deg, self.cfg.fill)
        self._scene.set_pose(self._cam, pose)
        self._scene.set_pose(self._light, pose)
        color, _ = self._renderer.render(self._scene)
        return RenderedView(i, az, el, pose, np.ascontiguousarray(color[:, :, :3]))

    def close(self) -> None:
        self._renderer.delete()


def _has_normals(geom) -> bool:
    # vertex normals of scanned meshes make them look smooth; cheap to compute if absent
    return len(geom.faces) < 2_000_000


def encode_png(image: np.ndarray) -> bytes:
    """PNG bytes of an RGB uint8 image (fast compression level: renders are re-decoded, not archived)."""
    from PIL import Image

    buf = io.BytesIO()
    Image.fromarray(image).save(buf, format="PNG", compress_level=3)
    return buf.getvalue()


def decode_png(data: bytes):
    """PIL RGB image from PNG bytes."""
    from PIL import Image

    return Image.open(io.BytesIO(data)).convert("RGB")
