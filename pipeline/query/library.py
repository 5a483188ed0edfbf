"""What a query needs from a store, loaded once: the onboarding run's models and fingerprints, the
active meshes, the stage-1 caption table and the stage-2 view table.

The two embedding tables are derived data: they are cached as Arrow IPC segments under
``STORE/_cache/query/`` (memory-mapped on the next open) and brought up to date from the Delta table's
files on each open (:mod:`pipeline.query.cache`): a commit costs the next open only the added files.
"""

from __future__ import annotations

import json
import threading
from dataclasses import dataclass

import numpy as np
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
    features: dict | None = None  # the local-feature config (pipeline.localfeat.FeatureConfig fields)
    render: dict | None = None  # the render config (pipeline.mesh.settings.RenderConfig fields)

    def render_config(self):
        """The run's :class:`~pipeline.mesh.settings.RenderConfig` (``None`` when the run did not record it)."""
        from dataclasses import fields

        from pipeline.mesh.settings import RenderConfig

        if not self.render:
            return None
        known = {f.name for f in fields(RenderConfig)}
        return RenderConfig(
            **{k: (tuple(v) if isinstance(v, list) else v) for k, v in self.render.items() if k in known}
        )


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
        row["run_id"],
        cfg.get("profile") or row["profile"] or "?",
        cfg["models"],
        cfg["fingerprints"],
        cfg.get("features"),
        cfg.get("render"),
    )


def query_profile(onboarding: Onboarding, profile: str | None, model_overrides: dict[str, str] | None = None):
    """The :class:`~pipeline.profiles.Profile` to query with (``"auto"``/``None``: the store's own)."""
    from pipeline.profiles import PROFILES, get_profile

    if profile in (None, "", "auto"):
        profile = onboarding.profile if onboarding.profile in PROFILES else "offline"
    try:
        return get_profile(profile, model_overrides)
    except ValueError as exc:
        raise QueryError(str(exc)) from None


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


def check_learned(onboarding: Onboarding, spec, store_root) -> None:
    """Fail with one line when the store's learned view embeddings come from another encoder or other options
    than the query's ``learned_encoder`` (a store without them, or a query without the role, is fine: the
    query then ranks by the descriptor alone)."""
    stored = onboarding.fingerprints.get("embed_image:learned_encoder")
    if spec is None or not stored:
        return
    from pipeline.onboard.stages import encoder_fingerprint

    render = onboarding.fingerprints.get("render")
    if encoder_fingerprint(None, spec, render) != stored:
        raise QueryError(
            f"store {store_root} was onboarded with learned_encoder "
            f"{onboarding.models.get('learned_encoder')} under other options than the query's {spec.key()} "
            f"{spec.options}: onboard the library again (only the learned view embeddings are recomputed), "
            "query with --model learned_encoder=none, or pass the same --model overrides as at onboarding"
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
        self._db_lock = threading.Lock()  # self.con (candidate_views, view_poses): one statement at a time
        self._row_of: dict[str, int] | None = None
        if self.store.dataset(self.text_dataset) is None:
            raise QueryError(f"store {store.root} has no caption embeddings: re-run onboarding")
        self.captions = self._embeddings("caption", self.text_dataset, fps["embed_text"], slice_layout)
        self.views = self._embeddings("view", self.view_dataset, fps["embed_image:view_encoder"])
        self.learned_views = self._learned_views()
        self.adapter, self.adapter_note = self._adapter()
        if self.captions.num_rows == 0:
            raise QueryError(
                f"store {store.root} has no caption embeddings for its active meshes: re-run onboarding"
            )

    def mesh(self, mesh_id: str) -> dict:
        """The active-mesh record of ``mesh_id`` (name, paths, format, referenced files)."""
        if self._row_of is None:
            self._row_of = {m: j for j, m in enumerate(self.meshes.column("mesh_id").to_pylist())}
        j = self._row_of.get(mesh_id)
        if j is None:
            raise QueryError(f"no active mesh {mesh_id!r} in this store")
        return self.meshes.slice(j, 1).to_pylist()[0]

    def candidate_views(self, mesh_ids: list[str]) -> list[dict]:
        """Rendered views (PNG bytes) and captions of ``mesh_ids`` (``sql/candidate_views.sql``)."""
        fps = self.onboarding.fingerprints
        params = {
            "mesh_ids": list(mesh_ids),
            "render_fingerprint": fps["render"],
            "caption_fingerprint": fps["caption"],
        }
        with self._db_lock:
            rel = self.con.sql(load_sql("candidate_views"), params=params)
            return rel.to_arrow_table().to_pylist()

    def view_images(self, mesh_id: str, view_indices: list[int]) -> dict[int, bytes]:
        """The PNG bytes of some rendered views of one model, by view index (``sql/view_images.sql``;
        views it has no image of are left out)."""
        params = {
            "mesh_id": str(mesh_id),
            "view_indices": [int(v) for v in view_indices],
            "render_fingerprint": self.onboarding.fingerprints["render"],
        }
        with self._db_lock:
            rows = self.con.sql(load_sql("view_images"), params=params).fetchall()
        return {int(v): bytes(png) for v, png in rows if png is not None}

    def view_patches(self, mesh_id: str, view_indices: list[int]) -> dict[int, np.ndarray]:
        """The learned encoder's object patch tokens of some views of one model, as onboarding stored them
        (``sql/view_patches.sql``; float16 rows), by view index; views without stored tokens are left out,
        and every view is when the store's run had no ``patches`` stage (the caller then encodes them)."""
        from pipeline.query.patches import tokens_of

        fp = self.onboarding.fingerprints.get("patches")
        if not fp:  # (a store without the table: the connection's view_patches_all is empty)
            return {}
        params = {"mesh_id": str(mesh_id), "view_indices": [int(v) for v in view_indices], "patches_fingerprint": fp}
        with self._db_lock:
            rows = self.con.sql(load_sql("view_patches"), params=params).fetchall()
        return {int(v): tokens_of(t, n, d) for v, n, d, t in rows if t is not None and n}

    def view_poses(self, mesh_ids: list[str]) -> list[dict]:
        """Cameras (pose, field of view, size; no pixels) of the rendered views of ``mesh_ids``
        (``sql/view_poses.sql``; the pose-estimator hand-off, :mod:`pipeline.query.handoff`)."""
        fp = self.onboarding.fingerprints.get("render")
        params = {"mesh_ids": list(mesh_ids), "render_fingerprint": fp}
        with self._db_lock:
            return self.con.sql(load_sql("view_poses"), params=params).to_arrow_table().to_pylist()

    @property
    def versions(self) -> dict[str, int]:
        """The table versions this state reads (one consistent snapshot, :mod:`pipeline.snapshot`). Derived
        data of the query path (the embedding cache; a stage-1 vector index) is built from this pinned
        store (``store.parts(dataset)``) and keyed on these versions, so a reload moves it with the rest."""
        return self.store.versions()
    def _learned_views(self) -> pa.Table | None:
        """The learned encoder's view table (``None`` when the store was onboarded without one)."""
        key = self.onboarding.models.get("learned_encoder")
        fp = self.onboarding.fingerprints.get("embed_image:learned_encoder")
        if not key or not fp:
            return None
        dataset = f"image_embeddings/{slug(key)}"
        if self.store.dataset(dataset) is None:
            return None
        table = self._embeddings("learned", dataset, fp, sql="view")
        return table if table.num_rows else None

    def _adapter(self):
        """The store's query adapter fitted on exactly the learned views this state reads, and a note when
        the store has one that does not match (``(None, None)`` without probes)."""
        from pipeline.adapter.table import for_query

        fps = self.onboarding.fingerprints
        key, probe_fp = self.onboarding.models.get("learned_encoder"), fps.get("probe")
        if self.learned_views is None or not key or not probe_fp:
            return None, None
        ids = self.meshes.column("mesh_id").to_pylist()
        present = np.unique(self.learned_views.column("mesh_idx").to_numpy())
        try:
            adapter = for_query(self.store, key, fps["embed_image:learned_encoder"], probe_fp, [ids[i] for i in present])
        except ValueError as exc:
            return None, f"the store's query adapter is not used: {exc}"
        if adapter is None and self.store.dataset("adapters") is not None:
            return None, (
                "the store's query adapter was fitted on other models than it now holds (an onboarding run "
                "did not finish): ranked without it until a run finishes"
            )
        return adapter, None

    # ------------------------------------------------------------------ embeddings (cached)
    def _embeddings(self, kind: str, dataset: str, fp: str, layout=None, sql: str | None = None) -> pa.Table:
        """The rows of ``dataset`` a query uses (``query_<sql or kind>_embeddings.sql``), in ``layout``; from
        the incremental cache (:mod:`pipeline.query.cache`) for tables of at least ``CACHE_MIN_ROWS`` rows."""
        sql = sql or kind
        dt = self.store.delta(dataset)
        n_rows = 0
        if dt is not None:
            add = dt.get_add_actions(flatten=True)
            n_rows = sum(x or 0 for x in add.column("num_records").to_pylist())
        if self.use_cache and n_rows >= CACHE_MIN_ROWS:
            try:
                return self._cached(kind, dataset, fp, layout, sql)
            except OSError:
                pass  # read-only or full disk: queries still work, uncached
        d = self.store.dataset(dataset)
        if d is None:
            return pa.table({"mesh_idx": pa.array([], pa.int32()), "view_index": pa.array([], pa.int16())})
        self.con.register(f"query_{sql}_source", d)
        table = self.con.sql(load_sql(f"query_{sql}_embeddings"), params={"fingerprint": fp}).to_arrow_table()
        self.con.unregister(f"query_{sql}_source")
        return layout(table) if layout is not None else table.combine_chunks()

    def _cached(self, kind: str, dataset: str, fp: str, layout, sql: str) -> pa.Table:
        from pipeline.query.cache import SegmentCache

        key = fingerprint(
            {
                "kind": kind,
                "dataset": dataset,
                "fp": fp,
                "sql": load_sql(f"query_{sql}_embeddings") + load_sql("query_active_meshes"),
                "layout": (getattr(layout, "__name__", None), SLICES),
                "format": 2,
            }
        )
        directory = self.store.root.joinpath(*CACHE_DIR) / f"{kind}-{key}"
        self.store.check_files(dataset)
        files = [(p.name, p) for p in self.store.parts(dataset)]

        def vector_columns(seg: pa.Table) -> list[str]:
            return [c for c in seg.column_names if c == "embedding" or (c[0] == "e" and c[1:].isdigit())]

        cache = SegmentCache(directory, vector_columns, layout)
        table = cache.load(
            files, self.store.schema(dataset), fp, self.meshes.column("mesh_id").combine_chunks()
        )
        self.cache_stats = getattr(self, "cache_stats", {})
        self.cache_stats[kind] = cache.stats
        return table


def store_version(root) -> object:
    """An opaque token that changes with every commit to the store at ``root``; cheap enough to poll.

    The query service compares tokens to decide when to reopen (:func:`pipeline.store.store_version`:
    the newest Delta commit of each table). ``None`` when the store has no commit.
    """
    from pipeline.store import store_version as delta_store_version

    return delta_store_version(root)


def connect_store(store: Store):
    """``pipeline.db.connect`` without the analysts' views (the query path needs only the raw tables)."""
    import inspect

    kw = {"views": False} if "views" in inspect.signature(connect).parameters else {}
    return connect(store, **kw)
