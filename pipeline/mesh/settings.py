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
    extra_bg_view: bool = False  # reference scripts: view 0 again on black, an extra stage-2 view

    def __post_init__(self) -> None:
        import math

        if not 16 <= self.resolution <= 8192:
            raise ValueError(f"resolution must be 16..8192 pixels, got {self.resolution}")
        if not math.isfinite(self.upper_ring_offset_deg):
            raise ValueError(f"upper ring offset must be a finite angle, got {self.upper_ring_offset_deg}")

    def fingerprint(self) -> str:
        d = asdict(self)
        if not d["extra_bg_view"]:
            del d["extra_bg_view"]  # off: the fingerprint of before the option existed (stores stay valid)
        if self.cameras == "cap3d":
            d["cap3d_layout"] = 2  # views 4 and 5 at 26.3 deg (0.7), as the reference; 1 had them at 8 deg
        return fingerprint({"v": RENDER_VERSION, **d})
