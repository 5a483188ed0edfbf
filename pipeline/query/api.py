"""The Python API of the query path; the CLI, batch mode, the service and the evaluation wrap it.

>>> from pipeline.query import Retriever
>>> with Retriever.open("data/store", profile="offline") as r:
...     result = r.query("photo.jpg", "the yellow mustard bottle", box=(120, 40, 260, 300))
...     print(result.best.name)

``make_roi`` -> ``embed`` -> ``rank`` are the three parts of ``query``. ``rank`` runs the mode's step list
(:mod:`pipeline.query.steps`) and calls no model, so sweeps over tau, fallback-k, prompt weight or mode
reuse one embedding. A ``Retriever`` only opens the store and the models and hands them to the steps.

A ``Retriever`` is thread-safe: stage 1 borrows a DuckDB connection per call, models are built once under a
lock, and the adapters and stage 2 only read shared state. It answers from the store state it opened;
:meth:`Retriever.reopened` gives one on the latest commits that shares the loaded models (what the HTTP
service does when :func:`pipeline.query.library.store_version` changes). The state is one consistent
snapshot of every table (:mod:`pipeline.snapshot`), leased in the store while open (:mod:`pipeline.leases`)
so that ``compact`` spares its files; a query that still meets a vanished file reloads the newest snapshot
in place and retries once (:mod:`pipeline.query.recover`; ``retriever.recover = False`` turns that off).
"""

from __future__ import annotations

from pipeline.query.context import ranking_context
from pipeline.query.embed import embed_roi, strategy_for
from pipeline.query.images import clean_prompt
from pipeline.query.inputs import check_knobs, roi_from_inputs
from pipeline.query.library import StoreTables, store_version
from pipeline.query.models import QueryModels, roles_for
from pipeline.query.opening import open_state
from pipeline.query.overlap import beside
from pipeline.query.patches import PatchMatcher
from pipeline.query.recover import Gate, recovering, vanished_file
from pipeline.query.results import QueryEmbedding, QueryResult
from pipeline.query.roi import Roi
from pipeline.query.settings import QuerySettings
from pipeline.query.steps import rank
from pipeline.query.timing import PartClock


class Retriever:
    """An opened store plus the profile's query models, loaded once. Use :meth:`open`."""

    def __init__(
        self, store, profile, tables: StoreTables, settings: QuerySettings, *, device, models, threads
    ):
        self.store, self.profile, self.tables = store, profile, tables
        self.settings, self.device = settings, device
        self.strategy = strategy_for(profile.clip_image_encoder is not None)
        self.models = QueryModels(profile, device, models)
        self.model, self.load_seconds = self.models.get, self.models.load_seconds
        self.version = None  # store version this state was read at (set by open)
        self.versions: dict[str, int] = store.versions()  # the snapshot read (pinned at open)
        self.lease = None  # this reader's lease in the store (set by open)
        self.recover = True  # reload and retry once when a query meets a vanished file
        self.generation = 0  # bumped by each reload in place
        self._gate = Gate()
        self.open_args: dict = {}  # what open() was called with (reopened() repeats it)
        self.mesh = tables.mesh
        # the engines the steps call (pipeline.query.context): stage 1, stage 2, learned, verify, hand-off
        self.ranking = ranking_context(store, profile, tables, settings, device=device, threads=threads)
        c = self.ranking  # its engines, also as attributes of the Retriever (tests, benchmarks, evaluation)
        self.text_filter, self.reranker, self.learned = c.text_filter, c.reranker, c.learned
        self.verifier, self.handoff = c.verifier, c.handoff
        if c.learned is not None:  # the verdict's patch agreement encodes the top-1's view when asked
            c.patches = PatchMatcher(
                tables.view_images, lambda: self.model("learned_encoder"), stored=tables.view_patches
            )

    @classmethod
    def open(
        cls,
        store_path,
        profile: str = "offline",
        model_overrides: dict[str, str] | None = None,
        device: str | None = None,
        models: dict[str, object] | None = None,
        *,
        settings: QuerySettings | None = None,
        use_cache: bool = True,
        threads: int | None = None,
        settings_changes: dict | None = None,
        preload: bool = True,
        lease: bool = True,
    ) -> Retriever:
        """Open ``store_path`` for queries with ``profile`` ("auto": the profile the store was onboarded with).

        ``models`` injects ready adapters by role (tests, notebooks); other roles are built through
        :func:`pipeline.models.registry.create_model` from the profile (detector and segmenter on first use).
        ``settings`` / ``settings_changes`` replace / adjust the profile's query defaults
        (:mod:`pipeline.query.settings`); ``use_cache`` reads and writes ``STORE/_cache/query``;
        ``preload=False`` defers every model to its first use; ``lease=False`` opens without a reader
        lease (compaction then spares this reader's files only through its retention period).
        """
        args = {k: v for k, v in locals().items() if k != "cls"}
        try:
            return cls._open(**args)
        except Exception as exc:
            if not vanished_file(exc, store_path):
                raise
        return cls._open(**args)  # compaction removed files while opening: once more, on its result

    @classmethod
    def _open(cls, store_path, profile, model_overrides, device, models, *, preload, threads, **opts):
        o = open_state(store_path, profile, model_overrides, **opts)
        try:
            r = cls(o.store, o.profile, o.tables, o.settings, device=device, models=models, threads=threads)
        except BaseException:
            o.store.close()
            if o.lease is not None:
                o.lease.release()
            raise
        r.version, r.lease = o.version, o.lease
        r.open_args = {"store_path": store_path, "profile": o.profile.name, "model_overrides": model_overrides}
        r.open_args |= {"device": device, "threads": threads, "settings": o.settings}
        r.open_args |= {"use_cache": opts["use_cache"], "lease": opts["lease"]}  # settings_changes: in settings
        if preload:
            r.load_models(r.required_roles())
        return r

    def __enter__(self) -> Retriever:
        return self

    def __exit__(self, *exc) -> None:
        self.close()

    def reopened(self, *, preload: bool = True) -> Retriever:
        """A new Retriever on the store's latest commits, with the same settings and the already loaded
        models (no model is loaded twice). This one stays usable until closed."""
        r = Retriever.open(**self.open_args, models=self.models.snapshot(), preload=False)
        r.load_seconds.update(self.load_seconds)
        if preload:
            r.load_models(r.required_roles())
        return r

    def is_stale(self) -> bool:
        """Whether the store has commits this Retriever does not see (cheap: for polling)."""
        return store_version(self.store.root) != self.version

    def close(self) -> None:
        self.text_filter.close()
        self.tables.con.close()
        self.store.close()
        if self.lease is not None:
            self.lease.release()

    def required_roles(self, source: str | None = None, roi_mode: str = "segm") -> list[str]:
        """Roles a query needs (:func:`pipeline.query.models.roles_for`) that this profile has, with the
        learned view encoder where the store has its embeddings."""
        roles = list(self.strategy.roles(self.settings.prompt_weight > 0))
        roles += ["learned_encoder"] if self.learned is not None else []
        return self.models.available(roles_for(roles, source, roi_mode))

    def load_models(self, roles) -> None:
        """Build the adapters of ``roles`` now (not yet loaded ones only)."""
        self.models.load(roles)

    def make_roi(self, image, prompt: str, box=None, mask=None, roi_mode: str = "segm") -> Roi:
        """Validate the inputs and cut the prompted object out of ``image`` (path, PIL image or array)."""
        return roi_from_inputs(self.settings, self.model, self.profile.name, image, prompt, box, mask, roi_mode)

    def embed(self, roi: Roi, prompt: str) -> QueryEmbedding:
        """The ROI's vectors in the caption space and the view-encoder space (plus the prompt's if used)."""
        prompt = clean_prompt(prompt, self.settings.max_prompt_chars)
        learned = None
        if self.learned is not None:  # loaded here, run beside the rest (pipeline/query/overlap.py)
            enc = self.model("learned_encoder")  # an adapter without ROI framing embeds the ROI as a view
            if hasattr(enc, "encode_roi_patches"):  # the vector and the object's patch tokens, one pass
                learned = beside(lambda: enc.encode_roi_patches(roi.image))
            else:
                learned = beside(lambda: (getattr(enc, "encode_roi", enc.encode_image)([roi.image])[0], None))
        try:
            emb = embed_roi(self.strategy, self.model, roi, prompt, self.settings.prompt_weight > 0)
            if self.settings.verify and self.verifier.available:
                emb.local = self.verifier.roi_features(roi.image, roi.crop_mask)
        except BaseException:
            if learned is not None:
                learned.exception()  # the side call ends with this query; the first error is the one raised
            raise
        if learned is not None:
            emb.learned, emb.learned_patches = learned.result()
        return emb

    @recovering
    def rank(self, emb: QueryEmbedding, mode: str | None = None, **knobs) -> QueryResult:
        """Rank the store's models for ``emb`` with the mode's step list (no model calls). ``knobs``:
        ``threshold``, ``fallback_k``, ``top``, ``prompt_weight``, ``fallback_unit``, ``views``, ``verify``
        (:meth:`pipeline.query.steps.state.RankRequest.make`; ``None`` = the settings' value).
        Verification reads stored features as it goes, so a rank can meet a file that compaction
        removed: it then reloads and retries once, as :meth:`query` does."""
        return rank(self.ranking, emb, mode=mode, **knobs)

    @recovering
    def query(self, image, prompt: str, box=None, mask=None, roi_mode: str = "segm", **knobs) -> QueryResult:
        """ROI, embedding and ranking (``knobs`` as :meth:`rank`'s) of one photo + prompt, with a per-part
        latency breakdown (model loading counted apart)."""
        check_knobs(knobs)
        clock = PartClock(self.load_seconds)
        roi = clock.part("roi_ms", self.make_roi, image, prompt, box=box, mask=mask, roi_mode=roi_mode)
        emb = clock.part("embed_ms", self.embed, roi, prompt)
        result = rank(self.ranking, emb, **knobs)  # not self.rank: this call already holds the gate
        result.timings = clock.timings(result.timings)
        prompt = clean_prompt(prompt, self.settings.max_prompt_chars)
        result.query = {"image": roi.photo_source, "image_size": list(roi.photo_size), "prompt": prompt}
        result.query |= {"profile": self.profile.name, "roi": roi.describe(), "embedding": emb.describe()}
        result.roi = roi  # for --explain; not serialised
        return result

    @recovering
    def candidate_views(self, mesh_ids: list[str]) -> list[dict]:
        """Rendered views (PNG bytes) and captions of ``mesh_ids`` (``sql/candidate_views.sql``)."""
        return self.tables.candidate_views(mesh_ids)

    @recovering
    def view_poses(self, mesh_ids: list[str]) -> list[dict]:
        """Cameras (pose, field of view, size; no pixels) of the rendered views of ``mesh_ids``
        (``sql/view_poses.sql``)."""
        return self.tables.view_poses(mesh_ids)

    @property
    def n_meshes(self) -> int:
        return self.ranking.n_meshes

    @property
    def mesh_ids(self) -> list[str]:
        """Active mesh ids in ``mesh_idx`` order (what a :class:`ViewRanking`'s ``mesh_idx`` indexes)."""
        return self.ranking.mesh_id
