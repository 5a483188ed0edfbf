"""Geometric verification of the top stage-2 candidates with local features (offline profile default).

The ROI's keypoints (detected in :meth:`LocalVerifier.roi_features`, once per query) are matched against
the stored ``view_features`` of the top ``verify_top`` candidates by global score: Lowe's ratio test, then
RANSAC (homography by default). A candidate's inlier count is the max over its views, and its fused score is

    fused = image_score + weight * clip((inliers - floor) / (cap - floor), 0, 1)

so a model whose views share a geometrically consistent set of keypoints with the ROI (printed labels,
logos, texture) moves up, and one without keeps its global score. Inlier counts are cached on the query
embedding, so re-rankings (evaluation sweeps) verify each (query, model) pair once.
"""

from __future__ import annotations

import time

import numpy as np
import pyarrow.compute as pc

from pipeline.localfeat import FeatureConfig, Features, detect, from_row
from pipeline.localfeat.config import VerifyConfig
from pipeline.localfeat.match import ViewBank, count_inliers

#: libraries with at most this many feature rows are loaded whole on first use; larger ones per candidate
PRELOAD_MAX_VIEWS = 5000


class LocalVerifier:
    """The store's view features (loaded lazily, cached) and the verification settings."""

    def __init__(self, store, onboarding, mesh_ids: list[str], cfg: VerifyConfig) -> None:
        self.store = store
        self.cfg = cfg
        self.mesh_ids = mesh_ids
        stored = getattr(onboarding, "features", None) or {}
        self.fingerprint = onboarding.fingerprints.get("features")
        self.features = FeatureConfig(**stored) if stored and self.fingerprint else None
        self._views: dict[int, tuple[ViewBank, list[int]]] = {}  # mesh_idx -> its views' bank, view_index
        self._all_loaded = False

    @property
    def available(self) -> bool:
        """True when the store has local features (onboarded with ``--local-features`` sift or orb)."""
        return self.features is not None and self.store.dataset("view_features") is not None

    def roi_features(self, image, mask: np.ndarray | None) -> Features:
        """Keypoints of the ROI (object on gray; ``mask`` marks its pixels)."""
        return detect(image, self.features, mask=mask, max_keypoints=self.cfg.roi_keypoints)

    def _load(self, mesh_idx: list[int]) -> None:
        missing = [j for j in mesh_idx if j not in self._views]
        if not missing or self._all_loaded:
            return
        flt = pc.field("fingerprint") == self.fingerprint
        if not self._views:  # first load: a small table is read whole, once
            n = self.store.read("view_features", columns=["mesh_id"], filter=flt).num_rows
            if n <= PRELOAD_MAX_VIEWS:
                missing = list(range(len(self.mesh_ids)))
                self._all_loaded = True
        if not self._all_loaded:
            flt = flt & pc.field("mesh_id").isin([self.mesh_ids[j] for j in missing])
        cols = ["mesh_id", "view_index", "n_keypoints", "keypoints", "descriptor_dim", "descriptors"]
        t = self.store.read_latest("view_features", columns=cols, filter=flt)
        index = {m: j for j, m in enumerate(self.mesh_ids)}
        found: dict[int, tuple[list[Features], list[int]]] = {j: ([], []) for j in missing}
        for r in t.to_pylist():
            j = index.get(r["mesh_id"])
            if j is None:
                continue
            f = from_row(r["n_keypoints"], r["keypoints"], r["descriptor_dim"], r["descriptors"])
            found.setdefault(j, ([], []))[0].append(f)
            found[j][1].append(int(r["view_index"]))
        for j, (fs, vs) in found.items():
            self._views[j] = (ViewBank.build(fs, self.features.detector, self.cfg.view_keypoints), vs)

    def inliers(self, roi: Features, mesh_idx: list[int], cache: dict) -> tuple[dict, float]:
        """``{mesh_idx: (inliers, best view_index)}`` for ``mesh_idx`` (``cache`` is reused and filled)."""
        t0 = time.perf_counter()
        todo = [int(j) for j in mesh_idx if int(j) not in cache]
        if todo:
            self._load(todo)
            banks, owner, vidx = [], [], []
            for j in todo:
                cache[j] = (0, None)
                if j in self._views and self._views[j][1]:
                    bank, vs = self._views[j]
                    banks.append(bank)
                    owner += [j] * len(vs)
                    vidx += vs
            if banks:
                counts = count_inliers(roi, ViewBank.concat(banks), self.cfg, self.features)
                for c, j, v in zip(counts, owner, vidx, strict=True):
                    if c > cache[j][0]:
                        cache[j] = (int(c), v)
        return cache, time.perf_counter() - t0
