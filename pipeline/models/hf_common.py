"""Shared plumbing of the Hugging Face adapters: device/dtype choice, loading with one-line errors, batching.

Heavy imports (torch, transformers) happen inside functions only, so importing this module is cheap.
"""

from __future__ import annotations

import inspect
import os
import re
import socket
from collections.abc import Callable, Iterator, Sequence
from contextlib import contextmanager
from typing import Any, TypeVar

from PIL import Image

from pipeline.models.registry import ModelLoadError, register

T = TypeVar("T")

_TRUE = {"1", "true", "yes", "on"}
_HUB_ID = re.compile(r"^[A-Za-z0-9][\w.-]*(/[\w.-]+)?$")
_DTYPES = {
    "float32": "float32",
    "fp32": "float32",
    "float": "float32",
    "bfloat16": "bfloat16",
    "bf16": "bfloat16",
    "float16": "float16",
    "fp16": "float16",
    "half": "float16",
}


def offline_default() -> bool:
    """``local_files_only`` default: true when the Hugging Face offline switches are set."""
    return any(
        os.environ.get(k, "").strip().lower() in _TRUE for k in ("HF_HUB_OFFLINE", "TRANSFORMERS_OFFLINE")
    )


def resolve_device(device: str | None = "auto") -> Any:
    """``"auto"`` -> cuda if available else cpu; anything else is passed to ``torch.device``."""
    import torch

    if device in (None, "", "auto"):
        return torch.device("cuda" if torch.cuda.is_available() else "cpu")
    return torch.device(device)


def resolve_dtype(dtype: Any, device: Any, gpu_default: str = "bfloat16") -> Any:
    """``"auto"`` -> ``gpu_default`` on a GPU, float32 on CPU; names like "bf16"/"float16" or torch dtypes."""
    import torch

    if isinstance(dtype, torch.dtype):
        return dtype
    name = str(dtype or "auto").strip().lower().removeprefix("torch.")
    if name == "auto":
        name = gpu_default if device.type == "cuda" else "float32"
    if name not in _DTYPES:
        raise ModelLoadError(f"unknown dtype {dtype!r}; use auto, float32, bfloat16 or float16")
    return getattr(torch, _DTYPES[name])


def dtype_kwargs(dtype: Any) -> dict[str, Any]:
    """``from_pretrained`` keyword for the weights' dtype (``dtype`` in transformers 5, ``torch_dtype`` before)."""
    import transformers

    major = int(transformers.__version__.split(".", 1)[0])
    return {"dtype": dtype} if major >= 5 else {"torch_dtype": dtype}


@contextmanager
def quiet_transformers() -> Iterator[None]:
    """Silence transformers' load reports (e.g. the unused half of a CLIP checkpoint) while loading."""
    from huggingface_hub.utils import logging as hub_logging
    from transformers.utils import logging as hf_logging

    levels = hf_logging.get_verbosity(), hub_logging.get_verbosity()
    hf_logging.set_verbosity_error()
    hub_logging.set_verbosity_error()  # its "Retrying in 1s" lines while the network is down
    try:
        yield
    finally:
        hf_logging.set_verbosity(levels[0])
        hub_logging.set_verbosity(levels[1])


def hub_reachable(timeout: float = 3.0) -> bool:
    """Quick TCP probe of the hub endpoint, so a machine without network fails fast instead of retrying.

    Behind a proxy the probe is skipped (assumed reachable) and the hub client decides.
    """
    if any(os.environ.get(k) for k in ("HTTPS_PROXY", "https_proxy", "ALL_PROXY", "all_proxy")):
        return True
    from urllib.parse import urlparse

    from huggingface_hub import constants

    url = urlparse(constants.ENDPOINT)
    port = url.port or (443 if url.scheme == "https" else 80)
    try:
        with socket.create_connection((url.hostname or "huggingface.co", port), timeout=timeout):
            return True
    except OSError:
        return False


def _looks_like_path(model_id: str) -> bool:
    return model_id.startswith((".", "/", "~", os.sep, "\\")) or not _HUB_ID.match(model_id)


def _exception_chain(exc: BaseException) -> list[BaseException]:
    chain, seen = [], set()
    cur: BaseException | None = exc
    while cur is not None and id(cur) not in seen:
        seen.add(id(cur))
        chain.append(cur)
        cur = cur.__cause__ or cur.__context__
    return chain


def _reason(exc: BaseException, local_only: bool) -> str:
    names = {type(e).__name__ for e in _exception_chain(exc)}
    text = " ".join(str(exc).split())
    if names & {"RepositoryNotFoundError", "GatedRepoError", "RevisionNotFoundError"}:
        return "not found on the Hugging Face hub, or gated/private"
    offline_markers = {"LocalEntryNotFoundError", "OfflineModeIsEnabled", "ConnectError", "ConnectionError"}
    if names & offline_markers or "couldn't connect" in text.lower() or "local_files_only" in text:
        if local_only:
            return "not in the local Hugging Face cache and offline mode is on"
        return "not found locally and no network"
    if len(text) > 200:
        text = text[:197] + "..."
    return f"{type(exc).__name__}: {text}" if text else type(exc).__name__


def _hint(role: str) -> str:
    return f"pass a local directory with --model {role}=DIR, or use --profile offline"


def load_pretrained(
    role: str, model_id: str, loader: Callable[[str, bool], T], local_files_only: bool | None
) -> T:
    """Run ``loader(source, local_files_only)``; turn any failure into a one-line :class:`ModelLoadError`.

    A local directory is loaded as is. A hub id is tried from the local cache first and, unless
    ``local_files_only``, then from the network.
    """
    local_only = offline_default() if local_files_only is None else bool(local_files_only)
    model_id = str(model_id)
    path = os.path.expanduser(model_id)
    if os.path.isdir(path):
        attempts = [(path, True)]
    elif _looks_like_path(model_id) or os.path.exists(path):
        raise ModelLoadError(f"cannot load {role} {model_id!r} (no such model directory): {_hint(role)}")
    else:
        attempts = [(model_id, True)] + ([] if local_only else [(model_id, False)])
    last: BaseException | None = None
    reason = None
    for source, lfo in attempts:
        if not lfo and not hub_reachable():
            reason = "not found locally and no network"
            break
        try:
            with quiet_transformers():
                return loader(source, lfo)
        except ModelLoadError:
            raise
        except (KeyboardInterrupt, SystemExit):
            raise
        except Exception as exc:  # noqa: BLE001 - every load failure becomes one clear line
            last = exc
    assert last is not None
    reason = reason or _reason(last, local_only)
    raise ModelLoadError(f"cannot load {role} {model_id!r} ({reason}): {_hint(role)}") from last


def register_adapter(cls: type, *pairs: tuple[str, str]) -> type:
    """Register ``cls`` as ``factory(model_id, **options)`` for each (role, backend) pair.

    Unknown options are a :class:`ModelLoadError` naming the accepted ones (never a raw ``TypeError``).
    """
    accepted: list[str] = []
    for klass in cls.__mro__:
        if "__init__" in vars(klass) and klass is not object:
            for name, param in inspect.signature(klass.__init__).parameters.items():
                plain = param.kind not in (param.VAR_KEYWORD, param.VAR_POSITIONAL)
                if plain and name not in ("self", "model_id", "role") and name not in accepted:
                    accepted.append(name)

    for role, backend in pairs:

        def factory(model_id: str, _role: str = role, _backend: str = backend, **options: Any) -> Any:
            unknown = sorted(set(options) - set(accepted))
            if unknown:
                raise ModelLoadError(
                    f"unknown option(s) {', '.join(unknown)} for {_role} backend {_backend!r}; "
                    f"accepted: {', '.join(accepted)}"
                )
            return cls(model_id, role=_role, **options)

        factory.__name__ = f"create_{backend}_{role}"
        register(role, backend)(factory)
    return cls


def rgb(images: Sequence[Image.Image]) -> list[Image.Image]:
    return [im if im.mode == "RGB" else im.convert("RGB") for im in images]


def batched(items: Sequence[T], size: int) -> Iterator[Sequence[T]]:
    size = max(1, int(size))
    for i in range(0, len(items), size):
        yield items[i : i + size]


def move_inputs(batch: Any, device: Any, dtype: Any = None, keep_fp32: Sequence[str] = ()) -> dict[str, Any]:
    """Tensors to ``device``; floating tensors also to ``dtype`` (except the keys in ``keep_fp32``)."""
    import torch

    out: dict[str, Any] = {}
    for key, value in dict(batch).items():
        if isinstance(value, torch.Tensor):
            value = value.to(device)
            if dtype is not None and value.is_floating_point() and key not in keep_fp32:
                value = value.to(dtype)
        out[key] = value
    return out


class HFAdapter:
    """Common constructor arguments of every Hugging Face adapter."""

    #: dtype that ``dtype="auto"`` picks on a GPU (float32 on CPU)
    gpu_dtype = "bfloat16"
    default_batch_size = 16

    def __init__(
        self,
        model_id: str,
        *,
        role: str,
        device: str | None = "auto",
        dtype: Any = "auto",
        batch_size: int | None = None,
        local_files_only: bool | None = None,
    ) -> None:
        self.model_id = str(model_id)
        self.role = role
        self.device = resolve_device(device)
        self.dtype = resolve_dtype(dtype, self.device, self.gpu_dtype)
        self.batch_size = int(batch_size or self.default_batch_size)
        self.local_files_only = local_files_only

    def _load(self, loader: Callable[[str, bool], T]) -> T:
        return load_pretrained(self.role, self.model_id, loader, self.local_files_only)

    def _place(self, model: Any) -> Any:
        return model.to(self.device).eval()

    def __repr__(self) -> str:
        return f"{type(self).__name__}({self.model_id!r}, device={self.device}, dtype={self.dtype})"
