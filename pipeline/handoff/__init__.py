"""From answers to a pose estimator's input: ``python -m pipeline.handoff`` (docs/handoff.md)."""
