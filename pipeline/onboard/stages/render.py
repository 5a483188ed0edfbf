"""Render stage: mesh files in, one row per rendered view (with the mesh's geometry stats) out."""

from __future__ import annotations

import pyarrow as pa

from pipeline import schemas
from pipeline.mesh.load import load_mesh
from pipeline.onboard.stages.base import error_row, with_errors
from pipeline.onboard.stages.step import StageConfig, Step

GEOMETRY_FIELDS = [
    pa.field("n_vertices", pa.int64()),
    pa.field("n_faces", pa.int64()),
    pa.field("bounds_min", schemas.VEC3),
    pa.field("bounds_max", schemas.VEC3),
    pa.field("units_guess", pa.string()),
    pa.field("scale_to_unit", pa.float64()),
]
RENDER_OUT = with_errors(pa.schema(list(schemas.VIEWS) + GEOMETRY_FIELDS))
RENDER_IN = pa.schema(
    [pa.field("mesh_id", pa.string()), pa.field("abs_path", pa.string()), pa.field("format", pa.string())]
)


class RenderStage:
    """Loads, normalises and renders each mesh of a batch; the GL context lives as long as the object."""

    def __init__(self, cfg: StageConfig, run_id: str, step: Step, model=None):
        self.cfg = cfg
        self.run_id = run_id
        self.fingerprint = step.fingerprint
        self._renderer = None

    @property
    def renderer(self):
        """The GL renderer, created on first use (it lives as long as this object)."""
        if self._renderer is None:
            from pipeline.mesh.render import Renderer

            self._renderer = Renderer(self.cfg.render)
        return self._renderer

    def warm_up(self) -> None:
        """Create the GL context and compile the shaders now (render workers do this before timing)."""
        self.renderer.warm_up()

    def __call__(self, batch: pa.Table) -> pa.Table:
        rows: list[dict] = []
        for item in batch.select(["mesh_id", "abs_path", "format"]).to_pylist():
            rows.extend(self.render_one(item))
        return pa.Table.from_pylist(rows, schema=RENDER_OUT)

    def render_one(self, item: dict) -> list[dict]:
        """Rows for one mesh: one per view, or a single error row."""
        from pipeline.mesh.render import encode_png

        base = {"mesh_id": item["mesh_id"], "fingerprint": self.fingerprint, "run_id": self.run_id}
        try:
            rc = self.cfg.render
            mesh = load_mesh(
                item["abs_path"],
                item["format"],
                max_faces=self.cfg.max_faces,
                up=rc.up,
                max_texture=rc.max_texture,
                max_texture_pixels=self.cfg.max_texture_pixels,
            )
            views = self.renderer.render(mesh)
        except Exception as exc:  # one bad mesh must never stop the run
            return [error_row(RENDER_OUT, base, exc)]
        geo = {
            "n_vertices": mesh.n_vertices,
            "n_faces": mesh.n_faces,
            "bounds_min": mesh.bounds_min,
            "bounds_max": mesh.bounds_max,
            "units_guess": mesh.units_guess,
            "scale_to_unit": mesh.scale_to_unit,
        }
        return [
            {
                **base,
                **geo,
                "view_index": v.view_index,
                "azimuth_deg": v.azimuth_deg,
                "elevation_deg": v.elevation_deg,
                "camera_pose": v.camera_pose.reshape(-1).tolist(),
                "yfov_deg": rc.yfov_deg,
                "width": rc.resolution,
                "height": rc.resolution,
                "image": encode_png(v.image),
            }
            for v in views
        ]
