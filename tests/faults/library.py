"""A tiny mesh library (three meshes, one textured) and store builder for the fault corpus."""

from __future__ import annotations

import shutil
from pathlib import Path

import numpy as np

RESOLUTION = 64  # tiny renders: the corpus checks outcomes, not pixels


def write_textured_obj(
    folder: Path, texture: bytes | None = None, name: str = "model", colour=(200, 30, 30)
) -> Path:
    """A textured box (OBJ + MTL + 16x16 PNG, half ``colour``) in ``folder``; returns the .obj path.

    Boxes of another ``colour`` have other content, hence another ``mesh_id`` (new work for a run)."""
    import trimesh
    from PIL import Image

    folder.mkdir(parents=True, exist_ok=True)
    box = trimesh.creation.box(extents=(1.0, 0.6, 0.4))
    lines = ["mtllib model.mtl", "usemtl m"]
    lines += [f"v {x:.4f} {y:.4f} {z:.4f}" for x, y, z in box.vertices]
    uv = (box.vertices[:, :2] - box.vertices[:, :2].min(0)) / np.ptp(box.vertices[:, :2], axis=0)
    lines += [f"vt {u:.4f} {v:.4f}" for u, v in uv]
    lines += ["f " + " ".join(f"{i + 1}/{i + 1}" for i in f) for f in box.faces]
    (folder / f"{name}.obj").write_text("\n".join(lines) + "\n")
    (folder / "model.mtl").write_text("newmtl m\nKd 1 1 1\nmap_Kd texture.png\n")
    if texture is None:
        img = np.zeros((16, 16, 3), np.uint8)
        img[:, :8] = colour
        img[:, 8:] = (30, 30, 200)
        Image.fromarray(img).save(folder / "texture.png")
    else:
        (folder / "texture.png").write_bytes(texture)
    return folder / f"{name}.obj"


def write_library(root: Path) -> Path:
    """Three small meshes: a textured cube (OBJ), a sphere (PLY) and a cylinder (STL)."""
    import trimesh

    root.mkdir(parents=True, exist_ok=True)
    write_textured_obj(root / "cube")
    trimesh.creation.icosphere(subdivisions=1).export(root / "sphere.ply")
    trimesh.creation.cylinder(radius=0.3, height=1.0, sections=12).export(root / "cylinder.stl")
    return root


def copy_tree(src: Path, dst: Path) -> Path:
    shutil.copytree(src, dst, symlinks=True)
    return dst
