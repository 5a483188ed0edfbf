"""``--export DIR``: the winning model for a pose estimator, in metres by default, with a ``model_info.json``.

* ``fmt="mesh"``: the source file type with its materials and textures. Files are copied byte for byte when
  no scaling is needed (``units="source"``, or a file already in the target units); otherwise the mesh is
  loaded with trimesh, scaled, and written again (OBJ with its ``.mtl`` and textures, PLY with its texture
  coordinates and a ``TextureFile`` comment, glTF/STL/OFF as trimesh writes them).
* ``fmt="bop"``: the BOP models layout that MegaPose, FoundationPose and the BOP toolkit read:
  ``models/obj_000001.ply`` in millimetres (vertices, normals, texture coordinates or vertex colours) and
  ``models/models_info.json`` (``diameter``, ``min_x/y/z``, ``size_x/y/z`` in mm).

Every written mesh is reloaded with trimesh and its size checked against the store's bounds times the scale;
a mismatch is an error, not a silent bad export.
"""

from __future__ import annotations

import json
import os
import shutil
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from pipeline.query.errors import QueryError
from pipeline.query.handoff import metric_info

EXPORT_UNITS = ("m", "mm", "source")
EXPORT_FORMATS = ("mesh", "bop")
#: relative tolerance of the reload check (PLY stores float32 coordinates)
SIZE_RTOL = 1e-4


@dataclass
class Export:
    """What an export wrote: the folder, every file (the mesh first), and ``model_info.json``'s content."""

    folder: Path
    files: list[Path]
    unchanged: bool  # the source files still hash to the mesh id
    info: dict = field(default_factory=dict)


def export_mesh(mesh: dict, out_dir: str | Path) -> tuple[Path, list[Path], bool]:
    """Copy ``mesh`` (an active-mesh record) into ``out_dir/<name>/``, keeping the references' relative paths.

    Returns (folder, copied files, unchanged) where ``unchanged`` says the files still hash to the mesh_id.
    """
    src, deps, unchanged = _source(mesh)
    dest = Path(out_dir) / _safe(mesh.get("name") or src.stem)
    return dest, _copy(src, deps, dest), unchanged


def export_model(
    mesh: dict, out_dir: str | Path, *, units: str = "m", fmt: str = "mesh", prior: dict | None = None
) -> Export:
    """Export ``mesh`` into ``out_dir/<name>/`` in ``units`` (m | mm | source) as ``fmt`` (mesh | bop).

    ``prior`` (a candidate's ``best_view``, ``best_view_pose``, ``intrinsics``) goes into ``model_info.json``.
    """
    if units not in EXPORT_UNITS:
        raise QueryError(f"unknown export units {units!r}; choose from {', '.join(EXPORT_UNITS)}")
    if fmt not in EXPORT_FORMATS:
        raise QueryError(f"unknown export format {fmt!r}; choose from {', '.join(EXPORT_FORMATS)}")
    if fmt == "bop" and units != "mm":
        units = "mm"  # the BOP layout is millimetres by definition
    src, deps, unchanged = _source(mesh)
    metric = metric_info(mesh)
    factor = unit_factor(metric, units)
    dest = Path(out_dir) / _safe(mesh.get("name") or src.stem)
    try:
        dest.mkdir(parents=True, exist_ok=True)
        if fmt == "bop":
            files = write_bop_models([(1, mesh)], dest)
        elif factor == 1.0:
            files = _copy(src, deps, dest)
        else:
            files = _rewrite(src, mesh.get("format") or src.suffix.lstrip("."), factor, dest)
    except OSError as exc:
        raise QueryError(f"cannot export to {dest}: {exc.strerror or exc}") from None
    size = check_size(files[0], mesh, factor)
    info = model_info(mesh, metric, units, factor, size, files[0].relative_to(dest), prior)
    (dest / "model_info.json").write_text(json.dumps(info, indent=2) + "\n")
    return Export(dest, files + [dest / "model_info.json"], unchanged, info)


def unit_factor(metric: dict, units: str) -> float:
    """What the file's coordinates are multiplied by to be in ``units``."""
    if units == "source":
        return 1.0
    if metric["scale_to_metres"] is None:
        raise QueryError(
            "the model has no recorded size or units (onboarded before they were recorded?): re-run "
            "onboarding, or export with --export-units source"
        )
    return metric["scale_to_metres"] * (1000.0 if units == "mm" else 1.0)


def model_info(mesh, metric, units, factor, size, file, prior) -> dict:
    """The ``model_info.json`` record of an export (sizes in metres and in the export's units)."""
    out = {
        "mesh_id": mesh["mesh_id"],
        "name": mesh.get("name"),
        "source_path": mesh.get("source_path"),
        "library_root": mesh.get("library_root"),
        "file": str(file),
        "units": units if units != "source" else metric["units_guess"],
        "scale_applied": factor,
        **metric,
        "extent": [round(v, 6) for v in size["extent"]],
        "diameter": round(size["diameter"], 6),
        "diameter_m": None if metric["scale_to_metres"] is None else round(size["diameter_m"], 6),
    }
    prior = prior or {}
    out["best_view"] = prior.get("best_view")
    out["best_view_pose"] = prior.get("best_view_pose")  # metres, whatever the export's units
    out["intrinsics"] = prior.get("intrinsics")
    if (
        out["best_view_pose"] is not None
        and metric["scale_to_metres"]
        and factor != metric["scale_to_metres"]
    ):
        pose = np.asarray(out["best_view_pose"], np.float64)
        pose[:3, 3] *= factor / metric["scale_to_metres"]  # metres -> export units
        out["best_view_pose_export_units"] = pose.round(9).tolist()
    return out


def check_size(path: Path, mesh: dict, factor: float) -> dict:
    """Reload ``path`` with trimesh; its size must be the store's bounds times ``factor``.

    Returns the extent and diameter (largest vertex distance) in the export's units and the diameter in metres.
    """
    import trimesh
    from scipy.spatial.distance import pdist

    try:
        loaded = trimesh.load(str(path), process=False)
    except Exception as exc:  # trimesh raises many types
        raise QueryError(f"the exported mesh {path} does not load: {type(exc).__name__}: {exc}") from None
    geoms = loaded.dump() if isinstance(loaded, trimesh.Scene) else [loaded]
    verts = np.concatenate([np.asarray(g.vertices, np.float64) for g in geoms if len(g.vertices)])
    extent = verts.max(axis=0) - verts.min(axis=0)
    lo, hi = mesh.get("bounds_min"), mesh.get("bounds_max")
    if lo is not None and hi is not None:
        want = (np.asarray(hi, np.float64) - np.asarray(lo, np.float64)) * factor
        if not np.allclose(extent, want, rtol=SIZE_RTOL, atol=SIZE_RTOL * float(np.max(want))):
            raise QueryError(
                f"the exported mesh {path} reloads with size {np.round(extent, 6).tolist()}, expected "
                f"{np.round(want, 6).tolist()}: export not written correctly"
            )
    try:
        hull = trimesh.convex.convex_hull(verts).vertices
    except Exception:  # flat or degenerate point sets: every vertex
        hull = verts
    diameter = float(pdist(hull).max()) if len(hull) > 1 else 0.0
    metric = metric_info(mesh)
    per_metre = (metric["scale_to_metres"] or 0.0) / factor if factor else 0.0
    return {"extent": extent.tolist(), "diameter": diameter, "diameter_m": diameter * per_metre}


# ---------------------------------------------------------------------------- BOP layout
def write_bop_models(items: list[tuple[int, dict]], out_dir: str | Path) -> list[Path]:
    """``out_dir/models/obj_NNNNNN.ply`` (mm) per (obj_id, mesh record) plus ``models/models_info.json``."""
    models = Path(out_dir) / "models"
    models.mkdir(parents=True, exist_ok=True)
    files, infos = [], {}
    for obj_id, mesh in items:
        src, _deps, _ = _source(mesh)
        factor = unit_factor(metric_info(mesh), "mm")
        ply = models / f"obj_{int(obj_id):06d}.ply"
        files += write_ply(_load(src, mesh.get("format") or src.suffix.lstrip(".")), factor, ply)
        size = check_size(ply, mesh, factor)
        verts = _ply_vertices(ply)
        lo = verts.min(axis=0)
        infos[str(int(obj_id))] = {
            "diameter": round(size["diameter"], 6),
            **{f"min_{a}": round(float(v), 6) for a, v in zip("xyz", lo, strict=True)},
            **{f"size_{a}": round(float(v), 6) for a, v in zip("xyz", size["extent"], strict=True)},
        }
    info_path = models / "models_info.json"
    info_path.write_text(json.dumps(infos, indent=2) + "\n")
    return files + [info_path]


def write_ply(loaded, factor: float, path: Path) -> list[Path]:
    """One binary PLY of every geometry of ``loaded`` scaled by ``factor`` (the BOP toolkit's layout).

    A single textured geometry keeps its texture (``texture_u``/``texture_v`` per vertex and a
    ``comment TextureFile`` naming a PNG beside it); several textured parts, or colour-only meshes, become
    per-vertex colours (one texture file per PLY is what BOP readers take).
    """
    import trimesh
    from plyfile import PlyData, PlyElement

    geoms = loaded.dump() if isinstance(loaded, trimesh.Scene) else [loaded]
    geoms = [g for g in geoms if isinstance(g, trimesh.Trimesh) and len(g.faces)]
    texture = _single_texture(geoms)
    parts, faces, offset = [], [], 0
    for g in geoms:
        v = np.asarray(g.vertices, np.float64) * factor
        cols = {"x": v[:, 0], "y": v[:, 1], "z": v[:, 2]}
        n = np.asarray(g.vertex_normals, np.float64)
        cols.update({"nx": n[:, 0], "ny": n[:, 1], "nz": n[:, 2]})
        if texture is not None:
            uv = np.asarray(g.visual.uv, np.float64)
            cols.update({"texture_u": uv[:, 0], "texture_v": uv[:, 1]})
        else:
            rgb = _vertex_colours(g)
            cols.update({"red": rgb[:, 0], "green": rgb[:, 1], "blue": rgb[:, 2]})
        parts.append(cols)
        faces.append(np.asarray(g.faces, np.int64) + offset)
        offset += len(v)
    names = list(parts[0])
    dtype = [(k, "u1" if k in ("red", "green", "blue") else "f4") for k in names]
    vertex = np.empty(offset, dtype=dtype)
    for k in names:
        vertex[k] = np.concatenate([p[k] for p in parts])
    f = np.concatenate(faces)
    face = np.empty(len(f), dtype=[("vertex_indices", "i4", (3,))])
    face["vertex_indices"] = f
    comments, files = [], [path]
    if texture is not None:
        tex = path.with_suffix(".png")
        texture.convert("RGB").save(tex)
        comments.append(f"TextureFile {tex.name}")
        files.append(tex)
    ply = PlyData(
        [PlyElement.describe(vertex, "vertex"), PlyElement.describe(face, "face")],
        text=False,
        byte_order="<",
        comments=comments,
    )
    ply.write(str(path))
    return files


def _single_texture(geoms):
    """The texture image when there is exactly one textured geometry with per-vertex UVs, else None."""
    if len(geoms) != 1:
        return None
    visual = geoms[0].visual
    if getattr(visual, "kind", None) != "texture" or getattr(visual, "uv", None) is None:
        return None
    material = getattr(visual, "material", None)
    img = getattr(material, "image", None) or getattr(material, "baseColorTexture", None)
    return img if img is not None and len(visual.uv) == len(geoms[0].vertices) else None


def _vertex_colours(g) -> np.ndarray:
    """uint8 RGB per vertex (a texture sampled at the UVs, vertex colours, or the material's colour)."""
    try:
        colours = g.visual.to_color().vertex_colors if g.visual.kind == "texture" else g.visual.vertex_colors
        rgb = np.asarray(colours, np.uint8)[:, :3]
        if len(rgb) == len(g.vertices):
            return rgb
    except Exception:  # trimesh visuals without colours
        pass
    return np.full((len(g.vertices), 3), 180, np.uint8)


def _ply_vertices(path: Path) -> np.ndarray:
    from plyfile import PlyData

    v = PlyData.read(str(path))["vertex"]
    return np.stack([np.asarray(v[a], np.float64) for a in "xyz"], axis=1)


# ---------------------------------------------------------------------------- helpers
def _source(mesh: dict) -> tuple[Path, list[str], bool]:
    from pipeline.mesh.discover import content_hash

    src = Path(mesh["library_root"]) / mesh["source_path"]
    if not src.is_file():
        raise QueryError(f"the model's file is gone: {src} (run onboarding again to refresh the store)")
    deps = [d["path"] for d in (mesh.get("deps") or [])]
    missing = [d for d in deps if not (src.parent / d).is_file()]
    if missing:
        raise QueryError(f"the model's referenced file is gone: {src.parent / missing[0]}")
    return src, deps, content_hash(str(src), deps) == mesh["mesh_id"]


def _copy(src: Path, deps: list[str], dest: Path) -> list[Path]:
    base = src.parent
    copied = []
    try:
        dest.mkdir(parents=True, exist_ok=True)
        copied.append(Path(shutil.copy2(src, dest / src.name)))
        for rel in deps:
            # named under ``dest`` as given (not resolved: a relative or symlinked folder stays so)
            target = Path(os.path.normpath(dest / rel))
            if dest.resolve() not in target.resolve().parents:  # "../tex.png": keep it inside the folder
                target = dest / Path(rel).name
            target.parent.mkdir(parents=True, exist_ok=True)
            copied.append(Path(shutil.copy2(base / rel, target)))
    except OSError as exc:
        raise QueryError(f"cannot export to {dest}: {exc.strerror or exc}") from None
    return copied


def _load(src: Path, fmt: str):
    import trimesh

    try:
        return trimesh.load(str(src), file_type=fmt, process=False)  # split at UV seams (tests/test_uv_seams.py)
    except Exception as exc:  # trimesh raises many types for corrupt files
        raise QueryError(f"cannot load {src} for export: {type(exc).__name__}: {exc}") from None


def _rewrite(src: Path, fmt: str, factor: float, dest: Path) -> list[Path]:
    """``src`` scaled by ``factor``, written as the same file type into ``dest`` (materials beside it)."""
    loaded = _load(src, fmt)
    out = dest / src.name
    if fmt == "ply":
        return write_ply(loaded, factor, out)
    loaded.apply_scale(factor)
    before = set(dest.rglob("*"))
    loaded.export(str(out), file_type=fmt)
    extra = sorted(p for p in set(dest.rglob("*")) - before if p.is_file() and p != out)
    return [out, *extra]


def _safe(name: str) -> str:
    keep = "".join(c if c.isalnum() or c in "._-" else "_" for c in name).strip("._")
    return keep or "model"
