"""The captioning prompts are the paper's, byte for byte, and changing a prompt re-captions only."""

from __future__ import annotations

import pytest

from pipeline import profiles

# Copied verbatim from the paper's prompt table (as quoted in the design brief, DESIGN.md).
PAPER_PROMPTS = {
    "blind": "Imagine you're describing the object to a blind person. Be extremely detailed about the object's appearance, colors, shape, material, any text or logos, and any unique markings.",  # noqa: E501
    "comma": "Describe the object in a comma-separated list, focusing on its visual appearance, color, material, and any visible text or brand names. Be concise.",  # noqa: E501
    "caption": "Write a detailed visual caption of the image, mentioning colors, materials, brand names, and visible labels.",  # noqa: E501
    "attributes": "Extract visual attributes of the main object in the image: object type, brand name, color, material, and label text.",  # noqa: E501
}


def test_prompt_texts_are_the_papers_byte_for_byte():
    assert set(profiles.PROMPT_STYLES) == set(PAPER_PROMPTS)
    for style, text in PAPER_PROMPTS.items():
        assert profiles.PROMPT_STYLES[style].encode() == text.encode(), style
    assert profiles.DEFAULT_PROMPT_STYLE == "attributes"  # the reference scripts' prompt


def test_prompt_text_is_in_the_caption_fingerprint_only():
    from pipeline.onboard.config import OnboardConfig

    cfg = OnboardConfig(profile="paper")
    old = cfg.fingerprints()
    patched = dict(profiles.PROMPT_STYLES, attributes="What is this?")
    with pytest.MonkeyPatch.context() as mp:
        mp.setattr("pipeline.onboard.config.PROMPT_STYLES", patched)
        new = cfg.fingerprints()
        assert cfg.prompt == "What is this?"
    assert new["render"] == old["render"]
    assert all(new[k] == old[k] for k in old if k.startswith("embed_image"))
    assert new["caption"] != old["caption"] and new["embed_text"] != old["embed_text"]


def test_store_captioned_with_an_old_prompt_is_recaptioned_not_rerendered(tmp_path, offline_models):
    from conftest import copy_ycb
    from onboard_helpers import onboard

    from pipeline.store import Store

    lib = copy_ycb(tmp_path / "lib", ["061_foam_brick"])
    store = tmp_path / "store"
    old = dict(profiles.PROMPT_STYLES, attributes="Describe the object in the image.")  # a pre-fix prompt
    with pytest.MonkeyPatch.context() as mp:
        mp.setattr("pipeline.onboard.config.PROMPT_STYLES", old)
        first = onboard(lib, store, offline_models)
    assert first.rendered == 1 and first.captioned == 1
    s = Store.open(store)
    views_before = s.read("views").num_rows
    assert set(s.read("captions").column("prompt").to_pylist()) == {old["attributes"]}

    second = onboard(lib, store, offline_models)  # the paper's prompt now
    assert second.rendered == 0 and second.captioned == 1
    s = Store.open(store)
    assert s.read("views").num_rows == views_before
    latest = s.read_latest("captions")
    assert PAPER_PROMPTS["attributes"] in set(latest.column("prompt").to_pylist())
