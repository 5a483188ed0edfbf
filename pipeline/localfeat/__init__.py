"""Weight-free local features (OpenCV SIFT or ORB) for geometric verification of stage-2 candidates.

At onboarding, :mod:`pipeline.stages.features` detects keypoints and descriptors on every view and stores
them in the ``view_features`` table. At query time, :mod:`pipeline.query.verify` detects them on the ROI,
matches them against the top candidates' views (ratio test, then a RANSAC inlier count) and fuses the
inlier count with the global descriptor score.
"""

from pipeline.localfeat.config import DETECTORS, FeatureConfig
from pipeline.localfeat.detect import Features, detect, from_row, to_row

__all__ = ["DETECTORS", "FeatureConfig", "Features", "detect", "from_row", "to_row"]
