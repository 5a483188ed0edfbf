"""The paper profile's real onboarding path (LLaVA captions, CLIP text/image, DINOv2 views) with tiny
random models of the real architectures, passed by local directory through the CLI's --model option."""

from __future__ import annotations

import json
import shutil

import numpy as np
from conftest import SAMPLE_LIBRARY

from pipeline import schemas
from pipeline.onboard.cli import main
from pipeline.store import Store


def test_paper_profile_onboarding_with_tiny_models(tmp_path, tiny_paper_models, capsys):
    lib, store = tmp_path / "lib", tmp_path / "store"
    shutil.copytree(SAMPLE_LIBRARY / "011_banana", lib / "banana")
    models = [a for role, d in tiny_paper_models.items() for a in ("--model", f"{role}={d}")]
    argv = [
        str(lib),
        "--store",
        str(store),
        "--profile",
        "paper",
        *models,
        "--resolution",
        "96",
        "--workers",
        "0",
        "--no-progress",
        "--json",
    ]
    assert main(argv) == 0
    summary = json.loads(capsys.readouterr().out)
    assert summary["rendered"] == 1 and summary["failed"] == 0

    s = Store.open(store)
    caps = s.read("captions")
    assert caps.num_rows == 8
    assert set(caps.column("captioner_id").to_pylist()) == {f"llava:{tiny_paper_models['captioner']}"}
    assert all(isinstance(c, str) for c in caps.column("caption").to_pylist())
    assert caps.column("prompt")[0].as_py().startswith("Extract visual attributes of the main object")

    (text_ds,) = s.datasets("text_embeddings")
    image_ds = s.datasets("image_embeddings")
    assert len(image_ds) == 2  # DINOv2 (stage 2) and CLIP image (ablations)
    for ds in [text_ds, *image_ds]:
        t = s.read(ds)
        assert t.num_rows == 8
        dim = t.column("dim")[0].as_py()
        assert t.schema.equals(schemas.embedding_schema(dim))
        v = np.stack(t.column("embedding").to_numpy(zero_copy_only=False))
        assert np.allclose(np.linalg.norm(v, axis=1), 1, atol=1e-4)
    encoders = {s.read(d).column("encoder_id")[0].as_py().split(":")[0] for d in image_ds}
    assert encoders == {"dinov2", "clip_image"}
    run = json.loads(s.read("runs").column("config_json")[0].as_py())
    assert run["models"]["captioner"].startswith("llava:") and run["profile"] == "paper"

    # same models again: nothing to do; another captioner id re-captions but does not re-render
    assert main(argv) == 0
    assert json.loads(capsys.readouterr().out)["rendered"] == 0


def test_missing_weights_is_a_one_line_error(tmp_path, capsys):
    lib = tmp_path / "lib"
    shutil.copytree(SAMPLE_LIBRARY / "011_banana", lib / "banana")
    argv = [
        str(lib),
        "--store",
        str(tmp_path / "store"),
        "--profile",
        "paper",
        "--model",
        f"captioner={tmp_path / 'no_such_model'}",
        "--workers",
        "0",
        "--no-progress",
    ]
    code = main(argv)
    err = capsys.readouterr().err.strip()
    assert code != 0 and err.count("\n") == 0
    assert "no_such_model" in err and "--profile offline" in err
