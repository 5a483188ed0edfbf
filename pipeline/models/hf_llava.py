"""Hugging Face LLaVA captioner (the paper's LLaVA-v1.5-7B: ``llava-hf/llava-1.5-7b-hf``)."""

from __future__ import annotations

from typing import Any

from PIL import Image

from pipeline.models.hf_common import HFAdapter, batched, dtype_kwargs, move_inputs, register_adapter, rgb

#: prompt format of llava-1.5 when the processor ships no chat template
FALLBACK_TEMPLATE = "USER: <image>\n{prompt} ASSISTANT:"


class LlavaCaptioner(HFAdapter):
    """Greedy, batched LLaVA captions; returns only the generated text, stripped."""

    gpu_dtype = "float16"  # the reference scripts run llava-1.5-7b in fp16
    default_batch_size = 8

    def __init__(
        self, model_id: str, *, role: str = "captioner", max_new_tokens: int = 100, **common: Any
    ) -> None:
        super().__init__(model_id, role=role, **common)
        self.max_new_tokens = int(max_new_tokens)

        def load(source: str, local_files_only: bool) -> tuple[Any, Any]:
            from transformers import AutoProcessor, LlavaForConditionalGeneration

            model = LlavaForConditionalGeneration.from_pretrained(
                source, local_files_only=local_files_only, **dtype_kwargs(self.dtype)
            )
            processor = AutoProcessor.from_pretrained(source, local_files_only=local_files_only)
            return model, processor

        model, self.processor = self._load(load)
        self.model = self._place(model)
        tok = self.processor.tokenizer
        tok.padding_side = "left"  # decoder-only batched generation pads on the left
        if tok.pad_token is None:
            tok.pad_token = tok.eos_token
        self._pad_id = tok.pad_token_id

    def format_prompt(self, prompt: str) -> str:
        """The full text fed to the model: the processor's chat template, else llava-1.5's format."""
        if getattr(self.processor, "chat_template", None):
            conversation = [
                {"role": "user", "content": [{"type": "image"}, {"type": "text", "text": prompt}]}
            ]
            return self.processor.apply_chat_template(conversation, add_generation_prompt=True)
        return FALLBACK_TEMPLATE.format(prompt=prompt)

    def caption(self, images: list[Image.Image], prompt: str) -> list[str]:
        import torch

        text = self.format_prompt(prompt)
        captions: list[str] = []
        for chunk in batched(list(images), self.batch_size):
            enc = self.processor(
                images=rgb(chunk), text=[text] * len(chunk), padding=True, return_tensors="pt"
            )
            inputs = move_inputs(enc, self.device, self.dtype)
            with torch.inference_mode():
                ids = self.model.generate(
                    **inputs,
                    max_new_tokens=self.max_new_tokens,
                    do_sample=False,
                    num_beams=1,
                    pad_token_id=self._pad_id,
                )
            new_tokens = ids[:, inputs["input_ids"].shape[1] :]
            captions.extend(
                s.strip() for s in self.processor.batch_decode(new_tokens, skip_special_tokens=True)
            )
        return captions


register_adapter(LlavaCaptioner, ("captioner", "llava"))
