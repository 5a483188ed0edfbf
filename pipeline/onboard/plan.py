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
from pipeline.onboard.config import RunSpec
from pipeline.store import Store, latest_rows


@dataclass
class Plan:
    """The work of one run."""

    library_root: str
    files: list[FoundFile]  # identified files (mesh_id set)
    discover_errors: list[tuple[FoundFile, str]]
    removed_rows: list[dict]  # meshes rows marking vanished / replaced files
    new_paths: dict[str, list[FoundFile]]  # mesh_id -> files that need a meshes row
    todo: dict[str, set[str]] = field(default_factory=dict)  # step key -> mesh_ids that need it
    render: list[str] = field(default_factory=list)  # mesh_ids that need the first step, in library order
    skipped: int = 0  # meshes with nothing left to do
    failed_before: int = 0  # meshes skipped because they failed with the same config before
    n_hashed: int = 0
    n_active_before: int = 0  # files of this library that were active before the run
    n_vanished: int = 0  # of those, files the library no longer yields (the removal guard counts them)
    restored: int = 0  # new paths whose mesh was onboarded before (a library that came back)
    restored_unchanged: int = 0  # meshes of those with nothing left to do (not counted as unchanged)
    resumed: int = 0  # meshes already in the store with stages left (an interrupted run, a new stage, --force)

    def file_of(self) -> dict[str, FoundFile]:
        """mesh_id -> the first file (in library order) with that content: the one rendered."""
        out: dict[str, FoundFile] = {}
        for f in self.files:
            out.setdefault(f.mesh_id, f)
        return out

    def downstream_ids(self) -> list[str]:
        """Meshes that need work after the first step but no rendering, in library order."""
        pending = set().union(*self.todo.values())
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


def make_plan(store: Store, library: str, run: RunSpec) -> Plan:
    """Discover the library and decide the work of this run."""
    from pathlib import Path

    root = str(Path(library).resolve())
    problems: list[tuple[FoundFile, str]] = []
    found = walk_library(root, problems)
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

    files, errors, n_hashed = [], list(problems), 0
    for f in found:
        cached = current.get(f.source_path)
        try:
            identify(f, cached)
        except DiscoveryError as exc:
            errors.append((f, str(exc)))
            continue
        except Exception as exc:  # one file never stops a run
            errors.append((f, f"{type(exc).__name__}: {exc}"))
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
    active = {p for p, r in current.items() if r["status"] == "active"}
    plan.n_active_before = len(active)
    plan.n_vanished = len({p for p in active if p not in seen_paths and p not in bad_paths})
    cfg = run.cfg
    failed = failed_ids(store) if not cfg.retry_failed else {}
    force = set(cfg.force)
    ids = list(dict.fromkeys(f.mesh_id for f in files))

    # a mesh whose rendering failed with this config has nothing to feed the later steps
    bad_render = failed.get(run.source.fingerprint, set())
    ok = set(ids) - bad_render
    for step in run.steps:
        need = (
            set(ids)
            if step.stage.name in force
            else set(ids) - done_ids(store, step.dataset, step.fingerprint)
        )
        if step.input is not None:  # a mesh whose input is redone needs this step again too
            need |= plan.todo[step.input]
        plan.todo[step.key] = (need & ok) - failed.get(step.fingerprint, set())
    need_render = plan.todo[run.source.key]
    plan.render = [m for m in ids if m in need_render]
    back = {m for m in new_paths if m not in need_render and m not in bad_render}
    plan.restored = sum(len(new_paths[m]) for m in back)
    for f in files:  # a failed mesh that is rendered again gets a fresh meshes row (active or failed)
        row = current.get(f.source_path)
        if (
            row is not None
            and row["status"] == "failed"
            and row["mesh_id"] == f.mesh_id
            and f.mesh_id in need_render
        ):
            new_paths.setdefault(f.mesh_id, []).append(f)
    busy = set().union(*plan.todo.values())
    fps = run.fingerprints.values()
    plan.failed_before = len(
        {m for m in ids if m in bad_render or any(m in failed.get(fp, ()) for fp in fps)} - busy
    )
    plan.restored_unchanged = len(back - busy)
    plan.resumed = len(busy - set(new_paths))
    plan.skipped = len(set(ids) - busy) - plan.restored_unchanged
    return plan
