"""Running one fault case: the command-line entry points in-process, and the store before and after.

A case's outcome is one of three classes:

* ``error``: non-zero exit and exactly one line on stderr (``...error: ...``), no traceback;
* ``errors_row``: the run succeeds and the ``errors`` table gains a row whose reason contains the
  expected text (one bad file never stops a run);
* ``handled``: exit code 0 (plus the case's own check).

Whatever the outcome, nothing already in the store is lost: every store file present before the command
is still there with the same bytes (except files a writer may legitimately rewrite: the lock, the query
cache), and, where the store is readable, every row present before is still present (for compact: the
latest rows are the same).
"""

from __future__ import annotations

import contextlib
import hashlib
import io
import signal
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path

CASE_TIMEOUT_S = 60  # a hang is a failure, not a stuck CI job
VOLATILE_FILES = ("_lock", "_last_checkpoint")
VOLATILE_DIRS = ("_cache",)


@dataclass
class Result:
    rc: int
    out: str
    err: str


@dataclass
class Case:
    """One bad input: ``act(env)`` returns the command's :class:`Result`; ``prepare`` runs before the
    snapshot (damage that is part of the starting state)."""

    name: str
    tool: str  # onboard | query | sql | compact | evaluate
    outcome: str  # error | errors_row | handled
    act: Callable
    expect: str = ""  # text in the error line, or in an errors row's reason
    prepare: Callable | None = None
    check: Callable | None = None  # extra assertions: check(env, result)
    rows: str = "kept"  # kept (rows before are a subset after) | latest (compact) | skip (store unreadable)
    marks: list = field(default_factory=list)


@dataclass
class Env:
    """Paths of one case: a private copy of the base library and store."""

    tmp: Path
    lib: Path
    store: Path
    monkeypatch: object

    def cli(self, tool: str, argv: list[str], stdin: str | None = None) -> Result:
        return run_cli(tool, [str(a) for a in argv], stdin)

    def onboard(self, *extra, library: Path | None = None, store: Path | None = None) -> Result:
        """``python -m pipeline.onboard`` with the base store's settings (tiny renders, in-process)."""
        from faults.library import RESOLUTION

        argv = [library or self.lib, "--store", store or self.store, "--workers", "0"]
        argv += ["--resolution", str(RESOLUTION), "--no-progress", *extra]
        return self.cli("onboard", argv)

    def sql(self, *argv, stdin: str | None = None) -> Result:
        return self.cli("sql", [self.store, *argv], stdin)


def _entry(tool: str) -> Callable[[list[str]], int]:
    if tool == "onboard":
        from pipeline.onboard.cli import main
    elif tool == "query":
        from pipeline.query.cli import main
    elif tool == "sql":
        from pipeline.sql.cli import main
    elif tool == "compact":
        from pipeline.compact import main
    elif tool == "evaluate":
        from pipeline.evaluate.cli import main
    else:
        raise ValueError(tool)
    return main


def run_cli(tool: str, argv: list[str], stdin: str | None = None) -> Result:
    """Run ``python -m pipeline.<tool> argv`` in this process; capture exit code, stdout and stderr."""
    import sys

    out, err = io.StringIO(), io.StringIO()
    old_stdin = sys.stdin
    if stdin is not None:
        sys.stdin = io.StringIO(stdin)
    try:
        with contextlib.redirect_stdout(out), contextlib.redirect_stderr(err):
            try:
                rc = _entry(tool)(argv)
            except SystemExit as exc:  # argparse
                rc = exc.code if isinstance(exc.code, int) else 1
    finally:
        sys.stdin = old_stdin
    return Result(int(rc or 0), out.getvalue(), err.getvalue())


@contextlib.contextmanager
def deadline(seconds: int = CASE_TIMEOUT_S):
    """Raise ``TimeoutError`` in the main thread when a case runs longer than ``seconds``."""

    def on_alarm(*_):
        raise TimeoutError(f"case still running after {seconds} s (a hang?)")

    old = signal.signal(signal.SIGALRM, on_alarm)
    signal.alarm(seconds)
    try:
        yield
    finally:
        signal.alarm(0)
        signal.signal(signal.SIGALRM, old)


# ------------------------------------------------------------------ store snapshots
def file_digests(store: Path) -> dict[str, str]:
    """sha256 of every store file a command must never change or delete."""
    out = {}
    if not store.is_dir():
        return out
    for p in sorted(store.rglob("*")):
        rel = p.relative_to(store)
        if not p.is_file() or p.is_symlink() or p.name.endswith(".tmp") or p.name in VOLATILE_FILES:
            continue
        if rel.parts[0] in VOLATILE_DIRS:
            continue
        out[rel.as_posix()] = hashlib.sha256(p.read_bytes()).hexdigest()
    return out


def rows(store: Path, latest: bool = False) -> dict[str, list[str]] | None:
    """Every dataset's rows as sorted reprs (``latest``: only the latest row per key); None if unreadable."""
    from pipeline.store import Store

    try:
        s = Store.open(store)
    except Exception:
        return None
    out = {}
    try:
        for table in ("meshes", "views", "captions", "errors", "runs", "text_embeddings", "image_embeddings"):
            for d in s.datasets(table):
                t = s.read_latest(d) if latest else s.read(d)
                out[d] = sorted(map(repr, t.to_pylist()))
    except Exception:
        return None
    finally:
        s.close()
    return out


def new_errors(store: Path, before: dict | None) -> list[dict]:
    """``errors`` rows added since ``before`` (a :func:`rows` snapshot)."""
    from pipeline.store import Store

    old = set((before or {}).get("errors", []))
    with Store.open(store) as s:
        return [r for r in s.read("errors").to_pylist() if repr(r) not in old]


def assert_outcome(case: Case, env: Env, result: Result, before_rows: dict | None) -> None:
    if case.outcome == "error":
        lines = [ln for ln in result.err.splitlines() if ln.strip()]
        assert result.rc != 0, f"expected a non-zero exit; stdout: {result.out[-400:]}"
        assert "Traceback" not in result.err, result.err
        assert len(lines) == 1, f"expected one stderr line, got {len(lines)}:\n{result.err}"
        assert "error" in lines[0].lower(), lines[0]
        assert case.expect.lower() in lines[0].lower(), f"{case.expect!r} not in {lines[0]!r}"
    elif case.outcome == "errors_row":
        assert result.rc == 0, f"rc {result.rc}: {result.err}"
        reasons = [r["reason"] for r in new_errors(env.store, before_rows)]
        assert any(case.expect.lower() in (r or "").lower() for r in reasons), (
            f"no errors row with {case.expect!r}; new rows: {reasons}"
        )
    elif case.outcome == "handled":
        assert result.rc == 0, f"rc {result.rc}: {result.err}"
        assert "Traceback" not in result.err, result.err
    else:
        raise ValueError(case.outcome)


def assert_nothing_lost(case: Case, env: Env, files_before: dict, rows_before: dict | None) -> None:
    after = file_digests(env.store)
    if case.rows != "latest":  # compact replaces superseded parts by design; rows are compared below
        changed = [f for f, h in files_before.items() if after.get(f) != h]
        assert not changed, f"store files changed or deleted: {changed[:5]}"
    if case.rows == "skip" or rows_before is None:
        return
    now = rows(env.store, latest=case.rows == "latest")
    assert now is not None, "the store became unreadable"
    for dataset, old in rows_before.items():
        new = now.get(dataset, [])
        if case.rows == "latest":
            assert new == old, f"{dataset}: latest rows changed"
        else:
            missing = set(old) - set(new)
            assert not missing, f"{dataset}: {len(missing)} row(s) lost"
