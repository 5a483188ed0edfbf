"""What a query needs from a store, loaded once: the onboarding run's models and fingerprints, the
active meshes, the stage-1 caption table and the stage-2 view table.

The two embedding tables are derived data: they are cached as Arrow IPC files under
``STORE/_cache/query/`` (memory-mapped on the next open), keyed by the store parts they were built from,
so a warm open of a 1M-caption store costs milliseconds instead of a Parquet scan.
"""

from __future__ import annotations

import json
import os
from dataclasses import dataclass
from pathlib import Path

import pyarrow as pa

from pipeline.db import connect, load_sql
from pipeline.fingerprint import fingerprint
from pipeline.query.errors import QueryError
from pipeline.query.stage1 import SLICES, slice_layout
from pipeline.store import Store, slug

CACHE_DIR = ("_cache", "query")
#: tables smaller than this are rebuilt on every open instead of being cached (building is cheaper than IO)
CACHE_MIN_ROWS = 20_000
#: model roles whose identity decides whether a store's rows are comparable with the query's vectors
CHECKED_ROLES = ("captioner", "text_encoder", "view_encoder", "clip_image_encoder")


@dataclass(frozen=True)
class Onboarding:
    """What the latest successful onboarding run of a store used."""

    run_id: str
    profile: str
    models: dict[str, str | None]  # role -> "backend:model_id"
    fingerprints: dict[str, str]  # stage -> fingerprint


def latest_onboarding(store: Store) -> Onboarding:
    """The latest ``runs`` row with status ok (raises :class:`QueryError` when there is none)."""
    runs = store.read("runs", columns=["run_id", "profile", "config_json", "status"])
    rows = [r for r in runs.to_pylist() if r["status"] == "ok" and r["config_json"]]
    if not rows:
        raise QueryError(
            f"store {store.root} has no completed onboarding run: "
            f"run `python -m pipeline.onboard LIBRARY --store {store.root}`"
        )
    row = max(rows, key=lambda r: r["run_id"])
    cfg = json.loads(row["config_json"])
    return Onboarding(
        row["run_id"], cfg.get("profile") or row["profile"] or "?", cfg["models"], cfg["fingerprints"]
    )


def check_models(onboarding: Onboarding, profile_name: str, keys: dict[str, str], store_root) -> None:
    """Fail with one line when the store's vectors come from other models than the query's."""
    for role in CHECKED_ROLES:
        if role not in keys:
            continue
        stored = onboarding.models.get(role)
        if stored != keys[role]:
            fix = (
                f"query with --profile {onboarding.profile}"
                if onboarding.profile != profile_name
                else "pass the same --model overrides as at onboarding"
            )
            raise QueryError(
                f"store {store_root} was onboarded with {role} {stored or 'none'} (profile "
                f"{onboarding.profile}) but the query uses {keys[role]} (profile {profile_name}): {fix}, "
                f"or onboard again with --profile {profile_name}"
            )


class StoreTables:
    """Active meshes and the embedding tables of one store state, for one profile's encoders."""

    def __init__(self, store: Store, onboarding: Onboarding, *, use_cache: bool = True) -> None:
        self.store = store
        self.onboarding = onboarding
        self.use_cache = use_cache
        fps = onboarding.fingerprints
        self.text_dataset = f"text_embeddings/{slug(onboarding.models['text_encoder'])}"
        self.view_dataset = f"image_embeddings/{slug(onboarding.models['view_encoder'])}"
        self.con = connect_store(store)
        self.meshes = self.con.sql(load_sql("query_active_meshes")).to_arrow_table()
        if self.meshes.num_rows == 0:
            raise QueryError(
                f"store {store.root} has no active meshes: onboard a library first "
                f"(`python -m pipeline.onboard LIBRARY --store {store.root}`)"
            )
        self.con.register("query_meshes", self.meshes.select(["mesh_idx", "mesh_id"]))
        if self.store.dataset(self.text_dataset) is None:
            raise QueryError(f"store {store.root} has no caption embeddings: re-run onboarding")
        self.captions = self._embeddings("caption", self.text_dataset, fps["embed_text"], slice_layout)
        self.views = self._embeddings("view", self.view_dataset, fps["embed_image:view_encoder"])
        if self.captions.num_rows == 0:
            raise QueryError(
                f"store {store.root} has no caption embeddings for its active meshes: re-run onboarding"
            )

    # ------------------------------------------------------------------ embeddings (cached)
    def _embeddings(self, kind: str, dataset: str, fp: str, layout=None) -> pa.Table:
        """The rows of ``dataset`` a query uses (``query_<kind>_embeddings.sql``), in ``layout``, cached."""
        key = fingerprint(
            {
                "kind": kind,
                "fp": fp,
                "parts": [p.name for p in self.store.parts(dataset)],
                "meshes": [p.name for p in self.store.parts("meshes")],
                "sql": load_sql(f"query_{kind}_embeddings") + load_sql("query_active_meshes"),
                "layout": (getattr(layout, "__name__", None), SLICES),
            }
        )
        cache = self._cache_path(kind, key)
        if cache is not None and cache.exists():
            try:
                return _read_ipc(cache)
            except (OSError, pa.ArrowInvalid):
                pass  # a damaged cache file is rebuilt below
        d = self.store.dataset(dataset)
        if d is None:
            return pa.table({"mesh_idx": pa.array([], pa.int32()), "view_index": pa.array([], pa.int16())})
        self.con.register(f"query_{kind}_source", d)
        table = self.con.sql(
            load_sql(f"query_{kind}_embeddings"), params={"fingerprint": fp}
        ).to_arrow_table()
        self.con.unregister(f"query_{kind}_source")
        table = layout(table) if layout is not None else table.combine_chunks()
        if cache is not None and table.num_rows >= CACHE_MIN_ROWS:
            _write_ipc_atomic(table, cache, stale=cache.parent.glob(f"{kind}-*.arrow"))
        return table

    def _cache_path(self, kind: str, key: str) -> Path | None:
        if not self.use_cache:
            return None
        return self.store.root.joinpath(*CACHE_DIR) / f"{kind}-{key}.arrow"


def store_version(root) -> object:
    """An opaque token that changes with every commit to the store at ``root``; cheap enough to poll.

    The one place that knows how a store is versioned (the commit log's newest sequence number today):
    the query service compares tokens to decide when to reopen. ``None`` when the store has no commit.
    """
    import pipeline.store as store_module

    own = getattr(store_module, "store_version", None)  # a store backend that versions itself
    if callable(own):
        return own(root)
    from pipeline.store import LOG_DIR

    log = Path(root) / LOG_DIR
    try:
        seqs = [int(name[:-5]) for name in os.listdir(log) if name.endswith(".json") and name[:-5].isdigit()]
    except FileNotFoundError:
        return None
    return max(seqs, default=None)


def connect_store(store: Store):
    """``pipeline.db.connect`` without the analysts' views (the query path needs only the raw tables)."""
    import inspect

    kw = {"views": False} if "views" in inspect.signature(connect).parameters else {}
    return connect(store, **kw)


def _read_ipc(path: Path) -> pa.Table:
    import pyarrow.ipc as ipc

    source = pa.memory_map(str(path), "r")
    return ipc.open_file(source).read_all()


def _write_ipc_atomic(table: pa.Table, path: Path, stale) -> None:
    """Write the cache file via a temp name + rename; a read-only store simply goes uncached."""
    import pyarrow.ipc as ipc

    try:
        path.parent.mkdir(parents=True, exist_ok=True)
        old = [p for p in stale if p != path]
        # not "*.tmp": the store's writer deletes those as orphans
        tmp = path.with_name(f"{path.name}.{os.getpid()}.partial")
        try:
            with pa.OSFile(str(tmp), "wb") as sink, ipc.new_file(sink, table.schema) as writer:
                writer.write_table(table, max_chunksize=65536)
            os.replace(tmp, path)
        finally:
            tmp.unlink(missing_ok=True)
        for p in old:
            p.unlink(missing_ok=True)
    except OSError:
        pass  # read-only or full disk: queries still work, uncached
