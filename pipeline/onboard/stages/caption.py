"""Caption stage: view images in, one caption row per view out."""

from __future__ import annotations

import pyarrow as pa

from pipeline import schemas
from pipeline.onboard.stages.base import ModelStage, error_row, with_errors

CAPTION_OUT = with_errors(schemas.CAPTIONS)


class CaptionStage(ModelStage):
    """Captions every view with the profile's captioner (built once, lazily)."""

    def __call__(self, views: pa.Table) -> pa.Table:
        from pipeline.onboard.stages.decoded import decoded_view

        model = self.model  # a model that cannot load ends the run (ModelLoadError), it is no mesh's fault
        from pipeline.mesh.cameras import is_captioned

        items = [
            it
            for it in views.select(["mesh_id", "view_index", "image", "fingerprint"]).to_pylist()
            if is_captioned(self.cfg.render, it["view_index"])  # the extra background view is stage 2 only
        ]
        rows: list[dict] = []
        by_mesh: dict[str, list[dict]] = {}
        for it in items:
            by_mesh.setdefault(it["mesh_id"], []).append(it)
        for mesh_id, its in by_mesh.items():
            base = {"mesh_id": mesh_id, "fingerprint": self.fingerprint, "run_id": self.run_id}
            try:
                texts = model.caption([decoded_view(it["image"]) for it in its], self.cfg.prompt)
            except Exception as exc:  # a failing mesh becomes an errors row
                rows.append(error_row(CAPTION_OUT, base, exc))
                continue
            for it, text in zip(its, texts, strict=True):
                rows.append(
                    {
                        **base,
                        "view_index": it["view_index"],
                        "captioner_id": self.spec.key(),
                        "prompt_style": self.cfg.prompt_style,
                        "prompt": self.cfg.prompt,
                        "caption": text,
                        "view_fingerprint": it["fingerprint"],
                    }
                )
        return pa.Table.from_pylist(rows, schema=CAPTION_OUT)
