"""Shared fixtures: where the real data lives, small mesh libraries, and helpers to read stores."""

from __future__ import annotations

import os
import shutil
from pathlib import Path

import pytest

REPO = Path(__file__).resolve().parents[1]
SHARED_DATA = Path(os.environ.get("OSCAR_SHARED_DATA", REPO.parent / "shared" / "data"))
YCB = SHARED_DATA / "ycb"
SAMPLE_LIBRARY = REPO / "data" / "sample_library"

os.environ.setdefault("HF_HUB_OFFLINE", "1")
os.environ.setdefault("TRANSFORMERS_OFFLINE", "1")
# float32 for the learned encoder on every machine, so that recorded scores (tests/golden) do not depend on
# whether the CPU has AMX; the bfloat16 path is tested by name (tests/test_focus_weights.py)
os.environ.setdefault("OSCAR_PRECISION", "fp32")


def need_shared(path: Path = YCB) -> Path:
    """Skip the calling test when ../shared/data (or a part of it) is absent."""
    if not path.exists():
        pytest.skip(f"real data not found at {path} (set OSCAR_SHARED_DATA or clone beside ../shared)")
    return path


def copy_ycb(dst: Path, names: list[str]) -> Path:
    """Copy YCB mesh folders (obj, mtl, texture) into ``dst``; skip when the data is absent."""
    src = need_shared()
    for n in names:
        shutil.copytree(src / n, dst / n)
    return dst


@pytest.fixture(scope="session")
def offline_models():
    """The offline profile's adapters, built once per session and injected into executors."""
    from pipeline.models.registry import create_model
    from pipeline.profiles import get_profile

    p = get_profile("offline")
    return {
        "captioner": create_model("captioner", p.captioner),
        "text_encoder": create_model("text_encoder", p.text_encoder),
        "view_encoder": create_model("view_encoder", p.view_encoder),
        "learned_encoder": create_model("learned_encoder", p.learned_encoder),
    }


@pytest.fixture(scope="session")
def tiny_paper_models(tmp_path_factory) -> dict[str, str]:
    """Tiny random LLaVA, CLIP and DINOv2 saved to disk: role -> local dir, for ``--model ROLE=DIR``."""
    pytest.importorskip("transformers")
    import tiny_models

    root = tmp_path_factory.mktemp("tiny_hf")
    clip = str(tiny_models.build_clip(root / "clip"))
    return {
        "captioner": str(tiny_models.build_llava(root / "llava")),
        "text_encoder": clip,
        "clip_image_encoder": clip,
        "view_encoder": str(tiny_models.build_dinov2(root / "dinov2")),
    }
