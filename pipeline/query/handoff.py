"""The pose-estimator hand-off of an answer: metric units and size, and the best view's camera as a pose prior.

Per candidate (see docs/query.md, "Hand-off to a pose estimator"):

* ``units_guess`` / ``units_from``: the units of the source file (``"m"`` or ``"mm"``) and how they were
  decided: ``"gltf"`` (the glTF specification says metres) or ``"extent"`` (a guess: the loader takes a mesh
  whose longest side exceeds 20 file units for millimetres; OBJ, PLY, STL and OFF carry no units);
* ``scale_to_metres``: the factor that turns the file's coordinates into metres;
* ``extent_m``: the axis-aligned size (x, y, z) of the source mesh in metres;
* ``best_view_pose``: 4x4, source frame in metres -> camera of the best-matching view, OpenCV axes;
* ``intrinsics``: ``{"K": 3x3, "width", "height"}`` of that view.

The geometry is :mod:`pipeline.mesh.frames`; this module only picks the store's numbers. Views' cameras are
read per answer for the listed candidates only (``sql/view_poses.sql``) and kept per mesh.
"""

from __future__ import annotations

import threading
from collections.abc import Callable

import numpy as np

from pipeline.mesh import frames

#: cached meshes' view cameras at most (a long-running service sees many different answers)
MAX_CACHED = 4096
#: libraries of at most this many meshes have every view camera read on the first answer (one scan)
PRELOAD_MESHES = 2000


def metric_units(fmt: str | None, units_guess: str | None) -> tuple[str, str] | None:
    """(units, how decided) of a mesh file: glTF is metres by specification, others the loader's guess."""
    if (fmt or "").lower() in ("glb", "gltf"):
        return "m", "gltf"
    if units_guess in frames.METRES_PER_UNIT:
        return units_guess, "extent"
    return None


def metric_info(mesh: dict) -> dict:
    """Units, scale and metric size of an active-mesh record (None values when the mesh has no geometry)."""
    units = metric_units(mesh.get("format"), mesh.get("units_guess"))
    lo, hi = mesh.get("bounds_min"), mesh.get("bounds_max")
    if units is None or lo is None or hi is None:
        return {"units_guess": None, "units_from": None, "scale_to_metres": None, "extent_m": None}
    return {
        "units_guess": units[0],
        "units_from": units[1],
        "scale_to_metres": frames.scale_to_metres(units[0]),
        "extent_m": [round(v, 6) for v in frames.extent_m(lo, hi, units[0])],
    }


def view_prior(mesh: dict, view: dict, up: str = "auto") -> dict | None:
    """``best_view_pose`` and ``intrinsics`` of one stored view (a ``view_poses.sql`` row) of ``mesh``."""
    info = metric_info(mesh)
    if info["scale_to_metres"] is None or not mesh.get("scale_to_unit") or view.get("camera_pose") is None:
        return None
    norm = frames.normalisation(
        mesh["bounds_min"], mesh["bounds_max"], mesh["scale_to_unit"], mesh.get("format") or "", up
    )
    pose = frames.view_pose(view["camera_pose"], norm, info["scale_to_metres"])
    k = frames.intrinsics(view["yfov_deg"], view["width"], view["height"])
    return {
        "best_view_pose": (np.round(pose, 9) + 0.0).tolist(),  # + 0.0: no -0.0 in JSON
        "intrinsics": {
            "K": (np.round(k, 6) + 0.0).tolist(),
            "width": int(view["width"]),
            "height": int(view["height"]),
        },
    }


class HandOff:
    """Fills the hand-off fields of candidates from the active meshes and their views' cameras.

    ``meshes``: mesh_id -> active-mesh record (format, bounds, units_guess, scale_to_unit);
    ``fetch_views(mesh_ids)``: rows of ``sql/view_poses.sql``; ``up``: the render config's up axis.
    """

    def __init__(
        self,
        meshes: Callable[[str], dict],
        fetch_views: Callable[[list[str]], list[dict]],
        up: str,
        all_mesh_ids: list[str] | None = None,
    ):
        self._mesh = meshes
        self._fetch = fetch_views
        self.up = up or "auto"
        self._views: dict[str, dict[int, dict]] = {}
        self._lock = threading.Lock()
        small = all_mesh_ids is not None and len(all_mesh_ids) <= PRELOAD_MESHES
        self._preload = list(all_mesh_ids) if small else None

    def views_of(self, mesh_ids: list[str]) -> dict[str, dict[int, dict]]:
        """view_index -> camera row, per mesh (read once per mesh; a small library all at once)."""
        with self._lock:
            todo = sorted({m for m in mesh_ids if m not in self._views})
            if todo and self._preload is not None:
                todo, self._preload = sorted(set(self._preload) | set(todo)), None
        if todo:
            found: dict[str, dict[int, dict]] = {m: {} for m in todo}
            for row in self._fetch(todo):
                found[row["mesh_id"]][int(row["view_index"])] = row
            with self._lock:
                if self._views and len(self._views) + len(found) > MAX_CACHED:
                    self._views.clear()
                self._views.update(found)
        with self._lock:
            return {m: self._views.get(m, {}) for m in mesh_ids}

    def fill(self, candidates: list) -> None:
        """Set each candidate's units, scale, size, best-view pose and intrinsics in place."""
        views = self.views_of([c.mesh_id for c in candidates])
        for c in candidates:
            mesh = self._mesh(c.mesh_id)
            for key, value in metric_info(mesh).items():
                setattr(c, key, value)
            view = views.get(c.mesh_id, {}).get(c.best_view) if c.best_view is not None else None
            prior = view_prior(mesh, view, self.up) if view is not None else None
            if prior is not None:
                c.best_view_pose, c.intrinsics = prior["best_view_pose"], prior["intrinsics"]
