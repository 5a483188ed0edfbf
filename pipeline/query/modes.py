"""The ranking modes: the names of the step lists (:data:`pipeline.query.steps.STEP_LISTS`), written out
once here for the CLIs' ``--help`` (this module imports nothing)."""

MODES = ("two-stage", "text-only", "image-only")
