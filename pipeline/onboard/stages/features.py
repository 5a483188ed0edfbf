"""Local-features stage: view images in, one ``view_features`` row per view out (keypoints + descriptors).

Weight-free (OpenCV SIFT or ORB, :mod:`pipeline.localfeat`). Rows are keyed by the features config's
fingerprint, chained through the render fingerprint, so a re-run does nothing and changing the detector
config recomputes only this stage.
"""

from __future__ import annotations

import pyarrow as pa

from pipeline import schemas
from pipeline.onboard.stages.base import error_row, with_errors

FEATURES_OUT = with_errors(schemas.VIEW_FEATURES)


class FeatureStage:
    """Detects local features on every view of a batch (CPU; no model to load)."""

    model = None  # the engines load a step's model up front; this stage has none

    def __init__(self, cfg, run_id: str, step, model=None):
        self.cfg = cfg
        self.run_id = run_id
        self.features = cfg.features
        self.fingerprint = step.fingerprint

    def __call__(self, views: pa.Table) -> pa.Table:
        from pipeline.localfeat import detect, to_row
        from pipeline.onboard.stages.decoded import decoded_view

        items = views.select(["mesh_id", "view_index", "image", "fingerprint"]).to_pylist()
        by_mesh: dict[str, list[dict]] = {}
        for it in items:
            by_mesh.setdefault(it["mesh_id"], []).append(it)
        base = {"fingerprint": self.fingerprint, "run_id": self.run_id}
        rows: list[dict] = []
        for mesh_id, its in by_mesh.items():
            try:
                found = [
                    {
                        **base,
                        "mesh_id": mesh_id,
                        "view_index": it["view_index"],
                        "detector_id": self.features.detector_id(),
                        "source_fingerprint": it["fingerprint"],
                        **to_row(detect(decoded_view(it["image"]), self.features)),
                    }
                    for it in its
                ]
            except Exception as exc:  # a failing mesh becomes an errors row
                rows.append(error_row(FEATURES_OUT, {**base, "mesh_id": mesh_id}, exc))
                continue
            rows.extend(found)
        return pa.Table.from_pylist(rows, schema=FEATURES_OUT)
