"""Fusion of the learned view encoder with the descriptor and text scores (pipeline/query/fusion.py) and its
wiring in the Retriever, on hand-made stores with fake adapters."""

from __future__ import annotations

import numpy as np
import pytest
from query_helpers import AspectEncoder, fake_models, make_fake_store, object_image

from pipeline.query import QueryError, Retriever
from pipeline.query.fusion import FusionWeights, fuse
from pipeline.query.steps.text_terms import best_per_model


def test_fuse_is_a_weighted_mean_of_cosines():
    w = FusionWeights(desc=0.2, text=0.3)
    assert w.learned == pytest.approx(0.5)
    got = fuse(np.array([0.8, 0.2]), np.array([0.5, 0.9]), np.array([0.6, 0.6]), w)
    np.testing.assert_allclose(got, [0.5 * 0.8 + 0.2 * 0.5 + 0.3 * 0.6, 0.5 * 0.2 + 0.2 * 0.9 + 0.3 * 0.6])
    # image-only (no text): the two image weights are rescaled to sum to 1
    np.testing.assert_allclose(fuse(np.array([1.0]), np.array([0.0]), None, w), [0.5 / 0.7], rtol=1e-6)
    # a model without views of one kind ranks last
    assert fuse(np.array([-np.inf]), np.array([0.9]), np.array([0.5]), w)[0] == -np.inf


def test_fuse_weighs_the_roi_caption_and_the_prompt_apart():
    w = FusionWeights(desc=0.2, text=0.1, prompt=0.3)
    assert w.learned == pytest.approx(0.4)
    learned, desc, text, prompt = np.array([0.8]), np.array([0.5]), np.array([0.6]), np.array([0.9])
    got = fuse(learned, desc, text, w, prompt)
    np.testing.assert_allclose(got, [0.4 * 0.8 + 0.2 * 0.5 + 0.1 * 0.6 + 0.3 * 0.9], rtol=1e-6)
    # without the prompt's own score the one text score takes both text weights
    np.testing.assert_allclose(fuse(learned, desc, text, w), [0.4 * 0.8 + 0.2 * 0.5 + 0.4 * 0.6], rtol=1e-6)


@pytest.mark.parametrize(
    "desc,text,prompt", [(-0.1, 0.2, 0.0), (0.6, 0.5, 0.0), (0.2, 1.2, 0.0), (0.5, 0.2, 0.4)]
)
def test_fusion_weights_are_checked(desc, text, prompt):
    with pytest.raises(ValueError, match="fusion weights"):
        FusionWeights(desc, text, prompt)


@pytest.fixture(scope="module")
def learned_store(tmp_path_factory):
    """The fake library with learned (aspect-only) view vectors as well."""
    return make_fake_store(tmp_path_factory.mktemp("fusion") / "store", learned=AspectEncoder())


def models_with_learned():
    return {**fake_models(), "learned_encoder": AspectEncoder()}


def photo(colour, w, h):
    img = object_image(colour, w, h, pad=30)
    return img, np.abs(np.asarray(img, np.int16) - 205).sum(axis=2) > 30


def test_query_fuses_learned_descriptor_and_text(learned_store):
    img, mask = photo("red", 44, 52)
    with Retriever.open(learned_store, models=models_with_learned(), use_cache=False) as r:
        assert r.learned is not None and "learned_encoder" in r.required_roles()
        res = r.query(img, "the red can", mask=mask, top=4)
        s, w = r.settings, FusionWeights.of(r.settings)
        assert w.prompt > 0 and w.text > 0  # the offline profile weighs the two text terms apart
        emb = r.embed(r.make_roi(img, "the red can", mask=mask), "the red can")
        text = best_per_model(r.text_filter, emb.text_space, r.n_meshes)
        prompt = best_per_model(r.text_filter, emb.prompt_vec, r.n_meshes)
        index = {m: j for j, m in enumerate(r.mesh_ids)}
        for c in res.candidates:
            assert c.learned_score is not None
            j = index[c.mesh_id]
            want = w.learned * c.learned_score + s.fuse_desc * c.image_score
            want += w.text * text[j] + w.prompt * prompt[j]
            assert c.score == pytest.approx(want, abs=1e-5)
            # stage 1's blended score is the best caption's weighted mean of the two: never above both
            assert c.text_score <= max(text[j], prompt[j]) + 1e-6
        scores = [c.score for c in res.candidates]
        assert scores == sorted(scores, reverse=True)
        assert res.candidates[0].name == "red_can"
        assert res.query["embedding"]["learned_dim"] == 3


def test_weights_move_the_order(learned_store):
    """The aspect-only learned encoder cannot tell the red from the green can; with the descriptor's weight
    at 0 and no text the two cans tie on the learned score, with it the red can wins clearly."""
    img, mask = photo("red", 40, 50)
    with Retriever.open(
        learned_store,
        models=models_with_learned(),
        use_cache=False,
        settings_changes={"fuse_desc": 0.0, "fuse_text": 0.0, "fuse_prompt": 0.0},
    ) as r:
        res = r.query(img, "a can", mask=mask, top=4)
        cans = {c.name: c.score for c in res.candidates if c.name.endswith("_can")}
        assert cans["red_can"] == pytest.approx(cans["green_can"], abs=1e-5)
    with Retriever.open(
        learned_store,
        models=models_with_learned(),
        use_cache=False,
        settings_changes={"fuse_desc": 0.5, "fuse_text": 0.0, "fuse_prompt": 0.0},
    ) as r:
        res = r.query(img, "a can", mask=mask, top=4)
        cans = {c.name: c.score for c in res.candidates if c.name.endswith("_can")}
        assert res.candidates[0].name == "red_can" and cans["red_can"] - cans["green_can"] > 0.01


def test_bad_fusion_weights_are_a_query_error(learned_store):
    img, mask = photo("red", 40, 50)
    with Retriever.open(
        learned_store, models=models_with_learned(), use_cache=False, settings_changes={"fuse_desc": 0.95}
    ) as r:
        with pytest.raises(QueryError, match="fusion weights"):
            r.query(img, "a can", mask=mask)


def test_store_without_learned_embeddings_ranks_by_the_descriptor(tmp_path):
    store = make_fake_store(tmp_path / "plain")
    img, mask = photo("red", 44, 52)
    with Retriever.open(store, models=fake_models(), use_cache=False) as r:
        assert r.learned is None and "learned_encoder" not in r.required_roles()
        res = r.query(img, "the red can", mask=mask)
        assert all(c.learned_score is None for c in res.candidates)
        assert res.candidates[0].name == "red_can"


def test_query_can_drop_the_learned_encoder(learned_store):
    img, mask = photo("red", 44, 52)
    with Retriever.open(
        learned_store, model_overrides={"learned_encoder": "none"}, models=fake_models(), use_cache=False
    ) as r:
        assert r.learned is None
        res = r.query(img, "the red can", mask=mask)
        assert all(c.learned_score is None and c.score is None for c in res.candidates)


def test_other_learned_encoder_than_the_store_is_one_line(learned_store, tmp_path):
    with pytest.raises(QueryError, match="learned_encoder") as exc:
        Retriever.open(
            learned_store,
            model_overrides={"learned_encoder": str(tmp_path)},
            models=models_with_learned(),
            use_cache=False,
        )
    assert "\n" not in str(exc.value)


def test_a_large_library_keeps_the_tau_cut_when_fusing(learned_store):
    """Fusing ranks every model only up to fuse_all_max_models; past it stage 1's tau cut (or its top-k
    fallback) makes the shortlist, which is then fused."""
    img, mask = photo("red", 44, 52)
    with Retriever.open(learned_store, models=models_with_learned(), use_cache=False) as r:
        n = r.n_meshes
        every = r.query(img, "the red can", mask=mask, top=n, threshold=1.5)
        assert len(every.candidates) == n and not every.used_fallback  # all fused, tau is no cut
    changes = {"fuse_all_max_models": n - 1}
    with Retriever.open(
        learned_store, models=models_with_learned(), use_cache=False, settings_changes=changes
    ) as r:
        cut = r.query(
            img, "the red can", mask=mask, top=n, threshold=1.5, fallback_k=2, fallback_unit="meshes"
        )
        assert cut.used_fallback and len(cut.candidates) == 2  # nothing passes tau 1.5: the top-2 fallback
        w = FusionWeights.of(r.settings)
        c = cut.candidates[0]
        want = w.learned * c.learned_score + w.desc * c.image_score
        # still fused; the text terms are not computed past the bound: stage 1's score takes both weights
        assert c.score == pytest.approx(want + (w.text + w.prompt) * c.text_score, abs=1e-5)


def test_without_the_prompt_its_weight_goes_to_the_roi_caption(learned_store):
    img, mask = photo("red", 44, 52)
    with Retriever.open(learned_store, models=models_with_learned(), use_cache=False) as r:
        emb = r.embed(r.make_roi(img, "the red can", mask=mask), "the red can")
        res = r.rank(emb, "two-stage", top=4, prompt_weight=0.0, verify=False)
        w = FusionWeights.of(r.settings)
        text = best_per_model(r.text_filter, emb.text_space, r.n_meshes)
        index = {m: j for j, m in enumerate(r.mesh_ids)}
        for c in res.candidates:
            want = (
                w.learned * c.learned_score
                + w.desc * c.image_score
                + (w.text + w.prompt) * text[index[c.mesh_id]]
            )
            assert c.score == pytest.approx(want, abs=1e-5)
