"""Coordinate frames between a source mesh file, the renderer's normalised frame and a view's camera.

The renderer (:func:`pipeline.mesh.load.load_mesh`) moves a mesh into a *normalised frame*: the bounding
box centre to the origin, the bounding sphere (about that centre) to radius 1, and z up (glTF files are
y-up by specification). Views store their camera-to-world pose in that frame, in OpenGL axes. A pose
estimator needs the other way round: the transform from the source file's frame, **in metres**, to the
camera, in **OpenCV axes** (x right, y down, z forward), and the intrinsics ``K`` in pixels.

Everything here is plain NumPy over plain numbers (the meshes and views table's columns), so it can be
tested geometrically (``tests/test_handoff.py`` projects a mesh with these matrices onto its rendered view).
"""

from __future__ import annotations

import math

import numpy as np

from pipeline.mesh.load import up_rotation

#: metres per file unit, by the units the loader guessed (``meshes.units_guess``)
METRES_PER_UNIT = {"m": 1.0, "mm": 0.001}
#: OpenGL camera axes (x right, y up, looking down -z) to OpenCV's (x right, y down, z forward)
GL_TO_CV = np.diag([1.0, -1.0, -1.0, 1.0])


def scale_to_metres(units: str) -> float:
    """The factor that turns the file's coordinates into metres (``"m"`` 1, ``"mm"`` 0.001)."""
    try:
        return METRES_PER_UNIT[units]
    except KeyError:
        raise ValueError(f"unknown units {units!r}; choose from {', '.join(METRES_PER_UNIT)}") from None


def extent_m(bounds_min, bounds_max, units: str) -> list[float]:
    """The axis-aligned size (x, y, z) of the source mesh in metres."""
    size = np.asarray(bounds_max, np.float64) - np.asarray(bounds_min, np.float64)
    return [float(v) for v in size * scale_to_metres(units)]


def normalisation(bounds_min, bounds_max, scale_to_unit: float, fmt: str, up: str = "auto") -> np.ndarray:
    """4x4 from the source file's frame (file units) to the renderer's normalised frame.

    ``p_n = scale_to_unit * R_up @ (p - centre)``, with ``centre`` the bounding box centre, as
    :func:`pipeline.mesh.load.load_mesh` applies it (``up`` is the render config's up axis).
    """
    rot = up_rotation(fmt, up)
    centre = (np.asarray(bounds_min, np.float64) + np.asarray(bounds_max, np.float64)) / 2.0
    t = np.eye(4)
    t[:3, :3] = rot * float(scale_to_unit)
    t[:3, 3] = -(rot @ centre) * float(scale_to_unit)
    return t


def intrinsics(yfov_deg: float, width: int, height: int) -> np.ndarray:
    """3x3 pinhole ``K`` of a pyrender ``PerspectiveCamera(yfov)`` rendering ``width`` x ``height`` pixels.

    Square pixels (pyrender sets the x field of view from the aspect ratio); the principal point is the
    image centre in OpenCV's convention, where pixel (0, 0)'s *centre* is at (0, 0): ``((W-1)/2, (H-1)/2)``.
    """
    f = (height / 2.0) / math.tan(math.radians(yfov_deg) / 2.0)
    return np.array([[f, 0.0, (width - 1) / 2.0], [0.0, f, (height - 1) / 2.0], [0.0, 0.0, 1.0]])


def view_pose(camera_pose_gl, norm: np.ndarray, metres_per_unit: float) -> np.ndarray:
    """4x4 rigid transform from the source frame **in metres** to the view's camera, OpenCV axes.

    ``camera_pose_gl`` is the view's camera-to-world pose in the normalised frame (OpenGL, 16 numbers
    row-major or 4x4); ``norm`` is :func:`normalisation`. The normalised frame is the metric one scaled by
    ``s = scale_to_unit / metres_per_unit``; a uniform scale does not change a perspective projection, so the
    camera is placed at the same viewpoint ``1/s`` times farther: the rotation is the view's, the
    translation is in metres, and the object projects exactly as it does in the stored image.
    """
    c2w = np.asarray(camera_pose_gl, np.float64).reshape(4, 4)
    to_units = np.diag([1.0 / metres_per_unit] * 3 + [1.0])  # metres -> file units
    full = GL_TO_CV @ np.linalg.inv(c2w) @ norm @ to_units  # metres -> camera, scaled by s
    s = float(np.cbrt(np.linalg.det(full[:3, :3])))
    pose = np.eye(4)
    u, _, vt = np.linalg.svd(full[:3, :3] / s)  # re-orthonormalise (float32-rounded stored poses)
    pose[:3, :3] = u @ vt
    pose[:3, 3] = full[:3, 3] / s
    return pose


def project(points_m, pose: np.ndarray, k: np.ndarray) -> np.ndarray:
    """Pixel coordinates (n, 2), OpenCV convention, of ``points_m`` (n, 3, metres, source frame)."""
    p = np.asarray(points_m, np.float64) @ pose[:3, :3].T + pose[:3, 3]
    uv = p @ k.T
    return uv[:, :2] / uv[:, 2:3]


def rotation_angle_deg(r_a: np.ndarray, r_b: np.ndarray) -> float:
    """Geodesic angle (degrees) between two 3x3 rotations."""
    c = (np.trace(np.asarray(r_a)[:3, :3].T @ np.asarray(r_b)[:3, :3]) - 1.0) / 2.0
    return math.degrees(math.acos(min(1.0, max(-1.0, c))))
