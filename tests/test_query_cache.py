"""The query path's embedding cache follows the Delta log: only added files are read, and the cached
tables always equal the uncached ones (adds, --force re-embeds, compaction, removed meshes)."""

from __future__ import annotations

import json
from datetime import datetime, timezone

import numpy as np
import pyarrow as pa
import pytest

from pipeline import schemas
from pipeline.compact import main as compact_main
from pipeline.query import library
from pipeline.query.library import StoreTables, latest_onboarding
from pipeline.store import Store

ENC, VIEW_ENC, FP, VFP = "minilm:x", "descriptor:x", "fp-text", "fp-view"


def _mid(i: int) -> str:
    return f"{i:064x}"


def _meshes(ids, run, status="active"):
    return pa.Table.from_pylist(
        [
            {
                "mesh_id": _mid(i),
                "source_path": f"m{i}.obj",
                "library_root": "/lib",
                "status": status,
                "seen_at": datetime(2025, 1, 1, tzinfo=timezone.utc),
                "run_id": run,
            }
            for i in ids
        ],
        schema=schemas.MESHES,
    )


def _emb(ids, run, seed, dim=16):
    rng = np.random.default_rng(seed)
    n = len(ids) * 4
    x = rng.random((n, dim), dtype=np.float32)
    return pa.table(
        {
            "mesh_id": [_mid(i) for i in ids for _ in range(4)],
            "view_index": pa.array([v for _ in ids for v in range(4)], pa.int16()),
            "encoder_id": ["e"] * n,
            "dim": pa.array([dim] * n, pa.int32()),
            "embedding": pa.FixedSizeListArray.from_arrays(pa.array(x.reshape(-1)), dim),
            "fingerprint": [FP] * n,
            "source_fingerprint": ["s"] * n,
            "run_id": [run] * n,
        }
    )


def _commit(path, run, mesh_ids=(), emb_ids=(), seed=0, status="active"):
    with Store.open(path, create=True) as s:
        tables = {}
        if mesh_ids:
            tables["meshes"] = _meshes(mesh_ids, run, status)
        if emb_ids:
            tables["text_embeddings/minilm-x"] = _emb(emb_ids, run, seed)
            tables["image_embeddings/descriptor-x"] = _emb(emb_ids, run, seed + 1).set_column(
                5, "fingerprint", pa.array([VFP] * len(emb_ids) * 4)
            )
        cfg = {
            "profile": "offline",
            "models": {"text_encoder": ENC, "view_encoder": VIEW_ENC},
            "fingerprints": {"embed_text": FP, "embed_image:view_encoder": VFP},
        }
        run_row = {"run_id": run, "status": "ok", "profile": "offline", "config_json": json.dumps(cfg)}
        tables["runs"] = pa.Table.from_pylist([run_row], schema=schemas.RUNS)
        s.commit(tables, run)


def _rows(t: pa.Table, cols) -> list:
    out = [tuple(t.column(c)[i].as_py() for c in cols) for i in range(t.num_rows)]
    return sorted(out, key=repr)


def _open(path, cache: bool):
    s = Store.open(path)
    t = StoreTables(s, latest_onboarding(s), use_cache=cache)
    return t


def _same(path):
    cached, plain = _open(path, True), _open(path, False)
    cols = ["mesh_idx"] + [f"e{i}" for i in range(8)]
    assert _rows(cached.captions, cols) == _rows(plain.captions, cols)
    vcols = ["mesh_idx", "view_index", "embedding"]
    assert _rows(cached.views, vcols) == _rows(plain.views, vcols)
    return cached.cache_stats


@pytest.fixture(autouse=True)
def small_cache(monkeypatch):
    monkeypatch.setattr(library, "CACHE_MIN_ROWS", 1)


def test_cache_follows_the_delta_log(tmp_path):
    st = tmp_path / "st"
    _commit(st, "r1", range(6), range(6), seed=1)
    stats = _same(st)
    assert stats["caption"]["read_files"] == 1
    seg_dir = next((st / "_cache" / "query").glob("caption-*"))
    first = sorted(seg_dir.glob("seg-*.arrow"))
    first_mtime = first[0].stat().st_mtime_ns

    assert _same(st)["caption"] == {
        "read_files": 0,
        "new_segments": 0,
        "rewritten_segments": 0,
        "renumbered": 0,
    }

    _commit(st, "r2", [6], [6], seed=2)  # one mesh added: only its file is read, old segment untouched
    stats = _same(st)["caption"]
    assert stats["read_files"] == 1 and stats["new_segments"] == 1 and stats["rewritten_segments"] == 0
    assert first[0].stat().st_mtime_ns == first_mtime

    _commit(st, "r3", (), [2, 3], seed=3)  # --force re-embed of two meshes supersedes their old rows
    assert _same(st)["caption"]["rewritten_segments"] == 1

    _commit(st, "r4", [4], (), status="removed")  # a mesh leaves the library
    _same(st)
    _commit(st, "r5", [4], ())  # and comes back
    _same(st)

    assert compact_main([str(st), "--retention-hours", "0"]) == 0  # files rewritten: segments re-read
    _same(st)
    assert _same(st)["caption"]["read_files"] == 0


def test_many_segments_are_merged(tmp_path, monkeypatch):
    from pipeline.query import cache

    monkeypatch.setattr(cache, "MAX_SEGMENTS", 2)
    st = tmp_path / "st"
    for i in range(4):
        _commit(st, f"r{i}", [i], [i], seed=i)
        _same(st)
    seg_dir = next((st / "_cache" / "query").glob("caption-*"))
    assert len(list(seg_dir.glob("seg-*.arrow"))) <= 3
