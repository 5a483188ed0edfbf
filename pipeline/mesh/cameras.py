"""Camera layouts: the paper's two elevation rings and the reference scripts' Cap3D positions."""

from __future__ import annotations

import math

import numpy as np

from pipeline.mesh.settings import RenderConfig

#: Directions of Cap3D's 8 fixed camera positions (x, y, z as multiples of distance * ratio).
CAP3D_DIRECTIONS = [
    (1.0, -1.0, 0.2),
    (-1.0, 1.0, 0.2),
    (1.0, -0.5, 0.5),
    (-0.5, 1.0, 0.7),
    (1.0, 1.0, 0.2),
    (-1.0, -1.0, 0.2),
    (1.0, 0.5, -0.5),
    (-0.5, -1.0, -0.7),
]


def view_directions(cfg: RenderConfig) -> list[tuple[float, float, np.ndarray]]:
    """(azimuth_deg, elevation_deg, unit direction from the object to the camera) per view, z up."""
    out = []
    if cfg.cameras == "oscar":
        for ring, elev in enumerate(cfg.elevations_deg):
            for k in range(cfg.views_per_ring):
                az = (360.0 * k / cfg.views_per_ring + ring * cfg.upper_ring_offset_deg) % 360.0
                out.append((az, elev, _direction(az, elev)))
    elif cfg.cameras == "cap3d":
        for x, y, z in CAP3D_DIRECTIONS:
            d = np.array([x, y, z], dtype=np.float64)
            d /= np.linalg.norm(d)
            az = math.degrees(math.atan2(d[1], d[0])) % 360.0
            el = math.degrees(math.asin(d[2]))
            out.append((az, el, d))
    else:
        raise ValueError(f"unknown camera layout {cfg.cameras!r}; choose oscar or cap3d")
    return out


def _direction(az_deg: float, el_deg: float) -> np.ndarray:
    az, el = math.radians(az_deg), math.radians(el_deg)
    return np.array([math.cos(el) * math.cos(az), math.cos(el) * math.sin(az), math.sin(el)])


def look_at_pose(direction: np.ndarray, distance: float, up=(0.0, 0.0, 1.0)) -> np.ndarray:
    """Camera-to-world 4x4 (OpenGL: camera looks down -z) at ``distance * direction``, aimed at the origin."""
    eye = direction * distance
    fwd = -direction / np.linalg.norm(direction)
    up = np.asarray(up, dtype=np.float64)
    if abs(np.dot(fwd, up)) > 0.999:
        up = np.array([0.0, 1.0, 0.0])
    right = np.cross(fwd, up)
    right /= np.linalg.norm(right)
    true_up = np.cross(right, fwd)
    pose = np.eye(4)
    pose[:3, 0], pose[:3, 1], pose[:3, 2], pose[:3, 3] = right, true_up, -fwd, eye
    return pose


def framed_pose(
    points: np.ndarray, direction: np.ndarray, yfov_deg: float, fill: float, iterations: int = 12
) -> np.ndarray:
    """Camera-to-world pose looking along ``-direction`` with the object centred and filling ``fill`` of the frame.

    The aim point is moved across the view until the perspective projection of the object is centred
    (off-centre shapes such as a banana seen from the side stay centred); the distance is then fitted.
    """
    axes = look_at_pose(direction, 1.0)
    right, up = axes[:3, 0], axes[:3, 1]
    t = math.tan(math.radians(yfov_deg) / 2.0)
    u, v = points @ right, points @ up
    target = right * (u.min() + u.max()) / 2.0 + up * (v.min() + v.max()) / 2.0
    for _ in range(iterations):
        rel = points - target
        dist = fit_distance(rel, direction, yfov_deg, fill)
        depth = dist - rel @ direction
        x, y = (rel @ right) / (depth * t), (rel @ up) / (depth * t)
        cx, cy = (x.min() + x.max()) / 2.0, (y.min() + y.max()) / 2.0
        target = target + 0.6 * (right * cx + up * cy) * dist * t  # damped: the refit moves the frame too
    rel = points - target
    dist = fit_distance(rel, direction, yfov_deg, fill)
    pose = axes.copy()
    pose[:3, 3] = target + direction * dist
    return pose


def fit_distance(points: np.ndarray, direction: np.ndarray, yfov_deg: float, fill: float) -> float:
    """Smallest camera distance at which every point projects within ``fill`` of the (square) frame.

    With the camera on the ray ``direction`` looking at the origin, a point's lateral offsets do not depend
    on the distance, its depth is ``d - p.direction``; solve ``|lateral| / (depth * tan(fov/2)) <= fill``.
    """
    pose = look_at_pose(direction, 1.0)
    right, up = pose[:3, 0], pose[:3, 1]
    t = math.tan(math.radians(yfov_deg) / 2.0) * fill
    lateral = np.maximum(np.abs(points @ right), np.abs(points @ up))
    d = float(np.max(lateral / t + points @ direction))
    near_margin = float(np.max(points @ direction)) + 0.05
    return max(d, near_margin)
