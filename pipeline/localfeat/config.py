"""Configuration of the local-feature detector (onboarding) and of the verification (query time)."""

from __future__ import annotations

import hashlib
import json
from dataclasses import asdict, dataclass

#: Bump when detection code changes in a way that changes keypoints or descriptors.
FEATURES_VERSION = "lf-1"
#: "sift": OpenCV SIFT, 128 uint8 per keypoint, matched as RootSIFT; "orb": 32-byte binary, Hamming;
#: "none": no view_features stage (verification is then unavailable)
DETECTORS = ("sift", "orb", "none")


@dataclass(frozen=True)
class FeatureConfig:
    """What the ``features`` stage stores per view (its fingerprint keys the ``view_features`` rows)."""

    detector: str = "sift"
    max_keypoints: int = 256  # strongest keypoints kept per view (response order)
    work_side: int = 384  # the object's box is resized so its longer side has this many pixels

    def __post_init__(self) -> None:
        if self.detector not in DETECTORS:
            raise ValueError(
                f"unknown local-feature detector {self.detector!r}; choose from {', '.join(DETECTORS)}"
            )
        if not 16 <= int(self.max_keypoints) <= 4096:
            raise ValueError(f"max_keypoints must be within 16..4096, got {self.max_keypoints}")
        if not 64 <= int(self.work_side) <= 2048:
            raise ValueError(f"work_side must be within 64..2048, got {self.work_side}")

    @property
    def enabled(self) -> bool:
        return self.detector != "none"

    def fingerprint(self, render_fingerprint: str) -> str:
        blob = json.dumps({"v": FEATURES_VERSION, **asdict(self), "in": render_fingerprint}, sort_keys=True)
        return hashlib.sha256(blob.encode()).hexdigest()[:16]

    def detector_id(self) -> str:
        return f"opencv:{self.detector}-{self.max_keypoints}@{self.work_side}"


@dataclass(frozen=True)
class VerifyConfig:
    """Query-time verification of the top candidates against their views' local features."""

    enabled: bool = True
    top: int = 20  # candidates (by global score) that are verified
    ratio: float = 0.8  # Lowe's ratio test
    min_matches: int = 8  # fewer ratio-test matches: the view scores 0 inliers (RANSAC is skipped)
    method: str = "homography"  # "homography" (OpenCV USAC_FAST) | "affine" | "fundamental" (RANSAC)
    reproj_px: float = 0.02  # RANSAC threshold, as a fraction of the work side
    min_spread: float = 0.04  # inliers must spread at least this fraction of the work side (per axis std)
    roi_keypoints: int = 384  # keypoints detected on the ROI
    view_keypoints: int = 192  # strongest stored keypoints used per view (at most the stored count)
    inlier_floor: int = 4  # inliers at or below this add nothing (chance agreement)
    inlier_cap: int = 20  # inliers at or above this add the full weight
    weight: float = 0.3  # fused = global score + weight * clip((inliers - floor) / (cap - floor), 0, 1)

    def bonus(self, inliers, weight: float | None = None):
        """The fused score's local-feature term for an inlier count (scalar or array); ``weight`` replaces
        :attr:`weight` (the fusion with the learned encoder has its own)."""
        import numpy as np

        span = max(self.inlier_cap - self.inlier_floor, 1)
        w = self.weight if weight is None else float(weight)
        return w * np.clip((np.asarray(inliers, dtype=np.float32) - self.inlier_floor) / span, 0, 1)
