"""Per-query pose hypotheses from an answer's candidates, in the BOP ground-truth convention.

A hypothesis is ``cam_R_m2c`` (3x3 row-major, 9 numbers) and ``cam_t_m2c`` (millimetres): the model's frame
(the exported ``models/obj_NNNNNN.ply``, in mm) to the camera, OpenCV axes, as BOP's ``scene_gt.json``. The
rotation is the best view's. The translation is the best view's own (the object as far as it was rendered)
unless the photo's intrinsics are given: then it is placed on the ray through the ROI box centre, at the
depth where the object's projected box is as large as the ROI box (the pinhole ratio, from the best view's
own projected box), as MegaPose and FoundationPose initialise a translation from a detection.
"""

from __future__ import annotations

import itertools

import numpy as np

from pipeline.mesh import frames


def box_corners(extent_m, centre_m) -> np.ndarray:
    """The 8 corners (metres, source frame) of an axis-aligned box of size ``extent_m`` at ``centre_m``."""
    half = np.asarray(extent_m, np.float64) / 2.0
    signs = np.array(list(itertools.product((-1.0, 1.0), repeat=3)))
    return np.asarray(centre_m, np.float64) + signs * half


def projected_box(corners_m, pose, k) -> tuple[float, float, float, float]:
    """x0, y0, x1, y1 (pixels) of the projected corners."""
    uv = frames.project(corners_m, np.asarray(pose, np.float64), np.asarray(k, np.float64))
    return float(uv[:, 0].min()), float(uv[:, 1].min()), float(uv[:, 0].max()), float(uv[:, 1].max())


def hypothesis(candidate: dict, centre_m, roi_box=None, photo_k=None) -> dict:
    """One BOP-style pose hypothesis (mm) from a candidate of an answer (its ``--json`` dict).

    ``centre_m``: the model's bounding box centre in metres (source frame); ``roi_box``: the ROI box in
    photo pixels; ``photo_k``: the photo's 3x3 intrinsics (both or neither).
    """
    pose = np.asarray(candidate["best_view_pose"], np.float64)
    rot, t = pose[:3, :3], pose[:3, 3].copy()
    source = "view"
    if roi_box is not None and photo_k is not None:
        k_view = np.asarray(candidate["intrinsics"]["K"], np.float64)
        corners = box_corners(candidate["extent_m"], centre_m)
        x0, y0, x1, y1 = projected_box(corners, pose, k_view)
        view_depth = float((rot @ np.asarray(centre_m) + t)[2])
        kp = np.asarray(photo_k, np.float64)
        bx0, by0, bx1, by1 = (float(v) for v in roi_box)
        span_view = np.hypot(x1 - x0, y1 - y0) / k_view[0, 0]  # normalised image units
        span_photo = np.hypot(bx1 - bx0, by1 - by0) / kp[0, 0]
        depth = view_depth * span_view / span_photo
        ray = np.linalg.inv(kp) @ np.array([(bx0 + bx1) / 2.0, (by0 + by1) / 2.0, 1.0])
        centre_cam = ray / ray[2] * depth
        t = centre_cam - rot @ np.asarray(centre_m, np.float64)
        source = "roi_box"
    return {
        "cam_R_m2c": [round(float(v), 9) + 0.0 for v in rot.reshape(-1)],
        "cam_t_m2c": [round(float(v) * 1000.0, 4) + 0.0 for v in t],
        "translation_from": source,
    }
