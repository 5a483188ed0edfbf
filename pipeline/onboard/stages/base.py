"""Shared helpers of the stages: the model-holding base, the error columns and splitting failed rows."""

from __future__ import annotations

from typing import TYPE_CHECKING

import pyarrow as pa
import pyarrow.compute as pc

from pipeline import schemas
from pipeline.store import utcnow

if TYPE_CHECKING:
    from pipeline.onboard.stages.step import StageConfig, Step


class ModelStage:
    """A stage that holds one model role's adapter (built lazily, once) under one step's fingerprint."""

    def __init__(self, cfg: StageConfig, run_id: str, step: Step, model=None):
        self.cfg = cfg
        self.run_id = run_id
        self.role = step.role
        self.spec = step.spec
        self.fingerprint = step.fingerprint
        self._model = model

    @property
    def model(self):
        if self._model is None:
            from pipeline.models.registry import create_model

            self._model = create_model(self.role, self.spec, **self.cfg.model_options.get(self.role, {}))
        return self._model


ERROR_FIELDS = [pa.field("error", pa.string()), pa.field("error_type", pa.string())]


def with_errors(schema: pa.Schema) -> pa.Schema:
    """``schema`` with every field nullable plus the error columns (a stage's output schema)."""
    return pa.schema([f.with_nullable(True) for f in schema] + ERROR_FIELDS)


def error_row(
    schema: pa.Schema, values: dict, exc: BaseException | str, error_type: str | None = None
) -> dict:
    """One output row for a failed item: its key values, nulls elsewhere, and a one-line reason."""
    row = {f.name: values.get(f.name) for f in schema}
    msg = str(exc) if not isinstance(exc, str) else exc
    row["error"] = (msg.splitlines() or ["unknown error"])[0][:500]
    row["error_type"] = error_type or (type(exc).__name__ if not isinstance(exc, str) else "Error")
    return row


def split_errors(
    out: pa.Table, target: pa.Schema, stage: str, run_id: str, source_paths: dict[str, str] | None = None
) -> tuple[pa.Table, pa.Table]:
    """Split a stage's output into (rows conformed to ``target``, ``errors`` rows)."""
    if "error" not in out.column_names:
        return schemas.conform(out, target), schemas.ERRORS.empty_table()
    failed = pc.is_valid(out.column("error"))
    good = out.filter(pc.invert(failed))
    bad = out.filter(failed)
    now = utcnow()
    paths = source_paths or {}
    err = {
        "run_id": [run_id] * bad.num_rows,
        "stage": [stage] * bad.num_rows,
        "mesh_id": bad.column("mesh_id").to_pylist(),
        "source_path": [paths.get(m) for m in bad.column("mesh_id").to_pylist()],
        "fingerprint": bad.column("fingerprint").to_pylist() if "fingerprint" in bad.column_names else None,
        "error_type": bad.column("error_type").to_pylist(),
        "reason": bad.column("error").to_pylist(),
        "at": [now] * bad.num_rows,
    }
    if err["fingerprint"] is None:
        err["fingerprint"] = [None] * bad.num_rows
    errors = pa.table(err, schema=schemas.ERRORS)
    return schemas.conform(good.drop_columns(["error", "error_type"]), target), errors
