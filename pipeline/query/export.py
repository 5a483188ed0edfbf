"""``--export DIR``: copy the winning model's mesh file with its material and texture files."""

from __future__ import annotations

import shutil
from pathlib import Path

from pipeline.query.errors import QueryError


def export_mesh(mesh: dict, out_dir: str | Path) -> tuple[Path, list[Path], bool]:
    """Copy ``mesh`` (an active-mesh record) into ``out_dir/<name>/``, keeping the references' relative paths.

    Returns (folder, copied files, unchanged) where ``unchanged`` says the files still hash to the mesh_id.
    """
    from pipeline.mesh.discover import content_hash

    src = Path(mesh["library_root"]) / mesh["source_path"]
    if not src.is_file():
        raise QueryError(f"the model's file is gone: {src} (run onboarding again to refresh the store)")
    deps = [d["path"] for d in (mesh.get("deps") or [])]
    base = src.parent
    missing = [d for d in deps if not (base / d).is_file()]
    if missing:
        raise QueryError(f"the model's referenced file is gone: {base / missing[0]}")
    unchanged = content_hash(str(src), deps) == mesh["mesh_id"]
    dest = Path(out_dir) / _safe(mesh.get("name") or src.stem)
    copied = []
    try:
        dest.mkdir(parents=True, exist_ok=True)
        copied.append(Path(shutil.copy2(src, dest / src.name)))
        for rel in deps:
            target = (dest / rel).resolve()
            if dest.resolve() not in target.parents:  # "../tex.png": keep it inside the export folder
                target = dest / Path(rel).name
            target.parent.mkdir(parents=True, exist_ok=True)
            copied.append(Path(shutil.copy2(base / rel, target)))
    except OSError as exc:
        raise QueryError(f"cannot export to {dest}: {exc.strerror or exc}") from None
    return dest, copied, unchanged


def _safe(name: str) -> str:
    keep = "".join(c if c.isalnum() or c in "._-" else "_" for c in name).strip("._")
    return keep or "model"
