"""A BERT encoder in plain torch for sentence-transformers checkpoints (all-MiniLM-L6-v2 and kin).

Why not ``sentence_transformers``: importing it pulls in transformers, torch.distributed, sklearn and scipy,
which cost a cold ``python -m pipeline.query`` several times a bare ``import torch``. A BERT forward pass
is six small layers; this module reads the same ``model.safetensors``, ``config.json`` and
``tokenizer.json`` (with the ``tokenizers`` library) and computes the same mean-pooled vectors
(``tests/test_minilm_equivalence.py`` checks them against sentence-transformers to 1e-5), so stores
embedded by either stay valid. On the CPU a few texts (a query's prompt) go through NumPy, so the offline
query path imports no torch for them; a batch of at least :data:`TORCH_MIN_TEXTS` (an onboarding batch's
captions) goes through torch where the process has imported it already (for the learned view encoder; a
process without it, such as a Ray text actor or a descriptor-only run, stays on NumPy), in bfloat16
where the CPU computes it natively (:func:`pipeline.models.precision.use_bf16`; a cosine of about 1e-4 from
float32): 384 YCB captions 2.1x faster in float32 and 3.8x in bfloat16 than in NumPy on an AMD EPYC
(``bench/bench_text_encoder.py``; docs/performance.md, "Captions through torch"). On a GPU it is torch.
"""

from __future__ import annotations

import json
import sys
from pathlib import Path

import numpy as np

from pipeline.models.precision import requested, use_bf16

#: sentence-transformers' default when ``sentence_bert_config.json`` is absent
DEFAULT_MAX_SEQ_LENGTH = 256
#: on the CPU, calls with at least this many texts run in torch rather than NumPy, in a process that has
#: imported torch already (for the learned view encoder)
TORCH_MIN_TEXTS = 32


def _read_json(path: Path) -> dict:
    return json.loads(path.read_text()) if path.is_file() else {}


def max_seq_length(model_dir: Path, config: dict) -> int:
    """Token limit as sentence-transformers applies it (its config, capped by the position table)."""
    st = _read_json(model_dir / "sentence_bert_config.json")
    limit = int(st.get("max_seq_length") or DEFAULT_MAX_SEQ_LENGTH)
    return min(limit, int(config.get("max_position_embeddings", limit)))


def load_tokenizer(model_dir: Path, max_length: int):
    """The fast tokenizer of ``tokenizer.json``: truncation to ``max_length``, padding to the longest."""
    from tokenizers import Tokenizer

    tok = Tokenizer.from_file(str(model_dir / "tokenizer.json"))
    tok.enable_truncation(max_length=max_length)
    pad_id = tok.token_to_id("[PAD]")
    tok.enable_padding(pad_id=0 if pad_id is None else pad_id, pad_token="[PAD]")
    return tok


def load_weights(model_dir: Path) -> dict:
    """``model.safetensors`` as torch tensors, the ``bert.`` prefix of some checkpoints removed."""
    from safetensors.torch import load_file

    return {k.removeprefix("bert."): v for k, v in load_file(str(model_dir / "model.safetensors")).items()}


def bert_forward(w: dict, config: dict, ids, type_ids, mask):
    """BERT's last hidden state (B, T, H), computed functionally from the checkpoint's tensors ``w``.

    Functional on purpose: building ``torch.nn`` modules first would spend time on a random init (and, on
    the meta device, import torch._dynamo) only to overwrite every parameter with the file's.
    """
    import torch
    from torch.nn import functional as F

    eps = config.get("layer_norm_eps", 1e-12)
    heads = config["num_attention_heads"]

    def lin(x, name):
        return F.linear(x, w[f"{name}.weight"], w[f"{name}.bias"])

    def norm(x, name):
        return F.layer_norm(x, x.shape[-1:], w[f"{name}.weight"], w[f"{name}.bias"], eps)

    b, t = ids.shape
    pos = torch.arange(t, device=ids.device)[None, :]
    e = "embeddings."
    x = (
        F.embedding(ids, w[e + "word_embeddings.weight"])
        + F.embedding(pos, w[e + "position_embeddings.weight"])
        + F.embedding(type_ids, w[e + "token_type_embeddings.weight"])
    )
    x = norm(x, e + "LayerNorm")
    h = x.shape[-1]
    keep = mask.bool()[:, None, None, :]  # True = a real token

    def split(z):
        return z.view(b, t, heads, h // heads).transpose(1, 2)

    for i in range(config["num_hidden_layers"]):
        L = f"encoder.layer.{i}."
        q, k, v = (split(lin(x, L + f"attention.self.{n}")) for n in ("query", "key", "value"))
        a = F.scaled_dot_product_attention(q, k, v, attn_mask=keep).transpose(1, 2).reshape(b, t, h)
        x = norm(x + lin(a, L + "attention.output.dense"), L + "attention.output.LayerNorm")
        up = F.gelu(lin(x, L + "intermediate.dense"))
        x = norm(x + lin(up, L + "output.dense"), L + "output.LayerNorm")
    return x


def bert_forward_numpy(w: dict, config: dict, ids: np.ndarray, type_ids: np.ndarray, mask: np.ndarray):
    """:func:`bert_forward` in float32 NumPy: the CPU path, which needs no torch import at all."""
    from scipy.special import erf

    eps = np.float32(config.get("layer_norm_eps", 1e-12))
    heads = config["num_attention_heads"]

    def lin(x, name):  # one 2-D GEMM (a 3-D @ 2-D matmul would loop over the batch)
        y = x.reshape(-1, x.shape[-1]) @ w[f"{name}.weight"].T
        return (y + w[f"{name}.bias"]).reshape(*x.shape[:-1], -1)

    def norm(x, name):
        mu = x.mean(-1, keepdims=True)
        var = ((x - mu) ** 2).mean(-1, keepdims=True)
        return (x - mu) / np.sqrt(var + eps) * w[f"{name}.weight"] + w[f"{name}.bias"]

    b, t = ids.shape
    e = "embeddings."
    x = (
        w[e + "word_embeddings.weight"][ids]
        + w[e + "position_embeddings.weight"][np.arange(t)][None]
        + w[e + "token_type_embeddings.weight"][type_ids]
    )
    x = norm(x, e + "LayerNorm")
    h = x.shape[-1]
    d = h // heads
    # padding keys get the most negative float: exp() of it is 0, as torch's boolean attention mask
    bias = np.where(mask.astype(bool), np.float32(0), np.finfo(np.float32).min)[:, None, None, :]
    scale = np.float32(1.0 / np.sqrt(d))

    def split(z):
        return z.reshape(b, t, heads, d).transpose(0, 2, 1, 3)

    for i in range(config["num_hidden_layers"]):
        L = f"encoder.layer.{i}."
        q, k, v = (split(lin(x, L + f"attention.self.{n}")) for n in ("query", "key", "value"))
        scores = (q @ k.transpose(0, 1, 3, 2)) * scale + bias
        scores = np.exp(scores - scores.max(-1, keepdims=True))
        a = (scores / scores.sum(-1, keepdims=True)) @ v
        a = a.transpose(0, 2, 1, 3).reshape(b, t, h)
        x = norm(x + lin(a, L + "attention.output.dense"), L + "attention.output.LayerNorm")
        up = lin(x, L + "intermediate.dense")
        up = np.float32(0.5) * up * (np.float32(1) + erf(up / np.float32(np.sqrt(2.0))).astype(np.float32))
        x = norm(x + lin(up, L + "output.dense"), L + "output.LayerNorm")
    return x


def use_numpy(device: str | None) -> bool:
    """CPU work runs in NumPy (no torch import: a cold query costs less than ``import torch``)."""
    from pipeline.device import resolve_device

    return resolve_device(device) == "cpu"


class MeanPooledBert:
    """Tokenizer + BERT + attention-masked mean pooling: sentence-transformers' ``encode`` without it.

    On the CPU the forward pass is NumPy; on another device (``cuda``) it is torch.
    """

    def __init__(self, model_dir: str | Path, device: str = "cpu") -> None:
        model_dir = Path(model_dir)
        config = _read_json(model_dir / "config.json")
        if config.get("model_type", "bert") != "bert":
            raise ValueError(f"expected a BERT checkpoint, got model_type {config.get('model_type')!r}")
        self.dim = int(config["hidden_size"])
        self.tokenizer = load_tokenizer(model_dir, max_seq_length(model_dir, config))
        self.config = config
        self.numpy = use_numpy(device)
        self.precision = requested("auto")  # a bad OSCAR_PRECISION fails the load, not the first batch
        self._cpu_torch: dict | None = None  # the NumPy weights as torch tensors, built on the first batch
        if self.numpy:
            from safetensors.numpy import load_file

            raw = load_file(str(model_dir / "model.safetensors"))
            self.weights = {k.removeprefix("bert."): np.asarray(v, np.float32) for k, v in raw.items()}
        else:
            import torch

            from pipeline.device import resolve_device

            self.device = torch.device(resolve_device(device))
            self.weights = {k: v.to(self.device) for k, v in load_weights(model_dir).items()}

    def _batch(self, texts: list[str]) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        enc = self.tokenizer.encode_batch(texts)
        return tuple(
            np.asarray([getattr(e, f) for e in enc], np.int64) for f in ("ids", "type_ids", "attention_mask")
        )

    def _torch_weights(self, n_texts: int) -> dict | None:
        """The weights to run ``n_texts`` texts through torch with, or None for NumPy."""
        if not self.numpy:
            return self.weights
        if n_texts < TORCH_MIN_TEXTS or "torch" not in sys.modules:
            return None  # a process without torch (a descriptor-only query, a Ray text actor) never loads it
        if self._cpu_torch is None:
            import torch

            dtype = torch.bfloat16 if use_bf16(self.precision, torch.device("cpu")) else torch.float32
            self._cpu_torch = {k: torch.from_numpy(v).to(dtype) for k, v in self.weights.items()}
        return self._cpu_torch

    def encode(self, texts: list[str], batch_size: int = 64) -> np.ndarray:
        """(n, dim) float32 mean-pooled vectors (not normalised), batched in input order."""
        out = []
        weights = self._torch_weights(len(texts))
        for i in range(0, len(texts), max(1, batch_size)):
            ids, types, mask = self._batch(texts[i : i + batch_size])
            if weights is None:
                hidden = bert_forward_numpy(self.weights, self.config, ids, types, mask)
                m = mask[:, :, None].astype(np.float32)
                out.append((hidden * m).sum(1) / np.maximum(m.sum(1), np.float32(1e-9)))
                continue
            import torch

            device = torch.device("cpu") if self.numpy else self.device
            ids, types, mask = (torch.from_numpy(a).to(device) for a in (ids, types, mask))
            with torch.inference_mode():
                hidden = bert_forward(weights, self.config, ids, types, mask).float()
                m = mask[:, :, None].to(hidden.dtype)
                pooled = (hidden * m).sum(1) / m.sum(1).clamp(min=1e-9)
            out.append(pooled.cpu().numpy())
        return np.concatenate(out).astype(np.float32) if out else np.zeros((0, self.dim), np.float32)
