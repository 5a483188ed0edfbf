"""How views are rendered (:class:`RenderConfig`) and the version that keys rendered pixels."""

from __future__ import annotations

from dataclasses import asdict, dataclass

from pipeline.fingerprint import fingerprint

#: Bump when rendering code changes in a way that changes pixels.
RENDER_VERSION = "pyrender-5"
GRAY = (205, 205, 205)


@dataclass(frozen=True)
class RenderConfig:
    """How views are rendered. The paper: K=8, 4 at -15 and 4 at +15 deg elevation, gray background."""

    cameras: str = "oscar"  # "oscar" (paper layout) | "cap3d" (reference scripts' 8 fixed positions)
    resolution: int = 512
    background: tuple[int, int, int] = GRAY
    yfov_deg: float = 40.0
    fill: float = 0.9  # the object's projection spans this fraction of the frame
    upper_ring_offset_deg: float = 45.0  # azimuth offset of the +15 deg ring (0 = same azimuths as -15 ring)
    elevations_deg: tuple[float, float] = (-15.0, 15.0)
    views_per_ring: int = 4
    max_texture: int = 1024  # textures are downscaled to this edge length before upload
    up: str = "auto"  # "auto" (z up; y up for glTF) | "z" | "y"

    def fingerprint(self) -> str:
        return fingerprint({"v": RENDER_VERSION, **asdict(self)})
