"""Patch agreement: does the ROI look like the top-1 model part by part, not only as a whole?

The open-set verdict's scores are whole-image cosines, and an absent object's best match is often a
look-alike that scores as high as a right answer (a box of another brand, a can of another soup). The
learned encoder's patch tokens tell more: for each patch of the ROI's object, how close the nearest patch
of the top-1's best view is. A right model has a counterpart for most parts of the object; a look-alike has
some and lacks others. Four features (:data:`PATCH_FEATURES`, offered to the calibration's selection),
each the best over the top-1's :data:`VIEWS` views that the plain learned cosine ranks first:

* ``patch_cover``: the mean over the ROI's object patches of the best cosine to a patch of the view;
* ``patch_sim``: its symmetric form, the mean of ``patch_cover`` and the same from the view's side;
* ``patch_mnn``: the share of the ROI's object patches that are mutual nearest neighbours with a patch of
  the view (each the other's closest): a one-to-one correspondence, which a look-alike's few shared parts
  cannot give to every patch;
* ``patch_low``: the lower quartile of the ROI patches' best cosines, the parts the view matches worst
  (a look-alike lacks some parts, which the mean dilutes).

Two more (:data:`LEAD_FEATURES`) compare the top-1 with the runner-up, the next model in the ranking:
``patch_second`` is the runner-up's ``patch_sim`` (its own best views), ``patch_lead`` how far the top-1's
``patch_sim`` is ahead of it. A right model usually matches part by part clearly better than the next one,
while an absent object's look-alikes match about as well as each other; and a lead cancels what a photo's
lighting and camera take off every model's patch cosines alike. They cost the runner-up's views one more
encoder pass, so they are computed only when the calibration reads them (or ``always``).

The views' tokens are read from the store's ``view_patches`` table, which onboarding fills from the
forward pass that embeds the views (:mod:`pipeline.onboard.stages.patches`; about 1 MB per model, the
object's patches only, float16). For views without stored tokens (a store onboarded before that stage) they
are computed from the stored view image, one encoder pass, the largest part of a warm masked query on 2 cores
(docs/performance.md, "Stored patch tokens"). Either way they are kept in a bounded cache per view.
Measured in docs/results.md, section 12.
"""

from __future__ import annotations

import io
import threading
from collections import OrderedDict
from collections.abc import Callable

import numpy as np
from PIL import Image

#: the features this module adds to an answer (:data:`pipeline.query.accept.FEATURES` lists them)
PATCH_FEATURES = ("patch_cover", "patch_sim", "patch_mnn", "patch_low")
#: the features comparing the top-1's patch agreement with the runner-up's (:func:`runner_up_lead`)
LEAD_FEATURES = ("patch_second", "patch_lead")
#: the features of the ROI against every view of the top-1 at once (:func:`union_agreement`)
UNION_FEATURES = ("patch_union", "patch_gain")
#: more views than any camera layout has: :data:`UNION_FEATURES` read every view of the top-1
ALL_VIEWS = 1024
#: the quantile of the ROI patches' best cosines that ``patch_low`` reads
LOW_QUANTILE = 0.25
#: a pixel is the object's when a channel differs from the background by more than this (as the encoders)
TOLERANCE = 12
#: a patch is the object's when this share of its pixels is
MIN_COVER = 0.3
#: with fewer object patches than this, every patch is used (a tiny or blank ROI)
MIN_PATCHES = 4
#: the top-1's views compared (those the learned cosine ranks first; one encoder batch): with 2 instead of 1
#: the patch features separate absent objects' answers better (docs/results.md, section 12)
VIEWS = 2
#: views whose patch tokens are kept (LRU)
CACHE_VIEWS = 512


def tokens_bytes(tokens: np.ndarray) -> bytes:
    """``tokens`` (rows) as the ``tokens`` column stores them: float16, little-endian, row-major."""
    return np.ascontiguousarray(tokens, dtype="<f2").tobytes()


def tokens_of(data: bytes | None, n: int, dim: int) -> np.ndarray | None:
    """The ``(n, dim)`` float16 tokens of a ``tokens`` value (``None`` for none)."""
    if data is None:
        return None
    return np.frombuffer(data, dtype="<f2", count=int(n) * int(dim)).reshape(int(n), int(dim))


def object_cells(image: Image.Image, fill: tuple[int, int, int], grid: int) -> np.ndarray:
    """Which cells of a ``grid`` x ``grid`` split of the square ``image`` hold the object (bool, row-major):
    at least :data:`MIN_COVER` of their pixels off the background ``fill``; all cells when fewer than
    :data:`MIN_PATCHES` do."""
    a = np.asarray(image.convert("RGB"), np.int16)
    side = (min(a.shape[0], a.shape[1]) // grid) * grid
    if side < grid:
        return np.ones(grid * grid, bool)
    off = np.abs(a[:side, :side] - np.asarray(fill, np.int16)).max(axis=2) > TOLERANCE
    step = side // grid
    cover = off.reshape(grid, step, grid, step).mean(axis=(1, 3)).reshape(-1)
    cells = cover >= MIN_COVER
    return cells if cells.sum() >= MIN_PATCHES else np.ones(grid * grid, bool)


def top_views(view_ids: np.ndarray, view_scores: np.ndarray, k: int) -> list[int]:
    """The ``k`` view indices of one model with the highest finite scores, best first (ids < 0: none)."""
    ids, sc = np.asarray(view_ids), np.asarray(view_scores, np.float64)
    ok = (ids >= 0) & np.isfinite(sc)
    ids, sc = ids[ok], sc[ok]
    return [int(ids[i]) for i in np.argsort(-sc, kind="stable")[: max(int(k), 0)]]


def best_views(learned, query: np.ndarray, mesh: int, k: int = VIEWS) -> list[int]:
    """The ``k`` views of model ``mesh`` (its store position) that the plain learned cosine of ``query``
    ranks first, best first (``learned``: the ranking's learned-encoder scorer): those the patch agreement
    reads."""
    s = learned.score(query, np.array([int(mesh)]), per_view=True)
    return top_views(s.view_ids[0], s.view_scores[0], k)


def runner_up_lead(top: dict[str, float | None], second: dict[str, float | None]) -> dict[str, float | None]:
    """:data:`LEAD_FEATURES` from the top-1's and the runner-up's :data:`PATCH_FEATURES`: the runner-up's
    ``patch_sim`` and the top-1's lead over it (``None`` where either is missing)."""
    a, b = top.get("patch_sim"), second.get("patch_sim")
    return {"patch_second": b, "patch_lead": None if a is None or b is None else float(a - b)}


def union_agreement(roi: np.ndarray | None, views: list[np.ndarray | None], cover: float | None) -> dict[str, float | None]:
    """:data:`UNION_FEATURES`: ``patch_union``, the mean over the ROI's object patches of the best cosine to a
    patch of any of ``views`` (a model's every view); ``patch_gain``, how much that exceeds ``cover`` (the
    ``patch_cover`` of its best views). A right model explains the ROI from one pose; a look-alike's parts
    match from several, so allowing every view gains it more. ``None`` where there is nothing to compare."""
    kept = [np.asarray(v, np.float32) for v in views if v is not None and len(v)]
    if roi is None or not len(roi) or not kept:
        return dict.fromkeys(UNION_FEATURES)
    union = float((np.asarray(roi, np.float32) @ np.concatenate(kept).T).max(axis=1).mean())
    return {"patch_union": union, "patch_gain": None if cover is None else union - float(cover)}


def patch_agreement(roi: np.ndarray | None, view: np.ndarray | None) -> dict[str, float | None]:
    """:data:`PATCH_FEATURES` of the ROI's and the view's object patch tokens (rows, L2-normalised);
    ``None`` for both when either side has none."""
    if roi is None or view is None or not len(roi) or not len(view):
        return dict.fromkeys(PATCH_FEATURES)
    s = np.asarray(roi, np.float32) @ np.asarray(view, np.float32).T
    rows, cols = np.arange(s.shape[0]), np.arange(s.shape[1])
    nearest, nearest_back = s.argmax(axis=1), s.argmax(axis=0)  # each side's closest patch, found once
    best = s[rows, nearest]
    cover = float(best.mean())
    back = float(s[nearest_back, cols].mean())
    mutual = nearest_back[nearest] == rows
    return {
        "patch_cover": cover,
        "patch_sim": 0.5 * (cover + back),
        "patch_mnn": float(mutual.mean()),
        "patch_low": float(np.quantile(best, LOW_QUANTILE)),
    }


class PatchMatcher:
    """The top-1 views' object patch tokens on demand: ``stored(mesh_id, view_indices)`` gives the tokens
    onboarding stored by view index (one store read; views without them left out), and for the others
    ``view_images(mesh_id, view_indices)`` the stored PNG bytes (views without an image left out), which
    ``encoder()``, the learned view encoder (loaded on first use), encodes in one batch. Tokens are cached
    per view (thread-safe; the store reads and the encoder run outside the lock). The verdict computes the
    features only when its calibration reads them, or always when ``always`` is set (the open-set
    evaluation, which records every feature an answer offers for the fits)."""

    def __init__(
        self,
        view_images: Callable[[str, list[int]], dict[int, bytes]],
        encoder: Callable[[], object],
        cache_views: int = CACHE_VIEWS,
        stored: Callable[[str, list[int]], dict[int, np.ndarray]] | None = None,
    ) -> None:
        self._view_images, self._encoder, self._stored = view_images, encoder, stored
        self._cache: OrderedDict[tuple[str, int], np.ndarray | None] = OrderedDict()
        self._size = max(int(cache_views), 1)
        self._lock = threading.Lock()
        self.always = False

    def wanted(self, model) -> bool:
        """Whether a verdict by ``model`` (an :class:`pipeline.query.accept.AcceptModel` or ``None``) needs
        the patch features."""
        return self.always or bool(
            model is not None and set(PATCH_FEATURES + LEAD_FEATURES + UNION_FEATURES) & set(model.features)
        )

    def wanted_union(self, model) -> bool:
        """Whether a verdict by ``model`` also needs the ROI against every view of the top-1 (:data:`UNION_FEATURES`)."""
        return self.always or bool(model is not None and set(UNION_FEATURES) & set(model.features))

    def views_read(self, model) -> int:
        """How many of the top-1's views, best first, a verdict by ``model`` reads: all of them for
        :data:`UNION_FEATURES`, else :data:`VIEWS`."""
        return ALL_VIEWS if self.wanted_union(model) else VIEWS

    def wanted_runner_up(self, model) -> bool:
        """Whether a verdict by ``model`` also needs the runner-up's patch agreement (:data:`LEAD_FEATURES`)."""
        return self.always or bool(model is not None and set(LEAD_FEATURES) & set(model.features))

    def clear(self) -> None:
        """Forget every cached view (benchmarks of the uncached cost)."""
        with self._lock:
            self._cache.clear()

    def view_tokens(self, mesh_id: str, views: list[int]) -> list[np.ndarray | None]:
        """The object patch tokens of ``views`` of ``mesh_id`` (``None`` for a view without an image);
        the uncached ones are read from the store, and those it has none of encoded in one batch."""
        keys = [(str(mesh_id), int(v)) for v in views]
        with self._lock:
            have = {k: self._cache[k] for k in keys if k in self._cache}
            for k in have:
                self._cache.move_to_end(k)
        todo = [k for k in dict.fromkeys(keys) if k not in have]
        if todo and self._stored is not None:  # one model per call
            found = self._stored(todo[0][0], [v for _, v in todo])
            got = {k: found[k[1]] for k in todo if k[1] in found}
            have.update(self._keep(got))
            todo = [k for k in todo if k not in got]
        if todo:
            got_png = self._view_images(todo[0][0], [v for _, v in todo])  # one model per call
            images = {}
            for k in todo:
                png = got_png.get(k[1])
                if png is not None:
                    with Image.open(io.BytesIO(png)) as im:
                        images[k] = im.convert("RGB")
            got = dict.fromkeys(todo)
            if images:
                got.update(zip(images, self._encoder().object_patches_batch(list(images.values())), strict=True))
            have.update(self._keep(got))
        return [have[k] for k in keys]

    def _keep(self, got: dict[tuple[str, int], np.ndarray | None]) -> dict[tuple[str, int], np.ndarray | None]:
        """Cache ``got`` (view key -> tokens), dropping the least recently used views beyond the bound."""
        with self._lock:
            for k, t in got.items():
                self._cache[k] = t
            while len(self._cache) > self._size:
                self._cache.popitem(last=False)
        return got

    def features(self, roi: np.ndarray | None, mesh_id: str, views: list[int]) -> dict[str, float | None]:
        """:data:`PATCH_FEATURES` of the ROI's patch tokens against the best of ``views`` of ``mesh_id``
        (each feature its own best view)."""
        views = [int(v) for v in views if v is not None and v >= 0]
        if roi is None or not views:
            return dict.fromkeys(PATCH_FEATURES)
        each = [patch_agreement(roi, t) for t in self.view_tokens(mesh_id, views)]
        out: dict[str, float | None] = {}
        for f in PATCH_FEATURES:
            vals = [e[f] for e in each if e[f] is not None]
            out[f] = max(vals) if vals else None
        return out
