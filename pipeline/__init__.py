"""OSCAR: open-set CAD retrieval from a language prompt and a single image.

Onboarding (``python -m pipeline.onboard``) renders, captions and embeds a CAD library into a Parquet
store; querying (``python -m pipeline.query``) returns the best-matching models for a photo + prompt.
"""

__version__ = "0.1.0"
