"""Every audit of sql/audit/ against hand-made rows that must, and must not, be returned."""

from __future__ import annotations

import pytest
from tiny_store import TinyStore

from pipeline.db import audit_names, connect
from pipeline.sql.session import run_audit, set_variables

OLD_RUN = "20240101T000000000000Z-aaaaaa"  # sorts before tiny_store.RUN


def audit(store, name: str, **variables) -> list[dict]:
    con = connect(store)
    set_variables(con, {k: str(v) for k, v in variables.items()})
    columns, rows = run_audit(con, name)
    return [dict(zip(columns, r, strict=True)) for r in rows]


def test_every_audit_has_a_header_comment_and_runs_on_an_empty_store(tmp_path):
    t = TinyStore(tmp_path / "s")
    t.run()
    store = t.commit()
    assert set(audit_names()) == {
        "short_captions",
        "duplicate_captions",
        "captions_missing_colour_or_type",
        "missing_outputs",
        "stale_rows",
        "errors_by_stage",
    }
    for name in audit_names():
        from pipeline.db import load_sql

        assert load_sql(f"audit/{name}").startswith(f"-- Audit {name}:")
        assert audit(store, name) == []


def test_short_captions(tmp_path):
    t = TinyStore(tmp_path / "s")
    t.complete("ok", "A red box-shaped object with a matte surface")
    t.complete("empty", "")
    t.mesh("null")
    t.views("null")
    t.captions("null", [None, "   "])
    t.complete("chars", "blue")
    t.complete("words", "Extraordinarily-colourful")  # 25 characters, 2 words
    t.complete("removed", "x")
    t.mesh("removed", status="removed", run_id="20250101T000000000000Z-zzzzzz")
    t.mesh("stale")
    t.captions("stale", ["x", "x"], fingerprint="c0")  # not the current fingerprint: not audited here
    t.run()
    store = t.commit()
    got = {(r["mesh_id"], r["view_index"]): r["problem"] for r in audit(store, "short_captions")}
    assert got == {
        ("empty", 0): "empty",
        ("empty", 1): "empty",
        ("null", 0): "empty",
        ("null", 1): "empty",
        ("chars", 0): "too few characters",
        ("chars", 1): "too few characters",
        ("words", 0): "too few words",
        ("words", 1): "too few words",
    }
    # thresholds are variables
    strict = {r["mesh_id"] for r in audit(store, "short_captions", audit_min_caption_words=10)}
    assert "ok" in strict
    lax = {
        r["mesh_id"]
        for r in audit(store, "short_captions", audit_min_caption_chars=1, audit_min_caption_words=1)
    }
    assert lax == {"empty", "null"}


def test_duplicate_captions(tmp_path):
    t = TinyStore(tmp_path / "s")
    t.complete("a", "A red box-shaped object")
    t.complete("b", "a  RED box-shaped object ")  # same text up to case and spacing
    t.complete("c", "A blue can")  # both views alike, but one mesh only
    t.complete("d", "A green ball")
    t.complete("e", "")  # empty captions are short_captions' business
    t.complete("f", "")
    t.mesh("gone")
    t.captions("gone", ["A green ball", "A green ball"])
    t.mesh("gone", status="removed", run_id="20250101T000000000000Z-zzzzzz")
    t.run()
    store = t.commit()
    rows = audit(store, "duplicate_captions")
    assert {(r["mesh_id"], r["view_index"]) for r in rows} == {("a", 0), ("a", 1), ("b", 0), ("b", 1)}
    assert {r["n_meshes"] for r in rows} == {2}
    assert {r["caption_key"] for r in rows} == {"a red box-shaped object"}
    assert audit(store, "duplicate_captions", audit_min_duplicate_meshes=3) == []


def test_captions_missing_colour_or_type(tmp_path):
    t = TinyStore(tmp_path / "s")
    cases = {
        "both": ("A red box-shaped object", None),
        "plural": ("Two green bottles side by side", None),
        "neither": ("A shiny thing with a smooth surface", "no colour and no object type"),
        "no_type": ("A blue object, tall and narrow", "no object type"),
        "no_colour": ("A tall bottle with a label", "no colour"),
        "not_words": ("A boxy reddish gadget", "no colour and no object type"),
    }
    for mesh, (caption, _) in cases.items():
        t.complete(mesh, caption)
    t.run()
    store = t.commit()
    got = {r["mesh_id"]: r["problem"] for r in audit(store, "captions_missing_colour_or_type")}
    assert got == {m: p for m, (_, p) in cases.items() if p}


def test_missing_outputs(tmp_path):
    t = TinyStore(tmp_path / "s")
    t.complete("done")
    t.mesh("views_only")
    t.views("views_only")
    t.mesh("one_view")
    t.views("one_view", indices=(0,))
    t.captions("one_view", ["A red box", "A red box"])
    t.embeddings("text_embeddings", "one_view")
    t.embeddings("image_embeddings", "one_view")
    t.mesh("cap_failed")
    t.views("cap_failed")
    t.error("caption", "cap_failed", "captioner ran out of memory", fingerprint="c1")
    t.mesh("render_failed", status="failed")
    t.error("render", "render_failed", "mesh has no faces", fingerprint="r1")
    t.complete("removed")
    t.mesh("removed", status="removed", run_id="20250101T000000000000Z-zzzzzz")
    t.mesh("old_only")
    t.views("old_only", fingerprint="r0")  # rendered under an older config only
    t.run()
    store = t.commit()
    got = {
        (r["mesh_id"], r["stage"]): (r["n_rows"], r["open_error"]) for r in audit(store, "missing_outputs")
    }
    later = ("caption", "embed_text", "embed_image:view_encoder")
    assert got == {
        **{("views_only", s): (0, None) for s in later},
        ("one_view", "render"): (1, None),
        ("cap_failed", "caption"): (0, "captioner ran out of memory"),
        ("cap_failed", "embed_text"): (0, None),
        ("cap_failed", "embed_image:view_encoder"): (0, None),
        **{("old_only", s): (0, None) for s in ("render", *later)},
    }
    assert {r["expected_rows"] for r in audit(store, "missing_outputs")} == {2}


def test_stale_rows(tmp_path):
    t = TinyStore(tmp_path / "s")
    t.complete("fresh")
    t.complete("rerendered")
    t.views("rerendered", fingerprint="r0", run_id=OLD_RUN)  # superseded by the current r1 views
    t.mesh("old_caption")
    t.views("old_caption")
    t.captions("old_caption", ["A red box", "A red box"], fingerprint="c0", run_id=OLD_RUN)
    t.embeddings(
        "text_embeddings", "fresh", fingerprint="t0", encoder_id="clip_text:old", dim=5, run_id=OLD_RUN
    )
    t.run()
    store = t.commit()
    got = {(r["table_name"], r["mesh_id"], r["fingerprint"]): r for r in audit(store, "stale_rows")}
    assert set(got) == {
        ("views", "rerendered", "r0"),
        ("captions", "old_caption", "c0"),
        ("text_embeddings", "fresh", "t0"),
    }
    assert got[("views", "rerendered", "r0")]["has_current"] is True
    assert got[("views", "rerendered", "r0")]["n_rows"] == 2
    assert got[("captions", "old_caption", "c0")]["has_current"] is False
    assert got[("text_embeddings", "fresh", "t0")]["model_id"] == "clip_text:old"
    assert all(r["mesh_active"] for r in got.values())


def test_errors_by_stage(tmp_path):
    t = TinyStore(tmp_path / "s")
    for m in ("bad1", "bad2"):
        t.mesh(m)
        t.views(m)
        t.error("caption", m, "captioner ran out of memory", fingerprint="c1")
    t.complete("healed")
    t.error(
        "render",
        "healed",
        "render timed out after 120 s",
        fingerprint="r1",
        error_type="Timeout",
        run_id=OLD_RUN,
    )
    t.mesh("old_config")
    t.error("render", "old_config", "old problem", fingerprint="r0", run_id=OLD_RUN)
    t.mesh("gone", status="removed", run_id="20250101T000000000000Z-zzzzzz")
    t.error("render", "gone", "file vanished", fingerprint="r1")
    t.error("discover", None, "missing texture x.png", source_path="broken/broken.obj")
    t.error("discover", None, "missing .mtl", source_path="fixed/fixed.obj", run_id=OLD_RUN)
    t.mesh("fixed", source_path="fixed/fixed.obj")
    t.run()
    store = t.commit()
    rows = audit(store, "errors_by_stage")
    got = {(r["stage"], r["reason"]): r["n_files"] for r in rows}
    assert got == {("caption", "captioner ran out of memory"): 2, ("discover", "missing texture x.png"): 1}
    assert rows[0]["stage"] == "caption"  # most widespread first
    assert {r["example_path"] for r in rows} == {"bad1/bad1.obj", "broken/broken.obj"}


@pytest.mark.parametrize("cameras,expected", [("oscar", 2), ("cap3d", 8)])
def test_expected_views_follow_the_camera_layout(tmp_path, cameras, expected):
    t = TinyStore(tmp_path / "s")
    t.complete("m")
    t.run(render={"cameras": cameras, "views_per_ring": 1, "elevations_deg": [-15.0, 15.0]})
    store = t.commit()
    rows = audit(store, "missing_outputs")
    assert len(rows) == (0 if expected == 2 else 4)
