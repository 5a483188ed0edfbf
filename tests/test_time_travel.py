"""``--as-of`` is exact: a time falls on the last run recorded by then, never on a run's half-written
batches; a time before the first run is an error; the analysts' DeltaTable example reads a run's state."""

from __future__ import annotations

import re
import time
from datetime import datetime, timezone
from pathlib import Path

import pyarrow as pa
import pytest

from pipeline import schemas
from pipeline.store import Store, StoreError

REPO = Path(__file__).resolve().parents[1]


def _captions(ids: list[str], run_id: str) -> pa.Table:
    n = len(ids)
    return pa.table(
        {
            "mesh_id": ids,
            "view_index": pa.array([0] * n, pa.int16()),
            "captioner_id": ["c"] * n,
            "caption": ["x"] * n,
            "fingerprint": ["fp"] * n,
            "view_fingerprint": ["v"] * n,
            "run_id": [run_id] * n,
        }
    )


def _runs(run_id: str) -> pa.Table:
    return pa.Table.from_pylist([{"run_id": run_id, "status": "ok"}], schema=schemas.RUNS)


def _now() -> str:
    time.sleep(0.02)
    at = datetime.now(timezone.utc).isoformat()
    time.sleep(0.02)
    return at


@pytest.fixture
def two_runs(tmp_path):
    """Run r0 writes two batches then its record; run r1 one batch, then (``mid``) another, then its
    record. Returns the store and the times between."""
    s = Store.open(tmp_path / "st", create=True)
    t = {"before": _now()}
    s.commit({"captions": _captions(["a"], "r0")}, "r0")
    t["r0_half"] = _now()
    s.commit({"captions": _captions(["b"], "r0")}, "r0")
    s.commit({"runs": _runs("r0")}, "r0")
    t["r0_done"] = _now()
    s.commit({"captions": _captions(["c"], "r1")}, "r1")
    t["r1_half"] = _now()
    s.commit({"captions": _captions(["d"], "r1")}, "r1")
    s.commit({"runs": _runs("r1")}, "r1")
    t["r1_done"] = _now()
    s.close()
    return tmp_path / "st", t


def test_a_time_falls_on_the_last_recorded_run(two_runs):
    store, t = two_runs

    def captions(at) -> list[str]:
        return sorted(Store.open(store, as_of=at).read("captions").column("mesh_id").to_pylist())

    assert captions(t["r0_done"]) == ["a", "b"]
    assert captions(t["r1_half"]) == ["a", "b"]  # r1 is half-written then: r0's state
    assert captions(t["r1_done"]) == ["a", "b", "c", "d"]
    assert captions(0) == ["a", "b"] and captions("1") == ["a", "b", "c", "d"]


def test_a_time_during_the_first_run_or_before_it_is_an_error(two_runs):
    store, t = two_runs
    for at in (t["before"], t["r0_half"], "2001-01-01T00:00:00Z"):
        with pytest.raises(StoreError, match="is before the first run of store"):
            Store.open(store, as_of=at)


def test_sql_as_of_before_the_first_run_is_one_line(two_runs, capsys):
    from pipeline.sql.cli import main

    store, _ = two_runs
    assert main([str(store), "--as-of", "2001-01-01T00:00:00Z", "-c", "SELECT 1"]) == 2
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and "before the first run" in err


def test_analysts_delta_example_reads_the_first_run(two_runs):
    """The docs' snippet, run against a store whose first run wrote two batches."""
    store, _ = two_runs
    text = (REPO / "docs" / "analysts.md").read_text()
    blocks = re.findall(r"```python\n(.*?)```", text, flags=re.S)
    (snippet,) = [b for b in blocks if "history()[-1]" in b]
    assert "version=0)" not in text  # a table's version 0 is one batch, not the first run
    scope: dict = {}
    exec(snippet.replace("data/store", str(store)), scope)  # noqa: S102 - the documented code itself
    assert sorted(scope["old"].column("mesh_id").to_pylist()) == ["a", "b"]
