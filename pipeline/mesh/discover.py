"""Discover meshes in a library folder, resolve the files each one references, and content-hash them.

Unchanged files are not re-hashed: a file whose size and mtime (and those of every file it references)
match what the store recorded keeps its ``mesh_id``.
"""

from __future__ import annotations

import hashlib
import json
import os
import re
from dataclasses import dataclass, field
from pathlib import Path

MESH_EXTENSIONS = {".obj": "obj", ".ply": "ply", ".glb": "glb", ".gltf": "gltf", ".stl": "stl", ".off": "off"}
_MTL_MAP = re.compile(r"^\s*(map_\w+|bump|disp|decal|norm|refl)\s+(.+?)\s*$", re.IGNORECASE)
_CHUNK = 1 << 20


class DiscoveryError(ValueError):
    """A mesh file whose references cannot be resolved (missing .mtl or texture, unreadable file)."""


@dataclass
class FoundFile:
    """One mesh file of the library as seen now."""

    source_path: str  # relative to the library root, posix separators
    abs_path: str
    format: str
    size: int
    mtime_ns: int
    deps: list[dict] = field(default_factory=list)  # [{"path": rel-to-mesh-dir, "size", "mtime_ns"}]
    mesh_id: str | None = None

    @property
    def name(self) -> str:
        """Readable model name: the parent folder for generic file names (``textured.obj``), else the stem."""
        p = Path(self.source_path)
        generic = {"textured", "model", "mesh", "scene", "untitled", "object"}
        if p.stem.lower() in generic and p.parent.name:
            return p.parent.name
        return p.stem


def walk_library(root: str | os.PathLike) -> list[FoundFile]:
    """All mesh files under ``root`` (hidden folders skipped), sorted by relative path."""
    root = Path(root).resolve()
    if not root.is_dir():
        raise DiscoveryError(f"library folder not found: {root}")
    found: list[FoundFile] = []
    stack = [root]
    while stack:
        d = stack.pop()
        try:
            entries = list(os.scandir(d))
        except OSError:
            continue
        for e in entries:
            if e.name.startswith("."):
                continue
            if e.is_dir(follow_symlinks=False):
                stack.append(Path(e.path))
                continue
            fmt = MESH_EXTENSIONS.get(os.path.splitext(e.name)[1].lower())
            if fmt is None:
                continue
            st = e.stat()
            rel = Path(e.path).relative_to(root).as_posix()
            found.append(FoundFile(rel, e.path, fmt, st.st_size, st.st_mtime_ns))
    found.sort(key=lambda f: f.source_path)
    return found


def referenced_files(path: str | os.PathLike, fmt: str) -> list[str]:
    """Files a mesh references, relative to its folder, in a stable order; raises on missing ones."""
    path = Path(path)
    base = path.parent
    refs: list[str] = []
    if fmt == "obj":
        for mtl in _obj_mtllibs(path):
            if not (base / mtl).is_file():
                raise DiscoveryError(f"missing material file {mtl!r} referenced by {path.name}")
            refs.append(mtl)
            mtl_dir = (base / mtl).parent
            for tex in _mtl_textures(base / mtl):
                rel = os.path.relpath(mtl_dir / tex, base)
                if not (base / rel).is_file():
                    raise DiscoveryError(f"missing texture {tex!r} referenced by {mtl}")
                refs.append(Path(rel).as_posix())
    elif fmt == "ply":
        for tex in _ply_textures(path):
            if not (base / tex).is_file():
                raise DiscoveryError(f"missing texture {tex!r} referenced by {path.name}")
            refs.append(tex)
    elif fmt == "gltf":
        try:
            doc = json.loads(path.read_text(encoding="utf-8"))
        except (OSError, UnicodeDecodeError, json.JSONDecodeError) as exc:
            raise DiscoveryError(f"unreadable glTF JSON: {exc}") from None
        for item in doc.get("buffers", []) + doc.get("images", []):
            uri = item.get("uri")
            if uri and not uri.startswith("data:"):
                if not (base / uri).is_file():
                    raise DiscoveryError(f"missing file {uri!r} referenced by {path.name}")
                refs.append(uri)
    return list(dict.fromkeys(refs))


def _obj_mtllibs(path: Path) -> list[str]:
    libs: list[str] = []
    with open(path, "rb") as fh:
        for raw in fh:
            if raw.startswith(b"mtllib"):
                libs.append(raw[6:].decode("utf-8", "replace").strip())
            elif raw[:2] in (b"v ", b"f "):  # references precede geometry in practice; stop scanning early
                if libs:
                    break
    return libs


def _mtl_textures(mtl: Path) -> list[str]:
    out = []
    for line in mtl.read_text(encoding="utf-8", errors="replace").splitlines():
        m = _MTL_MAP.match(line)
        if m:
            # options such as "-s 1 1 1" may precede the file name; the name is the last token
            out.append(m.group(2).split()[-1])
    return out


def _ply_textures(path: Path) -> list[str]:
    out = []
    with open(path, "rb") as fh:
        for _ in range(200):
            line = fh.readline()
            if not line or line.strip() == b"end_header":
                break
            parts = line.decode("latin-1").split()
            if len(parts) >= 3 and parts[0] == "comment" and parts[1].lower() == "texturefile":
                out.append(" ".join(parts[2:]))
    return out


def stat_deps(abs_path: str, refs: list[str]) -> list[dict]:
    """Size and mtime of each referenced file."""
    base = Path(abs_path).parent
    out = []
    for r in refs:
        st = (base / r).stat()
        out.append({"path": r, "size": st.st_size, "mtime_ns": st.st_mtime_ns})
    return out


def content_hash(abs_path: str, refs: list[str]) -> str:
    """sha256 over the mesh file and each referenced file (name + bytes), in order."""
    h = hashlib.sha256()
    base = Path(abs_path).parent
    for rel, p in [("", Path(abs_path))] + [(r, base / r) for r in refs]:
        h.update(rel.encode() + b"\0")
        with open(p, "rb") as fh:
            while chunk := fh.read(_CHUNK):
                h.update(chunk)
        h.update(b"\0")
    return h.hexdigest()


def deps_unchanged(abs_path: str, recorded: list[dict] | None) -> bool:
    """True when every recorded referenced file still has its recorded size and mtime."""
    base = Path(abs_path).parent
    for d in recorded or []:
        try:
            st = (base / d["path"]).stat()
        except OSError:
            return False
        if st.st_size != d["size"] or st.st_mtime_ns != d["mtime_ns"]:
            return False
    return True


def identify(f: FoundFile, cached: dict | None) -> FoundFile:
    """Fill ``f.mesh_id`` and ``f.deps``: from the cache when nothing changed, else by hashing."""
    if (
        cached is not None
        and cached["file_size"] == f.size
        and cached["mtime_ns"] == f.mtime_ns
        and deps_unchanged(f.abs_path, cached["deps"])
    ):
        f.mesh_id = cached["mesh_id"]
        f.deps = list(cached["deps"] or [])
        return f
    try:
        refs = referenced_files(f.abs_path, f.format)
        f.deps = stat_deps(f.abs_path, refs)
        f.mesh_id = content_hash(f.abs_path, refs)
    except OSError as exc:
        raise DiscoveryError(f"unreadable file: {exc.strerror or exc}") from None
    return f
