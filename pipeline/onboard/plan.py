"""Planning an onboarding run: what is new, changed, vanished, and which stages each mesh still needs.

Everything here reads the store and the library; nothing here renders or loads a model, so an unchanged
library re-runs in seconds.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import pyarrow as pa
import pyarrow.compute as pc

from pipeline import schemas
from pipeline.mesh.discover import DiscoveryError, FoundFile, identify, walk_library
from pipeline.onboard.config import OnboardConfig
from pipeline.store import Store, latest_rows, slug


@dataclass
class Plan:
    """The work of one run."""

    library_root: str
    files: list[FoundFile]  # identified files (mesh_id set)
    discover_errors: list[tuple[FoundFile, str]]
    removed_rows: list[dict]  # meshes rows marking vanished / replaced files
    new_paths: dict[str, list[FoundFile]]  # mesh_id -> files that need a meshes row
    render: list[str] = field(default_factory=list)  # mesh_ids, in library order
    caption: set[str] = field(default_factory=set)
    embed_text: set[str] = field(default_factory=set)
    embed_image: dict[str, set[str]] = field(default_factory=dict)  # role -> mesh_ids
    skipped: int = 0  # meshes with nothing left to do
    failed_before: int = 0  # meshes skipped because they failed with the same config before
    n_hashed: int = 0

    def file_of(self) -> dict[str, FoundFile]:
        """mesh_id -> the first file (in library order) with that content: the one rendered."""
        out: dict[str, FoundFile] = {}
        for f in self.files:
            out.setdefault(f.mesh_id, f)
        return out

    def downstream_ids(self) -> list[str]:
        """Meshes that need caption or embedding work but no rendering, in library order."""
        pending = self.caption | self.embed_text | set().union(*self.embed_image.values())
        order = list(dict.fromkeys(f.mesh_id for f in self.files))
        render = set(self.render)
        return [m for m in order if m in pending and m not in render]


def mesh_state(store: Store, library_root: str) -> pa.Table:
    """Latest meshes row per (path, mesh_id) of this library."""
    t = store.read("meshes", filter=pc.field("library_root") == library_root)
    return latest_rows(t, list(schemas.KEYS["meshes"]))


def done_ids(store: Store, dataset: str, fp: str) -> set[str]:
    """mesh_ids that have rows of fingerprint ``fp`` in ``dataset``."""
    if store.dataset(dataset) is None:
        return set()
    t = store.read(dataset, columns=["mesh_id"], filter=pc.field("fingerprint") == fp)
    return set(pc.unique(t.column("mesh_id")).to_pylist())


def failed_ids(store: Store) -> dict[str, set[str]]:
    """fingerprint -> mesh_ids with an error row at that fingerprint."""
    t = store.read("errors", columns=["mesh_id", "fingerprint"])
    out: dict[str, set[str]] = {}
    for m, fp in zip(t.column("mesh_id").to_pylist(), t.column("fingerprint").to_pylist(), strict=True):
        if m and fp:
            out.setdefault(fp, set()).add(m)
    return out


def make_plan(
    store: Store, library: str, cfg: OnboardConfig, text_slug: str, image_slugs: dict[str, str]
) -> Plan:
    """Discover the library and decide the work of this run."""
    from pathlib import Path

    root = str(Path(library).resolve())
    found = walk_library(root)
    state = mesh_state(store, root)
    rows = state.to_pylist()
    by_path: dict[str, list[dict]] = {}
    for r in rows:
        by_path.setdefault(r["source_path"], []).append(r)
    current: dict[str, dict] = {}  # path -> its live (active/failed) row
    for path, rs in by_path.items():
        live = [r for r in rs if r["status"] != "removed"]
        if live:
            current[path] = max(live, key=lambda r: (r["run_id"], r["seen_at"]))

    files, errors, n_hashed = [], [], 0
    for f in found:
        cached = current.get(f.source_path)
        try:
            identify(f, cached)
        except DiscoveryError as exc:
            errors.append((f, str(exc)))
            continue
        n_hashed += cached is None or cached["mesh_id"] != f.mesh_id or cached["mtime_ns"] != f.mtime_ns
        files.append(f)

    seen_paths = {f.source_path: f for f in files}
    bad_paths = {f.source_path for f, _ in errors}
    removed_rows, new_paths = [], {}
    for path, row in current.items():
        f = seen_paths.get(path)
        if (f is None and path not in bad_paths) or (f is not None and f.mesh_id != row["mesh_id"]):
            removed_rows.append({**row, "status": "removed"})
    for f in files:
        row = current.get(f.source_path)
        if row is None or row["mesh_id"] != f.mesh_id:
            new_paths.setdefault(f.mesh_id, []).append(f)

    plan = Plan(root, files, errors, removed_rows, new_paths, n_hashed=n_hashed)
    fps = cfg.fingerprints()
    failed = failed_ids(store) if not cfg.retry_failed else {}
    force = set(cfg.force)
    ids = list(dict.fromkeys(f.mesh_id for f in files))

    def todo(dataset: str, fp: str, stage: str) -> set[str]:
        if stage in force:
            return set(ids)
        return set(ids) - done_ids(store, dataset, fp)

    bad_render = failed.get(fps["render"], set())
    need_render = todo("views", fps["render"], "render") - bad_render
    # a mesh that must be re-rendered needs everything downstream again
    plan.render = [m for m in ids if m in need_render]
    for f in files:  # a failed mesh that is rendered again gets a fresh meshes row (active or failed)
        row = current.get(f.source_path)
        if (
            row is not None
            and row["status"] == "failed"
            and row["mesh_id"] == f.mesh_id
            and f.mesh_id in need_render
        ):
            new_paths.setdefault(f.mesh_id, []).append(f)
    ok = set(ids) - bad_render
    plan.caption = ((todo("captions", fps["caption"], "caption") | need_render) & ok) - failed.get(
        fps["caption"], set()
    )
    plan.embed_text = (
        (todo(f"text_embeddings/{text_slug}", fps["embed_text"], "embed_text") | plan.caption) & ok
    ) - failed.get(fps["embed_text"], set())
    for role, s in image_slugs.items():
        fp = fps[f"embed_image:{role}"]
        plan.embed_image[role] = (
            (todo(f"image_embeddings/{s}", fp, "embed_image") | need_render) & ok
        ) - failed.get(fp, set())
    busy = set(plan.render) | plan.caption | plan.embed_text | set().union(*plan.embed_image.values())
    plan.failed_before = len(
        {m for m in ids if m in bad_render or any(m in failed.get(fp, ()) for fp in fps.values())} - busy
    )
    plan.skipped = len(set(ids) - busy)
    return plan


def encoder_slugs(cfg: OnboardConfig) -> tuple[str, dict[str, str]]:
    """Dataset slugs of the text encoder and of each image encoder role of ``cfg``."""
    p = cfg.get_profile()
    return slug(p.text_encoder.key()), {r: slug(getattr(p, r).key()) for r in cfg.image_roles()}
