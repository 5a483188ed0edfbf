"""Hugging Face GroundedSAM parts: GroundingDINO box detector and box-prompted SAM segmenter."""

from __future__ import annotations

import inspect
from typing import Any

import numpy as np
from PIL import Image

from pipeline.models.hf_common import HFAdapter, dtype_kwargs, move_inputs, register_adapter

Box = tuple[float, float, float, float]


def grounding_prompt(prompt: str) -> str:
    """GroundingDINO expects lower-case phrases each ending with a dot."""
    text = " ".join(str(prompt).split()).lower()
    return text if text.endswith(".") else text + "."


class GroundingDinoDetector(HFAdapter):
    """Open-vocabulary boxes for a text prompt, best first, clipped to the image."""

    # Detection thresholds are calibrated in fp32 and the model is small: fp32 unless asked otherwise.
    gpu_dtype = "float32"

    def __init__(
        self,
        model_id: str,
        *,
        role: str = "detector",
        box_threshold: float = 0.3,
        text_threshold: float = 0.25,
        **common: Any,
    ) -> None:
        super().__init__(model_id, role=role, **common)
        self.box_threshold = float(box_threshold)
        self.text_threshold = float(text_threshold)

        def load(source: str, local_files_only: bool) -> tuple[Any, Any]:
            from transformers import AutoModelForZeroShotObjectDetection, AutoProcessor

            model = AutoModelForZeroShotObjectDetection.from_pretrained(
                source, local_files_only=local_files_only, **dtype_kwargs(self.dtype)
            )
            processor = AutoProcessor.from_pretrained(source, local_files_only=local_files_only)
            return model, processor

        model, self.processor = self._load(load)
        self.model = self._place(model)
        # transformers 5 names the box threshold ``threshold``; 4.x called it ``box_threshold``
        params = inspect.signature(self.processor.post_process_grounded_object_detection).parameters
        self._box_kw = "threshold" if "threshold" in params else "box_threshold"

    def detect(self, image: Image.Image, prompt: str) -> list[tuple[Box, float]]:
        import torch

        image = image.convert("RGB") if image.mode != "RGB" else image
        width, height = image.size
        enc = self.processor(images=image, text=grounding_prompt(prompt), return_tensors="pt")
        inputs = move_inputs(enc, self.device, self.dtype)
        with torch.inference_mode():
            outputs = self.model(**inputs)
        outputs.logits = outputs.logits.float()
        outputs.pred_boxes = outputs.pred_boxes.float()
        result = self.processor.post_process_grounded_object_detection(
            outputs,
            inputs["input_ids"],
            text_threshold=self.text_threshold,
            target_sizes=[(height, width)],
            **{self._box_kw: self.box_threshold},
        )[0]
        boxes = result["boxes"].cpu().numpy().astype(float)
        scores = result["scores"].cpu().numpy().astype(float)
        found: list[tuple[Box, float]] = []
        for (x0, y0, x1, y1), score in zip(boxes, scores, strict=True):
            x0, x1 = sorted((min(max(x0, 0.0), width), min(max(x1, 0.0), width)))
            y0, y1 = sorted((min(max(y0, 0.0), height), min(max(y1, 0.0), height)))
            found.append(((x0, y0, x1, y1), float(score)))
        found.sort(key=lambda item: -item[1])
        return found


class SamSegmenter(HFAdapter):
    """SAM with a box prompt: the best (by predicted IoU) of the multimask outputs, at the image's size."""

    gpu_dtype = "float32"  # mask logits are thresholded at 0; keep the reference precision by default

    def __init__(
        self, model_id: str, *, role: str = "segmenter", mask_threshold: float = 0.0, **common: Any
    ) -> None:
        super().__init__(model_id, role=role, **common)
        self.mask_threshold = float(mask_threshold)

        def load(source: str, local_files_only: bool) -> tuple[Any, Any]:
            from transformers import SamModel, SamProcessor

            model = SamModel.from_pretrained(
                source, local_files_only=local_files_only, **dtype_kwargs(self.dtype)
            )
            processor = SamProcessor.from_pretrained(source, local_files_only=local_files_only)
            return model, processor

        model, self.processor = self._load(load)
        self.model = self._place(model)

    def segment(self, image: Image.Image, box: Box) -> np.ndarray:
        import torch

        image = image.convert("RGB") if image.mode != "RGB" else image
        x0, y0, x1, y1 = (float(v) for v in box)
        enc = self.processor(images=image, input_boxes=[[[x0, y0, x1, y1]]], return_tensors="pt")
        inputs = move_inputs(enc, self.device, self.dtype)
        with torch.inference_mode():
            out = self.model(
                pixel_values=inputs["pixel_values"], input_boxes=inputs["input_boxes"], multimask_output=True
            )
        masks = self.processor.image_processor.post_process_masks(
            out.pred_masks.float().cpu(),
            enc["original_sizes"],
            enc["reshaped_input_sizes"],
            mask_threshold=self.mask_threshold,
        )[0]  # (boxes, masks, H, W)
        best = int(out.iou_scores[0, 0].float().argmax())
        return np.asarray(masks[0, best].cpu().numpy(), dtype=bool)


register_adapter(GroundingDinoDetector, ("detector", "grounding_dino"))
register_adapter(SamSegmenter, ("segmenter", "sam"))
