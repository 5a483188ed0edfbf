"""The evaluated library as plain data: the store's active meshes, how to find one by what a query names,
and the class label of each mesh (for class-level relevance)."""

from __future__ import annotations

import csv
import json
import os
import re
from dataclasses import dataclass, field
from pathlib import Path

#: Default class rule: the leading number of a YCB-style name ("065-a_cups" -> "065"); else the full name.
DEFAULT_CLASS_PATTERN = r"^(\d+)"


@dataclass(frozen=True)
class MeshRef:
    """One library mesh as the evaluation sees it."""

    mesh_id: str | None  # None for meshes read from a folder that was never onboarded
    source_path: str  # relative to library_root
    library_root: str
    name: str
    format: str

    @property
    def abs_path(self) -> str:
        return str(Path(self.library_root) / self.source_path)


def class_of(name: str, pattern: str | None = DEFAULT_CLASS_PATTERN) -> str:
    """Class label of a mesh name: the first group (or whole match) of ``pattern``, else the name."""
    if pattern:
        m = re.search(pattern, name)
        if m:
            return m.group(1) if m.groups() else m.group(0)
    return name


def load_class_map(path: str | os.PathLike) -> dict[str, str]:
    """Mesh -> class from a JSON object or a two-column CSV (mesh name, source path or mesh_id; label)."""
    p = Path(path)
    if p.suffix.lower() == ".json":
        data = json.loads(p.read_text())
        if not isinstance(data, dict):
            raise ValueError(f"{p}: expected a JSON object mapping mesh -> class label")
        return {str(k): str(v) for k, v in data.items()}
    with open(p, newline="") as fh:
        rows = [r for r in csv.reader(fh) if r and not r[0].startswith("#")]
    if rows and rows[0][:2] == ["mesh", "label"]:
        rows = rows[1:]
    return {r[0].strip(): r[1].strip() for r in rows if len(r) >= 2}


@dataclass
class Library:
    """Active meshes of a store (or a folder) with lookups by mesh_id, path and name, and class labels."""

    meshes: list[MeshRef]
    class_pattern: str | None = DEFAULT_CLASS_PATTERN
    class_map: dict[str, str] = field(default_factory=dict)

    def __post_init__(self) -> None:
        self.by_id = {m.mesh_id: m for m in self.meshes if m.mesh_id}
        self._keys: dict[str, set[str]] = {}
        for m in self.meshes:
            key = m.mesh_id or m.source_path
            for alias in (m.mesh_id, m.source_path, m.name, m.abs_path, _norm(m.abs_path)):
                if alias:
                    self._keys.setdefault(alias, set()).add(key)
        self.labels = {self.key(m): self._label(m) for m in self.meshes}

    @staticmethod
    def key(m: MeshRef) -> str:
        """The id rankings use for ``m``: its mesh_id (the source path for never-onboarded meshes)."""
        return m.mesh_id or m.source_path

    def _label(self, m: MeshRef) -> str:
        for alias in (m.mesh_id, m.source_path, m.name):
            if alias and alias in self.class_map:
                return self.class_map[alias]
        return class_of(m.name, self.class_pattern)

    def resolve(self, ref: str) -> set[str]:
        """Keys of the meshes ``ref`` names: a mesh_id, a path (relative to the library or absolute) or a name."""
        ref = ref.strip()
        for cand in (ref, _norm(ref), ref.lstrip("./")):
            if cand in self._keys:
                return set(self._keys[cand])
        # a path given relative to some parent of the library root ("ycb/006_x/textured.obj")
        hits = {self.key(m) for m in self.meshes if ref.endswith("/" + m.source_path)}
        return hits

    def with_label(self, label: str) -> set[str]:
        return {k for k, v in self.labels.items() if v == label}

    def name_of(self, key: str) -> str:
        m = self.by_id.get(key)
        if m is not None:
            return m.name
        return next((x.name for x in self.meshes if x.source_path == key), key)

    def __len__(self) -> int:
        return len(self.meshes)


def _norm(path: str) -> str:
    try:
        return os.path.realpath(path)
    except (OSError, ValueError):
        return path


def read_store_meshes(store_path: str | os.PathLike) -> list[MeshRef]:
    """Active meshes of the store (latest row per path), sorted by library root and path."""
    import pyarrow.compute as pc

    from pipeline.store import Store

    with Store.open(store_path) as store:
        t = store.read_latest(
            "meshes", columns=["mesh_id", "source_path", "library_root", "name", "format", "status"]
        )
    # a path's newest row wins: a changed file gets a new mesh_id and its old row is marked removed
    t = t.filter(pc.field("status") == "active")
    rows = sorted(t.to_pylist(), key=lambda r: (r["library_root"], r["source_path"]))
    seen: dict[str, MeshRef] = {}
    for r in rows:
        seen[r["mesh_id"]] = MeshRef(
            r["mesh_id"], r["source_path"], r["library_root"], r["name"] or r["source_path"], r["format"]
        )
    return list(seen.values())


def read_folder_meshes(library: str | os.PathLike) -> list[MeshRef]:
    """Meshes of a library folder (no hashing: queries then name their expected mesh by path)."""
    from pipeline.mesh.discover import walk_library

    root = str(Path(library).resolve())
    return [MeshRef(None, f.source_path, root, f.name, f.format) for f in walk_library(root)]
