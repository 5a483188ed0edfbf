"""How views are rendered (:class:`RenderConfig`) and the version that keys rendered pixels."""

from __future__ import annotations

from dataclasses import asdict, dataclass

from pipeline.fingerprint import fingerprint

#: Bump when rendering code changes in a way that changes pixels. 6: OBJ vertices are split where their
#: texture coordinates differ (UV seams); 5 and before gave every seam vertex one chart's coordinates, so
#: scanned meshes rendered with dark cracks along their seams (docs/results.md, section 9).
RENDER_VERSION = "pyrender-6"
GRAY = (205, 205, 205)
#: The paper's elevation rings (K=8: 4 views at -15 and 4 at +15 deg). The offline profile adds a +45 deg
#: ring (:data:`pipeline.profiles.PROFILES`): see docs/query.md, "Elevation rings".
PAPER_ELEVATIONS: tuple[float, ...] = (-15.0, 15.0)
#: At most this many elevation rings.
MAX_RINGS = 6


@dataclass(frozen=True)
class RenderConfig:
    """How views are rendered. The paper: K=8, 4 at -15 and 4 at +15 deg elevation, gray background."""

    cameras: str = "oscar"  # "oscar" (paper layout) | "cap3d" (reference scripts' 8 fixed positions)
    resolution: int = 512
    background: tuple[int, int, int] = GRAY
    yfov_deg: float = 40.0
    fill: float = 0.9  # the object's projection spans this fraction of the frame
    upper_ring_offset_deg: float = 45.0  # azimuth offset of ring r is r times this (0 = aligned rings)
    elevations_deg: tuple[float, ...] = PAPER_ELEVATIONS  # one ring of ``views_per_ring`` views each
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
        elevations = tuple(float(e) for e in self.elevations_deg)
        if not 1 <= len(elevations) <= MAX_RINGS:
            raise ValueError(f"give 1 to {MAX_RINGS} elevation rings, got {len(elevations)}")
        if not all(math.isfinite(e) and -89.0 <= e <= 89.0 for e in elevations):
            raise ValueError(f"elevations must be within -89..89 degrees, got {list(self.elevations_deg)}")
        object.__setattr__(self, "elevations_deg", elevations)  # a list (from JSON) becomes a tuple

    def fingerprint(self) -> str:
        d = asdict(self)
        if not d["extra_bg_view"]:
            del d["extra_bg_view"]  # off: the fingerprint of before the option existed (stores stay valid)
        if self.cameras == "cap3d":
            d["cap3d_layout"] = 2  # views 4 and 5 at 26.3 deg (0.7), as the reference; 1 had them at 8 deg
        return fingerprint({"v": RENDER_VERSION, **d})
