"""Evaluation: query sets (JSONL/CSV, BOP, synthetic), the paper's metrics, sweeps over the cheap query
stages, and reports (``python -m pipeline.evaluate``). Heavy modules are imported where they are used."""
