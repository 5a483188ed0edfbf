"""The learned ROI embedding runs beside the rest of the query's embedding (pipeline/query/overlap.py): same
vectors as in turn, its errors reach the caller, and it stays in the calling thread where it cannot pay."""

from __future__ import annotations

import threading

import numpy as np
import pytest
from query_helpers import AspectEncoder, fake_models, make_fake_store, object_image

from pipeline.query import Retriever
from pipeline.query import overlap as overlap_mod
from pipeline.query.overlap import OVERLAP_ENV, beside, overlapping


class ThreadRecordingEncoder(AspectEncoder):
    """The aspect-ratio stand-in learned encoder, recording the thread each call ran in."""

    def __init__(self, fail: bool = False):
        self.threads: list[str] = []
        self.fail = fail

    def encode_image(self, images):
        self.threads.append(threading.current_thread().name)
        if self.fail:
            raise RuntimeError("encoder broke")
        return super().encode_image(images)


@pytest.fixture(scope="module")
def store(tmp_path_factory):
    return make_fake_store(tmp_path_factory.mktemp("overlap") / "store", learned=AspectEncoder())


@pytest.fixture
def two_cores(monkeypatch):
    """As on a 2-core machine with torch on one thread (the query CLI's default there)."""
    monkeypatch.setattr(overlap_mod, "cpu_count", lambda: 2)
    monkeypatch.delenv(OVERLAP_ENV, raising=False)
    torch = pytest.importorskip("torch")
    monkeypatch.setattr(torch, "get_num_threads", lambda: 1)


def query(store, enc, monkeypatch, overlap: str):
    monkeypatch.setenv(OVERLAP_ENV, overlap)
    img = object_image("red", 44, 52, pad=30)
    mask = np.abs(np.asarray(img, np.int16) - 205).sum(axis=2) > 30
    with Retriever.open(store, models={**fake_models(), "learned_encoder": enc}, use_cache=False) as r:
        return r.query(img, "the red can", mask=mask, top=4)


def test_beside_runs_in_the_pool_and_gives_the_value(two_cores):
    assert overlapping()
    f = beside(lambda: threading.current_thread().name)
    assert f.result(timeout=30).startswith("oscar-embed")


def test_beside_raises_the_calls_error(two_cores):
    def boom():
        raise ValueError("bad roi")

    with pytest.raises(ValueError, match="bad roi"):
        beside(boom).result(timeout=30)


def test_beside_runs_in_place_when_switched_off_or_without_a_free_core(two_cores, monkeypatch):
    here = threading.current_thread().name
    monkeypatch.setenv(OVERLAP_ENV, "0")
    assert not overlapping() and beside(lambda: threading.current_thread().name).result() == here
    monkeypatch.delenv(OVERLAP_ENV)
    import torch

    monkeypatch.setattr(torch, "get_num_threads", lambda: 2)  # torch already on every core
    assert not overlapping() and beside(lambda: threading.current_thread().name).result() == here
    monkeypatch.setattr(overlap_mod, "cpu_count", lambda: 1)
    monkeypatch.setattr(torch, "get_num_threads", lambda: 1)
    assert not overlapping()
    with pytest.raises(KeyError):  # an error of an in-place call is raised by .result(), not by beside()
        f = beside(lambda: {}["x"])
        f.result()


def test_query_is_the_same_beside_and_in_turn(store, two_cores, monkeypatch):
    side, in_turn = ThreadRecordingEncoder(), ThreadRecordingEncoder()
    a = query(store, side, monkeypatch, "1")
    b = query(store, in_turn, monkeypatch, "0")
    assert side.threads and all(t.startswith("oscar-embed") for t in side.threads)
    assert in_turn.threads and not any(t.startswith("oscar-embed") for t in in_turn.threads)
    assert [c.mesh_id for c in a.candidates] == [c.mesh_id for c in b.candidates]
    assert [c.score for c in a.candidates] == pytest.approx([c.score for c in b.candidates], abs=1e-7)
    assert a.accepted == b.accepted and a.candidates[0].name == "red_can"


def test_an_encoder_error_beside_the_query_reaches_the_caller(store, two_cores, monkeypatch):
    enc = ThreadRecordingEncoder(fail=True)
    with pytest.raises(RuntimeError, match="encoder broke"):
        query(store, enc, monkeypatch, "1")
    assert enc.threads and enc.threads[0].startswith("oscar-embed")


def test_a_busy_pool_runs_the_call_in_place(two_cores, monkeypatch):
    monkeypatch.setattr(overlap_mod, "_pool", None)
    monkeypatch.setattr(overlap_mod, "_free", None)
    release, started = threading.Event(), threading.Event()

    def hold():
        started.set()
        release.wait(30)
        return threading.current_thread().name

    held = beside(hold)  # the 2-core pool's one thread
    assert started.wait(30)
    here = threading.current_thread().name
    assert beside(lambda: threading.current_thread().name).result() == here
    release.set()
    assert held.result(timeout=30).startswith("oscar-embed")
    assert beside(lambda: threading.current_thread().name).result(timeout=30).startswith("oscar-embed")


def test_a_forked_child_starts_a_pool_of_its_own(two_cores):
    import multiprocessing

    assert beside(lambda: 1).result(timeout=30) == 1  # the parent's pool exists
    ctx = multiprocessing.get_context("fork")
    with ctx.Pool(1) as pool:
        assert pool.apply(_side_thread_name, ()).startswith("oscar-embed")


def _side_thread_name() -> str:
    import torch

    torch.get_num_threads = lambda: 1  # the child of the 2-core stand-in (the fixture's patch is copied)
    return beside(lambda: threading.current_thread().name).result(timeout=30)
