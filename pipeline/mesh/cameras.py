"""Camera layouts: the paper's two elevation rings and the reference scripts' Cap3D positions."""

from __future__ import annotations

import math

import numpy as np

from pipeline.mesh.settings import RenderConfig

#: Directions of Cap3D's 8 fixed camera positions (x, y, z as multiples of distance * ratio), as its
#: Blender script sets them: ``elevation_factor`` starts at 0.2 and is reassigned before views 2 (0.5),
#: 3 (0.7), 6 (0.5) and 7 (0.7), so views 4 and 5 inherit view 3's 0.7: elevation atan(0.7 / sqrt(2)) =
#: 26.33 degrees, not the 8.05 degrees that 0.2 would give. Elevations, views 0-7: 8.05, 8.05, 24.09, 32.05,
#: 26.33, 26.33, -24.09, -32.05 degrees.
CAP3D_DIRECTIONS = [
    (1.0, -1.0, 0.2),
    (-1.0, 1.0, 0.2),
    (1.0, -0.5, 0.5),
    (-0.5, 1.0, 0.7),
    (1.0, 1.0, 0.7),
    (-1.0, -1.0, 0.7),
    (1.0, 0.5, -0.5),
    (-0.5, -1.0, -0.7),
]
#: Background of the optional extra reference view: Cap3D's ``_bg`` render has a transparent film (RGBA,
#: transparent pixels 0), which reads as black when the image is loaded as RGB for DINOv2.
EXTRA_BG_COLOR = (0, 0, 0)


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


def extra_bg_view(cfg: RenderConfig) -> tuple[int, float, float, np.ndarray] | None:
    """(view_index, azimuth, elevation, direction) of the extra ``_bg`` reference view, or ``None``.

    The reference renders it from view 0's position on a transparent background and uses it as one more
    DINOv2 reference view (stage 2 only: it is not captioned). Its index follows the layout's views.
    """
    if not getattr(cfg, "extra_bg_view", False):
        return None
    views = view_directions(cfg)
    az, el, d = views[0]
    return len(views), az, el, d


def is_captioned(cfg: RenderConfig, view_index: int) -> bool:
    """Whether a view gets a caption (every layout view; not the extra background view)."""
    extra = extra_bg_view(cfg)
    return extra is None or view_index != extra[0]


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
