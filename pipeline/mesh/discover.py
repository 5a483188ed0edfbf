"""Discover meshes in a library folder, resolve the files each one references, and content-hash them.

Unchanged files are not re-hashed: a file whose size and mtime (and those of every file it references)
match what the store recorded keeps its ``mesh_id``.
"""

from __future__ import annotations

import errno
import fcntl
import hashlib
import json
import os
import re
import stat
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


def walk_library(
    root: str | os.PathLike, problems: list[tuple[FoundFile, str]] | None = None
) -> list[FoundFile]:
    """All mesh files under ``root`` (hidden folders skipped), sorted by relative path.

    Rules (docs/architecture.md, "Discovery"): symlinked files are read through their link; a symlinked
    folder is followed once: a folder (by device and inode) already walked is not walked again, so link
    loops end. Entries with a mesh extension that cannot be used are appended to ``problems`` as
    ``(FoundFile, reason)`` (errors rows) instead of being read: dangling or looping symlinks, FIFOs,
    sockets and devices (opening a FIFO would block forever), files that vanish while being listed.
    """
    root = Path(root).resolve()
    if not root.is_dir():
        raise DiscoveryError(f"library folder not found: {root}")
    found: list[FoundFile] = []
    problems = problems if problems is not None else []
    walked: dict[tuple[int, int], str] = {}
    stack, linked = [root], []  # the real tree first, then symlinked folders: deterministic "first"
    while stack or linked:
        d = stack.pop() if stack else linked.pop(0)
        try:
            st = d.stat()
            entries = sorted(os.scandir(d), key=lambda e: e.name)
        except OSError:
            continue
        key = (st.st_dev, st.st_ino)
        rel_dir = d.relative_to(root).as_posix() if d != root else "."
        if key in walked:
            _problem(
                problems,
                rel_dir,
                str(d),
                f"symlinked folder leads to {walked[key]!r}, already walked: followed once, not again",
            )
            continue
        walked[key] = rel_dir
        for e in entries:
            if e.name.startswith("."):
                continue
            is_link = e.is_symlink()  # d_type: no system call for plain files and folders
            if not is_link and e.is_dir(follow_symlinks=False):
                stack.append(Path(e.path))
                continue
            fmt = MESH_EXTENSIONS.get(os.path.splitext(e.name)[1].lower())
            if fmt is None and not is_link:
                continue  # textures, materials, anything else: never stat'ed here
            rel = Path(e.path).relative_to(root).as_posix()
            if fmt is not None and not _utf8(rel):
                _problem(problems, rel, e.path, "file name is not valid UTF-8: rename the file")
                continue
            try:
                st = os.stat(e.path)  # follows symlinks
            except OSError as exc:
                _problem(problems, rel, e.path, _stat_reason(e, exc))
                continue
            if stat.S_ISDIR(st.st_mode):
                (linked if is_link else stack).append(Path(e.path))
                continue
            if fmt is None:
                continue
            if not stat.S_ISREG(st.st_mode):
                _problem(problems, rel, e.path, f"not a regular file ({_kind(st.st_mode)}): skipped")
                continue
            found.append(FoundFile(rel, e.path, fmt, st.st_size, st.st_mtime_ns))
    found.sort(key=lambda f: f.source_path)
    problems.sort(key=lambda p: p[0].source_path)
    return found


def _utf8(text: str) -> bool:
    try:
        text.encode("utf-8")
    except UnicodeEncodeError:
        return False
    return True


def _problem(problems: list, rel: str, abs_path: str, reason: str) -> None:
    rel = rel.encode("utf-8", "surrogateescape").decode("utf-8", "backslashreplace")  # storable text
    fmt = MESH_EXTENSIONS.get(os.path.splitext(rel)[1].lower(), "unknown")
    problems.append((FoundFile(rel, abs_path, fmt, 0, 0), reason))


def _stat_reason(entry: os.DirEntry, exc: OSError) -> str:
    if entry.is_symlink():
        target = os.readlink(entry.path) if os.path.islink(entry.path) else "?"
        if exc.errno == errno.ELOOP:
            return f"symlink loop ({entry.name} -> {target}): skipped"
        return f"dangling symlink ({entry.name} -> {target}, target {exc.strerror or exc}): skipped"
    if exc.errno == errno.ENOENT:
        return "file vanished while the library was listed"
    return f"cannot stat: {exc.strerror or exc}"


def _kind(mode: int) -> str:
    if stat.S_ISFIFO(mode):
        return "a FIFO"
    if stat.S_ISSOCK(mode):
        return "a socket"
    if stat.S_ISCHR(mode) or stat.S_ISBLK(mode):
        return "a device"
    return "not a file"


def open_regular(path: str | os.PathLike):
    """Open ``path`` for binary reading, refusing anything but a regular file without ever blocking.

    ``O_NONBLOCK`` makes opening a FIFO return at once (instead of waiting for a writer); ``fstat`` on the
    open descriptor then rejects it, so a file swapped for a FIFO after the walk cannot hang the run.
    """
    fd = os.open(path, os.O_RDONLY | os.O_NONBLOCK)
    try:
        mode = os.fstat(fd).st_mode
        if not stat.S_ISREG(mode):
            raise DiscoveryError(f"{Path(path).name} is {_kind(mode)}, not a regular file")
        fcntl.fcntl(fd, fcntl.F_SETFL, fcntl.fcntl(fd, fcntl.F_GETFL) & ~os.O_NONBLOCK)
        return os.fdopen(fd, "rb")
    except BaseException:
        os.close(fd)
        raise


def _is_regular(path: Path) -> bool:
    try:
        return stat.S_ISREG(os.stat(path).st_mode)
    except OSError:
        return False


def referenced_files(path: str | os.PathLike, fmt: str) -> list[str]:
    """Files a mesh references, relative to its folder, in a stable order; raises on missing ones."""
    path = Path(path)
    base = path.parent
    refs: list[str] = []
    if fmt == "obj":
        for mtl in _obj_mtllibs(path):
            if not _is_regular(base / mtl):
                raise DiscoveryError(f"missing material file {mtl!r} referenced by {path.name}")
            refs.append(mtl)
            mtl_dir = (base / mtl).parent
            for tex in _mtl_textures(base / mtl):
                rel = os.path.relpath(mtl_dir / tex, base)
                if not _is_regular(base / rel):
                    raise DiscoveryError(f"missing texture {tex!r} referenced by {mtl}")
                refs.append(Path(rel).as_posix())
    elif fmt == "ply":
        for tex in _ply_textures(path):
            if not _is_regular(base / tex):
                raise DiscoveryError(f"missing texture {tex!r} referenced by {path.name}")
            refs.append(tex)
    elif fmt == "gltf":
        try:
            with open_regular(path) as fh:
                doc = json.loads(fh.read().decode("utf-8"))
        except (OSError, UnicodeDecodeError, json.JSONDecodeError) as exc:
            raise DiscoveryError(f"unreadable glTF JSON: {exc}") from None
        for item in doc.get("buffers", []) + doc.get("images", []):
            uri = item.get("uri")
            if uri and not uri.startswith("data:"):
                if not _is_regular(base / uri):
                    raise DiscoveryError(f"missing file {uri!r} referenced by {path.name}")
                refs.append(uri)
    return list(dict.fromkeys(refs))


def _obj_mtllibs(path: Path) -> list[str]:
    libs: list[str] = []
    with open_regular(path) as fh:
        for raw in fh:
            if raw.startswith(b"mtllib"):
                libs.append(raw[6:].decode("utf-8", "replace").strip())
            elif raw[:2] in (b"v ", b"f "):  # references precede geometry in practice; stop scanning early
                if libs:
                    break
    return libs


def _mtl_textures(mtl: Path) -> list[str]:
    out = []
    with open_regular(mtl) as fh:
        text = fh.read().decode("utf-8", "replace")
    for line in text.splitlines():
        m = _MTL_MAP.match(line)
        if m:
            # options such as "-s 1 1 1" may precede the file name; the name is the last token
            out.append(m.group(2).split()[-1])
    return out


def _ply_textures(path: Path) -> list[str]:
    out = []
    with open_regular(path) as fh:
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
        with open_regular(p) as fh:
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


#: Seconds one file (with its references) may take to hash before it becomes an errors row.
HASH_TIMEOUT_S = 600.0


def identify(f: FoundFile, cached: dict | None, hash_timeout_s: float | None = None) -> FoundFile:
    """Fill ``f.mesh_id`` and ``f.deps``: from the cache when nothing changed, else by hashing (at most
    ``hash_timeout_s``, default :data:`HASH_TIMEOUT_S`, per file)."""
    hash_timeout_s = HASH_TIMEOUT_S if hash_timeout_s is None else hash_timeout_s
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
        f.mesh_id = _with_timeout(lambda: content_hash(f.abs_path, refs), hash_timeout_s)
    except TimeoutError:
        raise DiscoveryError(
            f"hashing took more than {hash_timeout_s:g} s (hung network mount?): skipped this run"
        ) from None
    except FileNotFoundError as exc:
        raise DiscoveryError(
            f"file vanished during the run: {Path(exc.filename or f.abs_path).name}"
        ) from None
    except OSError as exc:
        raise DiscoveryError(f"unreadable file: {exc.strerror or exc}") from None
    return f


def _with_timeout(fn, timeout_s: float):
    """``fn()`` in a daemon thread; ``TimeoutError`` after ``timeout_s`` (the thread is abandoned, not
    joined, so a read stuck on a hung mount cannot hold the run or the process exit)."""
    import threading

    box: dict = {}

    def target() -> None:
        try:
            box["value"] = fn()
        except BaseException as exc:
            box["error"] = exc

    t = threading.Thread(target=target, name="hash", daemon=True)
    t.start()
    t.join(timeout_s)
    if t.is_alive():
        raise TimeoutError
    if "error" in box:
        raise box["error"]
    return box["value"]
