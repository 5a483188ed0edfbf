"""A BERT encoder in plain torch for sentence-transformers checkpoints (all-MiniLM-L6-v2 and kin).

Why not ``sentence_transformers``: importing it pulls in transformers, torch.distributed, sklearn and scipy,
which cost a cold ``python -m pipeline.query`` several times a bare ``import torch``. A BERT forward pass
is six small layers; this module reads the same ``model.safetensors``, ``config.json`` and
``tokenizer.json`` (with the ``tokenizers`` library) and computes the same mean-pooled vectors
(``tests/test_minilm_equivalence.py`` checks them against sentence-transformers to 1e-5), so stores
embedded by either stay valid.
"""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np

#: sentence-transformers' default when ``sentence_bert_config.json`` is absent
DEFAULT_MAX_SEQ_LENGTH = 256


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


def build_bert(model_dir: Path, config: dict):
    """A ``torch.nn.Module`` with BERT's layers, weights loaded from ``model.safetensors`` (eval mode)."""
    import torch
    from safetensors.torch import load_file

    class Layer(torch.nn.Module):
        def __init__(self, h: int, inter: int, heads: int, eps: float) -> None:
            super().__init__()
            self.heads = heads
            self.q, self.k, self.v = (torch.nn.Linear(h, h) for _ in range(3))
            self.attn_out, self.attn_norm = torch.nn.Linear(h, h), torch.nn.LayerNorm(h, eps=eps)
            self.up, self.down = torch.nn.Linear(h, inter), torch.nn.Linear(inter, h)
            self.out_norm = torch.nn.LayerNorm(h, eps=eps)

        def forward(self, x, keep):  # keep: (B, 1, 1, T) bool, True = a real token
            b, t, h = x.shape

            def split(z):
                return z.view(b, t, self.heads, h // self.heads).transpose(1, 2)

            a = torch.nn.functional.scaled_dot_product_attention(
                split(self.q(x)), split(self.k(x)), split(self.v(x)), attn_mask=keep
            )
            x = self.attn_norm(x + self.attn_out(a.transpose(1, 2).reshape(b, t, h)))
            return self.out_norm(x + self.down(torch.nn.functional.gelu(self.up(x))))

    class Bert(torch.nn.Module):
        def __init__(self, c: dict) -> None:
            super().__init__()
            h, eps = c["hidden_size"], c.get("layer_norm_eps", 1e-12)
            self.word = torch.nn.Embedding(c["vocab_size"], h)
            self.position = torch.nn.Embedding(c["max_position_embeddings"], h)
            self.token_type = torch.nn.Embedding(c.get("type_vocab_size", 2), h)
            self.norm = torch.nn.LayerNorm(h, eps=eps)
            self.layers = torch.nn.ModuleList(
                Layer(h, c["intermediate_size"], c["num_attention_heads"], eps)
                for _ in range(c["num_hidden_layers"])
            )

        def forward(self, ids, type_ids, mask):
            pos = torch.arange(ids.shape[1], device=ids.device)[None, :]
            x = self.norm(self.word(ids) + self.position(pos) + self.token_type(type_ids))
            keep = mask.bool()[:, None, None, :]
            for layer in self.layers:
                x = layer(x, keep)
            return x

    model = Bert(config)
    model.load_state_dict(_rename(load_file(str(model_dir / "model.safetensors"))), strict=True)
    return model.eval()


def _rename(weights: dict) -> dict:
    """Hugging Face BERT parameter names -> this module's names (pooler and buffers dropped)."""
    table = {
        "attention.self.query": "q",
        "attention.self.key": "k",
        "attention.self.value": "v",
        "attention.output.dense": "attn_out",
        "attention.output.LayerNorm": "attn_norm",
        "intermediate.dense": "up",
        "output.dense": "down",
        "output.LayerNorm": "out_norm",
    }
    top = {
        "embeddings.word_embeddings": "word",
        "embeddings.position_embeddings": "position",
        "embeddings.token_type_embeddings": "token_type",
        "embeddings.LayerNorm": "norm",
    }
    out = {}
    for name, tensor in weights.items():
        name = name.removeprefix("bert.")
        stem, _, leaf = name.rpartition(".")
        if stem in top:
            out[f"{top[stem]}.{leaf}"] = tensor
        elif name.startswith("encoder.layer."):
            n, rest = name[len("encoder.layer.") :].split(".", 1)
            stem, _, leaf = rest.rpartition(".")
            out[f"layers.{n}.{table[stem]}.{leaf}"] = tensor
    return out


class MeanPooledBert:
    """Tokenizer + BERT + attention-masked mean pooling: sentence-transformers' ``encode`` without it."""

    def __init__(self, model_dir: str | Path, device: str = "cpu") -> None:
        import torch

        model_dir = Path(model_dir)
        config = _read_json(model_dir / "config.json")
        if config.get("model_type", "bert") != "bert":
            raise ValueError(f"expected a BERT checkpoint, got model_type {config.get('model_type')!r}")
        self.dim = int(config["hidden_size"])
        self.tokenizer = load_tokenizer(model_dir, max_seq_length(model_dir, config))
        self.device = torch.device(device)
        self.model = build_bert(model_dir, config).to(self.device)

    def encode(self, texts: list[str], batch_size: int = 64) -> np.ndarray:
        """(n, dim) float32 mean-pooled vectors (not normalised), batched in input order."""
        import torch

        out = []
        for i in range(0, len(texts), max(1, batch_size)):
            enc = self.tokenizer.encode_batch(texts[i : i + batch_size])

            def tensor(field: str, enc=enc):
                return torch.tensor([getattr(e, field) for e in enc], dtype=torch.long, device=self.device)

            ids, types, mask = tensor("ids"), tensor("type_ids"), tensor("attention_mask")
            with torch.inference_mode():
                hidden = self.model(ids, types, mask)
                m = mask[:, :, None].to(hidden.dtype)
                pooled = (hidden * m).sum(1) / m.sum(1).clamp(min=1e-9)
            out.append(pooled.float().cpu().numpy())
        return np.concatenate(out) if out else np.zeros((0, self.dim), np.float32)
