"""Where a stage-1 index lives and what its manifest records.

``STORE/_index/stage1/<dataset slug>-<fingerprint hash>/`` holds one index of one text-embedding dataset
at one fingerprint:

* ``vectors-<n>.f32``: the float32 caption vectors, one row per *slot*, append-only (a replaced or
  removed row keeps its slot, marked dead): exact rescoring reads survivors' rows from it, memory-mapped,
  so the floats never have to be resident;
* ``base-<g>.faiss`` + ``base-<g>-<array>.npy`` + ``meshes-<g>.arrow``: the IVF index over the base slots,
  and per base slot its mesh code, view index and run code (plus the slot order by key and by mesh, the
  centroids and the mesh ids' sorted order), one plain ``.npy`` per array so that a sync memory-maps them
  and reads only the pages its keys touch;
* ``delta-<k>.npz``: slots appended since the base was written, dead slots, meshes new since the base;
* ``manifest.json`` (replaced atomically, last): the Delta version and data files covered, encoder id,
  fingerprint, codec, error bound, drift statistics and the size of every file above.

Readers load the manifest and then only the files it names; writers never change a named file (new
generations get new names; the vector file only grows), so a reader's snapshot stays consistent while a
writer syncs. Old generations are deleted two generations later.
"""

from __future__ import annotations

import hashlib
import json
import os
from pathlib import Path

INDEX_DIR = ("_index", "stage1")
MANIFEST = "manifest.json"
LOCK = "sync.lock"
FORMAT = 2  # 2: the base's arrays are separate .npy files (1: one .npz)


def index_dir(store_root: Path, dataset: str, fingerprint: str) -> Path:
    """The directory of the index of ``dataset`` at ``fingerprint``."""
    slug = dataset.replace("/", "__")
    key = hashlib.sha1(fingerprint.encode()).hexdigest()[:12]
    return Path(store_root).joinpath(*INDEX_DIR) / f"{slug}-{key}"


def read_manifest(directory: Path) -> dict | None:
    """The manifest, or ``None`` when there is none (a damaged one raises ``ValueError``)."""
    path = directory / MANIFEST
    try:
        text = path.read_text()
    except FileNotFoundError:
        return None
    try:
        man = json.loads(text)
    except ValueError as exc:
        raise ValueError(f"{path}: not JSON ({exc})") from None
    if not isinstance(man, dict):
        raise ValueError(f"{path}: not a stage-1 index manifest")
    if man.get("format") != FORMAT:
        raise ValueError(
            f"{path}: an index of format {man.get('format')!r}, this version reads {FORMAT} (a sync rebuilds it)"
        )
    return man


def write_manifest(directory: Path, man: dict) -> None:
    """Replace the manifest atomically (after every file it names is on disk)."""
    man = {**man, "format": FORMAT}
    man["sizes"] = {name: (directory / name).stat().st_size for name in named_files(man)}
    tmp = directory / f"{MANIFEST}.{os.getpid()}.partial"
    tmp.write_text(json.dumps(man))
    os.replace(tmp, directory / MANIFEST)


def named_files(man: dict) -> list[str]:
    """The files a manifest names."""
    base = man["base"]
    return [man["vectors"], base["faiss"], *base["arrays"].values(), base["meshes"], man["delta"]["file"]]


def base_array(directory: Path, man: dict, name: str, *, mmap: bool = True):
    """One array of the base's slot metadata, memory-mapped read-only unless ``mmap`` is false."""
    import numpy as np

    return np.load(directory / man["base"]["arrays"][name], mmap_mode="r" if mmap else None, allow_pickle=False)


def check_files(directory: Path, man: dict) -> str | None:
    """``None`` when every named file is present with its recorded size, else what is wrong.

    The vector file only grows, so it may be longer than recorded, never shorter."""
    sizes = man.get("sizes", {})
    for name in named_files(man):
        path = directory / name
        try:
            size = path.stat().st_size
        except FileNotFoundError:
            return f"{path} is missing"
        want = sizes.get(name)
        if want is None or (size < want if name == man["vectors"] else size != want):
            return f"{path} is {size} bytes, the index manifest says {want}"
    need = man["n_slots"] * man["dim"] * 4
    if (directory / man["vectors"]).stat().st_size < need:
        return f"{directory / man['vectors']} is shorter than its {man['n_slots']} rows"
    return None


def remove_unnamed(directory: Path, keep: set[str]) -> None:
    """Delete generation files that neither the current manifest nor ``keep`` names, and the partial files
    of writers that died (call it holding the writer lock). A manifest this version cannot read (damaged,
    another format) names nothing: its index is rebuilt, never read."""
    try:
        man = read_manifest(directory)
    except (ValueError, OSError):
        man = None
    keep = set(keep) | (set(named_files(man)) if man else set())
    for p in directory.iterdir():
        if p.name in keep or p.name in (MANIFEST, LOCK):
            continue
        if p.name.endswith(".partial") or p.suffix in (".faiss", ".npz", ".npy", ".arrow", ".f32"):
            p.unlink(missing_ok=True)
