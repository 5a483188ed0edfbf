"""The fault corpus (tests/faults/): bad inputs and hostile SQL give a clear one-line error, an errors
row, or correct handling, and nothing already in the store is lost."""

from __future__ import annotations

import functools
import shutil

import pytest
from faults.cases import CASES
from faults.harness import Env, assert_nothing_lost, assert_outcome, deadline, file_digests, rows
from faults.library import RESOLUTION, copy_tree, write_library


@pytest.fixture(scope="session")
def fault_base(tmp_path_factory, offline_models):
    """One small library and its store, built once; every case works on a copy."""
    import pipeline.onboard.run as executor
    from pipeline.mesh.settings import RenderConfig
    from pipeline.onboard.config import OnboardConfig

    root = tmp_path_factory.mktemp("fault_base")
    lib = write_library(root / "lib")
    store = root / "store"
    # the CLI's render settings (the profile's elevation rings) at the corpus's tiny resolution
    rings = OnboardConfig().render.elevations_deg
    cfg = OnboardConfig(workers=0, render=RenderConfig(resolution=RESOLUTION, elevations_deg=rings))
    summary = executor.run_onboarding(str(lib), str(store), cfg, progress=False, models=offline_models)
    assert summary.status == "ok" and summary.failed == 0
    return lib, store


@pytest.fixture
def shared_models(offline_models):
    """The corpus's command-line onboarding runs reuse the session's models (loading them per case is
    slow); only while a corpus test runs, so other tests' CLI runs load their own."""
    import pipeline.onboard.run as executor

    with pytest.MonkeyPatch.context() as mp:
        mp.setattr(
            executor, "run_onboarding", functools.partial(executor.run_onboarding, models=offline_models)
        )
        yield


@pytest.mark.parametrize("case", [pytest.param(c, marks=c.marks, id=c.name) for c in CASES])
def test_fault(case, fault_base, shared_models, tmp_path, monkeypatch):
    lib0, store0 = fault_base
    env = Env(tmp_path, copy_tree(lib0, tmp_path / "lib"), copy_tree(store0, tmp_path / "store"), monkeypatch)
    if case.prepare:
        case.prepare(env)
    files_before = file_digests(env.store)
    rows_before = rows(env.store, latest=case.rows == "latest")
    with deadline():
        result = case.act(env)
    monkeypatch.undo()  # faults injected by the case end here; the checks read the store normally
    assert_outcome(case, env, result, rows_before)
    if case.check:
        case.check(env, result)
    assert_nothing_lost(case, env, files_before, rows_before)
    shutil.rmtree(tmp_path, ignore_errors=True)


def test_corpus_is_large_and_covers_every_tool():
    tools = {c.tool for c in CASES}
    assert len(CASES) >= 60
    assert {"onboard", "query", "sql", "compact"} <= tools
    assert len({c.name for c in CASES}) == len(CASES), "case names must be unique"
