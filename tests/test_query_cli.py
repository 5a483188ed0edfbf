"""``python -m pipeline.query``: output formats, batch mode, and one-line errors with a non-zero exit."""

from __future__ import annotations

import json
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest
from PIL import Image
from query_helpers import fake_models, make_fake_store, object_image

from pipeline.query.cli import main

REPO = Path(__file__).resolve().parents[1]


@pytest.fixture(scope="module")
def store(tmp_path_factory):
    return make_fake_store(tmp_path_factory.mktemp("cli") / "store")


@pytest.fixture(scope="module")
def photo(tmp_path_factory):
    d = tmp_path_factory.mktemp("photos")
    img = object_image("red", 44, 52, pad=30)
    img.save(d / "can.png")
    mask = np.abs(np.asarray(img, np.int16) - 205).sum(axis=2) > 30
    Image.fromarray(mask).save(d / "can_mask.png")
    return d


@pytest.fixture()
def fakes(monkeypatch):
    """Every model the CLI builds comes from the fake adapters (same factory entry point)."""
    import pipeline.models.registry as registry

    models = fake_models()
    monkeypatch.setattr(registry, "create_model", lambda role, spec, **kw: models[role])
    return models


def run(argv, capsys):
    code = main([str(a) for a in argv])
    out, err = capsys.readouterr()
    return code, out, err


def test_table_output(store, photo, fakes, capsys):
    code, out, err = run(
        [
            "--store",
            store,
            "--image",
            photo / "can.png",
            "--prompt",
            "the red can",
            "--mask",
            photo / "can_mask.png",
        ],
        capsys,
    )
    assert code == 0, err
    lines = out.splitlines()
    header = next(i for i, line in enumerate(lines) if line.lstrip().startswith("rank"))
    assert lines[header + 1].split()[:2] == ["1", "red_can"]
    assert "ROI caption: a red can" in out and out.rstrip().splitlines()[-1].startswith("timings:")


def test_json_explain_and_modes(store, photo, fakes, capsys, tmp_path):
    argv = [
        "--store",
        store,
        "--image",
        photo / "can.png",
        "--prompt",
        "the red can",
        "--box",
        "25,25,100,110",
    ]
    code, out, err = run(
        [*argv, "--json", "--explain", tmp_path / "x.png", "--mode", "image-only", "--top", "2"], capsys
    )
    assert code == 0, err
    data = json.loads(out)
    assert data["mode"] == "image-only" and data["decided_by"] == "stage2" and len(data["candidates"]) == 2
    assert data["candidates"][0]["name"] == "red_can" and Path(data["explain"]).is_file()
    assert data["query"]["roi"]["source"] == "box"
    code, out, err = run(
        [*argv, "--json", "--mode", "text-only", "--roi", "bbox", "--threshold", "0.99"], capsys
    )
    assert code == 0 and json.loads(out)["decided_by"] == "stage1"


def test_batch_mode_writes_jsonl(store, photo, fakes, capsys, tmp_path):
    q = tmp_path / "q.jsonl"
    q.write_text(
        json.dumps(
            {"image": str(photo / "can.png"), "prompt": "the red can", "mask": str(photo / "can_mask.png")}
        )
        + "\n"
        + json.dumps({"image": str(photo / "nope.png"), "prompt": "the red can", "box": [1, 1, 40, 40]})
        + "\n"
    )
    out_file = tmp_path / "out.jsonl"
    code, out, err = run(["--store", store, "--queries", q, "--output", out_file, "--no-progress"], capsys)
    rows = [json.loads(x) for x in out_file.read_text().splitlines()]
    assert code == 1 and len(rows) == 2 and rows[0]["candidates"][0]["name"] == "red_can"
    assert "image not found" in rows[1]["error"]
    assert err.strip() == "1 of 2 queries failed; see the error field of their lines"


def _bad_cases(store, photo, tmp_path):
    junk = tmp_path / "junk.png"
    junk.write_text("not an image")
    small_mask = tmp_path / "small.png"
    Image.new("L", (10, 10), 255).save(small_mask)
    gray16 = tmp_path / "gray16.png"
    Image.fromarray(np.full((8, 8), 40000, np.uint16)).save(gray16)
    img, prompt = photo / "can.png", "the red can"
    base = ["--store", store, "--image", img, "--prompt", prompt]
    return {
        "missing image": (
            ["--store", store, "--image", tmp_path / "none.jpg", "--prompt", prompt, "--box", "1,1,9,9"],
            "image not found",
        ),
        "not an image": (
            ["--store", store, "--image", junk, "--prompt", prompt, "--box", "1,1,9,9"],
            "not an image",
        ),
        "tiny 16-bit image": (
            ["--store", store, "--image", gray16, "--prompt", prompt, "--box", "1,1,9,9"],
            "too small",
        ),
        "empty prompt": (
            ["--store", store, "--image", img, "--prompt", "  ", "--box", "1,1,9,9"],
            "prompt is empty",
        ),
        "absurd prompt": (
            ["--store", store, "--image", img, "--prompt", "%%% 42", "--box", "1,1,9,9"],
            "no words",
        ),
        "box syntax": ([*base, "--box", "1,2,3"], "four"),
        "box outside": ([*base, "--box", "500,500,600,600"], "outside"),
        "mask size": ([*base, "--mask", small_mask], "mask is 10x10 but the image is 104x112"),
        "no store": (
            ["--store", tmp_path / "nostore", "--image", img, "--prompt", prompt, "--box", "1,1,60,60"],
            "no store",
        ),
        "other profile": ([*base, "--box", "1,1,60,60", "--profile", "paper"], "onboarded with"),
        "no detector": (base, "no object detector"),
        "bad --model": ([*base, "--box", "1,1,60,60", "--model", "text_encoder"], "ROLE=MODEL"),
        "unknown role": ([*base, "--box", "1,1,60,60", "--model", "painter=x"], "unknown model role"),
        "batch and image": (
            ["--store", store, "--queries", tmp_path / "q.jsonl", "--image", img],
            "--queries",
        ),
        "no prompt": (["--store", store, "--image", img], "give --image"),
        "missing queries file": (
            ["--store", store, "--queries", tmp_path / "none.jsonl"],
            "queries file not found",
        ),
        "export from a moved library": ([*base, "--box", "1,1,60,60", "--export", tmp_path / "exp"], "gone"),
    }


CASES = [
    "missing image",
    "not an image",
    "tiny 16-bit image",
    "empty prompt",
    "absurd prompt",
    "box syntax",
    "box outside",
    "mask size",
    "no store",
    "other profile",
    "no detector",
    "bad --model",
    "unknown role",
    "batch and image",
    "no prompt",
    "missing queries file",
    "export from a moved library",
]


@pytest.mark.parametrize("case", CASES)
def test_bad_input_is_one_line_and_non_zero(case, store, photo, fakes, capsys, tmp_path):
    argv, expected = _bad_cases(store, photo, tmp_path)[case]
    code, out, err = run(argv, capsys)
    assert code != 0
    lines = err.strip().splitlines()
    assert len(lines) == 1 and lines[0].startswith("error: ") and expected in lines[0], err


def test_store_unavailable_is_one_line(store, photo, fakes, capsys, monkeypatch):
    """A store that changed under the query and whose newest snapshot failed too (Retriever raises
    StoreUnavailable) ends the command with one line, not a traceback."""
    from pipeline.query import Retriever
    from pipeline.query.errors import StoreUnavailable

    def gone(self, *a, **kw):
        raise StoreUnavailable("the store changed under this query and its newest snapshot failed too: x")

    monkeypatch.setattr(Retriever, "query", gone)
    argv = ["--store", store, "--image", photo / "can.png", "--prompt", "the red can"]
    argv += ["--mask", photo / "can_mask.png"]
    code, out, err = run(argv, capsys)
    assert code == 2 and out == ""
    assert err.strip().splitlines() == [
        "error: the store changed under this query and its newest snapshot failed too: x"
    ], err


def test_empty_store(tmp_path, photo, capsys):
    from pipeline.store import Store

    Store.open(tmp_path / "s", create=True).close()
    code, _, err = run(
        ["--store", tmp_path / "s", "--image", photo / "can.png", "--prompt", "a can", "--box", "1,1,60,60"],
        capsys,
    )
    assert code == 2 and "no completed onboarding run" in err and len(err.strip().splitlines()) == 1


def test_subprocess_exit_code_and_fast_help(tmp_path):
    t0 = time.perf_counter()
    helped = subprocess.run(
        [sys.executable, "-m", "pipeline.query", "--help"], cwd=REPO, capture_output=True, text=True
    )
    assert helped.returncode == 0 and "--fallback-k" in helped.stdout
    assert time.perf_counter() - t0 < 10
    probe = "import sys, pipeline.query.cli; print(sorted(m for m in ('torch', 'transformers', 'pyrender', 'duckdb') if m in sys.modules))"
    assert (
        subprocess.run([sys.executable, "-c", probe], cwd=REPO, capture_output=True, text=True).stdout.strip()
        == "[]"
    )
    bad = subprocess.run(
        [
            sys.executable,
            "-m",
            "pipeline.query",
            "--store",
            str(tmp_path),
            "--image",
            "x.jpg",
            "--prompt",
            "a mug",
        ],
        cwd=REPO,
        capture_output=True,
        text=True,
    )
    assert (
        bad.returncode == 2
        and bad.stderr.count("\n") == 1
        and bad.stderr.startswith("error: image not found")
    )


def test_model_that_cannot_be_loaded_is_one_line(tmp_path, photo, capsys):
    from pipeline.profiles import get_profile

    models = {r: (s.key() if s else None) for r, s in get_profile("offline").roles().items()}
    models["text_encoder"] = "minilm:/nonexistent/minilm"
    store = make_fake_store(tmp_path / "s", models=models)
    argv = ["--store", store, "--image", photo / "can.png", "--prompt", "the red can", "--box", "1,1,60,60"]
    code, _, err = run([*argv, "--model", "text_encoder=/nonexistent/minilm"], capsys)
    assert code == 2 and len(err.strip().splitlines()) == 1
    assert err.startswith("error: ") and "/nonexistent/minilm" in err
