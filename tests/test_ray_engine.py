"""The Ray engine on a local 2-CPU Ray instance: same tables as the local engine, resumable, either engine
continues the other's work, a crashed worker retries its batch only, stored inputs are read back."""

from __future__ import annotations

import shutil

import pytest
from conftest import SAMPLE_LIBRARY
from ray_helpers import assert_same_store

from pipeline.mesh.settings import RenderConfig
from pipeline.onboard.config import OnboardConfig
from pipeline.onboard.engines.ray_options import RayOptions
from pipeline.onboard.run import run_onboarding
from pipeline.store import Store

ray = pytest.importorskip("ray", reason="the ray extra is not installed (pip install 'oscar-pipeline[ray]')")
pytestmark = [pytest.mark.ray, pytest.mark.slow]  # Ray start-up dominates: CI runs these as its slow step

MESHES = ["005_tomato_soup_can", "006_mustard_bottle", "011_banana"]
RAY = RayOptions(render_batch_size=1, caption_batch_size=2, embed_batch_size=2, max_retries=1)


def config(engine: str, **kw) -> OnboardConfig:
    kw.setdefault("ray", RAY)
    kw.setdefault("workers", 1 if engine == "ray" else 0)
    return OnboardConfig(render=RenderConfig(resolution=128), engine=engine, **kw)


def onboard(library, store, engine: str, **kw):
    return run_onboarding(str(library), str(store), config(engine, **kw), progress=False)


class Interrupt:
    """Patches ``Store.commit`` to raise KeyboardInterrupt on the data commit after ``n`` (the runs row
    still commits, as after a real Ctrl-C)."""

    def __init__(self, monkeypatch, n: int):
        self.n, self.calls = n, 0
        real = Store.commit

        def commit(store, tables, run_id):
            if "runs" not in tables:
                self.calls += 1
                if self.calls > self.n:
                    raise KeyboardInterrupt
            return real(store, tables, run_id)

        monkeypatch.setattr(Store, "commit", commit)


@pytest.fixture(scope="module")
def ray_session():
    started = not ray.is_initialized()
    if started:
        # address="local": a private instance, never a cluster another job left running on this machine
        ray.init(
            address="local", num_cpus=2, include_dashboard=False, logging_level="warning", log_to_driver=False
        )
    yield
    if started:
        ray.shutdown()


@pytest.fixture(scope="module")
def library(tmp_path_factory):
    lib = tmp_path_factory.mktemp("raylib") / "lib"
    for name in MESHES:
        shutil.copytree(SAMPLE_LIBRARY / name, lib / name)
    return lib


@pytest.fixture(scope="module")
def reference(library, tmp_path_factory):
    """The store the local engine builds in one uninterrupted run."""
    store = tmp_path_factory.mktemp("ref") / "store"
    summary = onboard(library, store, "local")
    assert summary.rendered == len(MESHES) and summary.failed == 0
    return store


def test_ray_engine_builds_the_same_tables(ray_session, library, reference, tmp_path):
    summary = onboard(library, tmp_path / "store", "ray")
    assert summary.rendered == len(MESHES) and summary.captioned == len(MESHES) and summary.failed == 0
    assert {"render", "caption", "embed_text", "embed_image", "commit"} <= set(summary.seconds)
    assert_same_store(reference, tmp_path / "store")
    runs = Store.open(tmp_path / "store").read("runs")
    assert runs.column("engine").to_pylist() == ["ray"] and runs.column("status").to_pylist() == ["ok"]
    again = onboard(library, tmp_path / "store", "ray")  # nothing left to do: no Ray work at all
    assert again.rendered == 0 and again.skipped == len(MESHES) and "ray_start" not in again.seconds


def test_interrupted_ray_run_resumes(ray_session, library, reference, tmp_path, monkeypatch):
    store = tmp_path / "store"
    patch = Interrupt(monkeypatch, 2)  # discovery + the first one-mesh batch, then Ctrl-C
    with pytest.raises(KeyboardInterrupt):
        onboard(library, store, "ray", batch_size=1)
    assert patch.calls == 3
    assert Store.open(store).read("runs").column("status").to_pylist() == ["interrupted"]
    monkeypatch.undo()
    summary = onboard(library, store, "ray", batch_size=1)
    assert summary.rendered == len(MESHES) - 1 and summary.skipped == 1
    assert_same_store(reference, store)


def test_engines_continue_each_other(ray_session, library, reference, tmp_path, monkeypatch):
    for first, second in (("local", "ray"), ("ray", "local")):
        store = tmp_path / f"{first}-{second}"
        Interrupt(monkeypatch, 2)
        with pytest.raises(KeyboardInterrupt):
            onboard(library, store, first, batch_size=1)
        monkeypatch.undo()
        summary = onboard(library, store, second, batch_size=1)
        assert summary.rendered == len(MESHES) - 1, (first, second)
        assert_same_store(reference, store)


def _mesh_id(reference, name: str) -> str:
    meshes = Store.open(reference).read("meshes").to_pylist()
    return next(r["mesh_id"] for r in meshes if r["name"] == name)


def test_crashed_caption_actor_retries_its_batch(ray_session, library, reference, tmp_path):
    marker = tmp_path / "crashed-once"
    victim = _mesh_id(reference, "011_banana")
    opts = RayOptions(
        render_batch_size=1,
        caption_batch_size=1,
        embed_batch_size=2,
        max_retries=2,
        inject_fault=f"caption:{victim}:{marker}",
    )
    summary = onboard(library, tmp_path / "store", "ray", ray=opts)
    assert marker.exists()  # the actor did die once
    assert summary.failed == 0
    assert_same_store(reference, tmp_path / "store")


def test_batch_failing_every_retry_becomes_errors_rows(ray_session, library, reference, tmp_path):
    victim = _mesh_id(reference, "011_banana")
    opts = RayOptions(
        render_batch_size=1,
        caption_batch_size=1,
        embed_batch_size=2,
        max_retries=1,
        inject_fault=f"caption:{victim}:",
    )
    summary = onboard(library, tmp_path / "store", "ray", ray=opts)
    assert summary.failed == 1
    s = Store.open(tmp_path / "store")
    errors = s.read("errors").to_pylist()
    # the whole row (its views too) was lost with the batch, so the mesh failed as a whole: it is
    # recorded at its first stage, like a crashed render worker in the local engine
    assert [(e["stage"], e["mesh_id"], e["error_type"]) for e in errors] == [
        ("render", victim, "WorkerCrash")
    ]
    for table in ("views", "captions"):
        done = set(s.read(table).column("mesh_id").to_pylist())
        assert victim not in done and len(done) == len(MESHES) - 1
    status = {r["mesh_id"]: r["status"] for r in s.read_latest("meshes").to_pylist()}
    assert status[victim] == "failed"


def test_ray_reads_stored_views_and_captions(ray_session, library, reference, tmp_path):
    store = tmp_path / "store"
    shutil.copytree(reference, store)
    summary = onboard(library, store, "ray", force=("embed_text", "embed_image"))
    assert summary.rendered == 0 and summary.captioned == 0 and summary.failed == 0
    assert summary.seconds.get("load", 0) > 0 and summary.seconds.get("embed_text", 0) > 0
    assert_same_store(reference, store)


def test_layout_shares_the_cluster():
    from pipeline.onboard.engines.ray import plan_layout

    cpu_only = plan_layout(RayOptions(), cpus=2, gpus=0, n_caption=1, n_embed=2, n_render=78)
    assert cpu_only.render_workers == 2 and cpu_only.caption_gpus == cpu_only.embed_gpus == 0
    assert 2 * cpu_only.render_cpus + 3 * cpu_only.model_cpus <= 2.0
    one_gpu = plan_layout(RayOptions(), cpus=16, gpus=1, n_caption=1, n_embed=2, n_render=1000)
    assert one_gpu.embed_gpus == 0.25 and one_gpu.caption_gpus == 0.5 and one_gpu.model_cpus == 1.0
    assert one_gpu.render_workers == 16 and 16 * one_gpu.render_cpus <= 13.0
    eight = plan_layout(RayOptions(caption_actors=8), cpus=64, gpus=8, n_caption=8, n_embed=2, n_render=10)
    assert eight.caption_gpus == pytest.approx(7.5 / 8) and eight.render_workers == 10
    fixed = plan_layout(RayOptions(gpus_per_actor=1), cpus=64, gpus=8, n_caption=2, n_embed=4, n_render=10)
    assert fixed.caption_gpus == fixed.embed_gpus == 1


def test_node_that_cannot_read_the_library_is_one_clear_error(ray_session, library, tmp_path, monkeypatch):
    """The library vanishes from the workers' view after the driver planned (an unmounted share on a
    node): one error naming the node and the path, no mesh failed."""
    from pipeline.onboard.engines import base
    from pipeline.onboard.engines.ray_cluster import LibraryUnreachableError

    lib = tmp_path / "lib"
    shutil.copytree(library, lib)
    real = base.make_plan

    def plan_then_unmount(store, root, run):
        plan = real(store, root, run)
        lib.rename(tmp_path / "unmounted")
        return plan

    monkeypatch.setattr(base, "make_plan", plan_then_unmount)
    pattern = rf"^Ray node \S+ \([0-9a-f]{{8}}\) cannot read the library at {lib} \(no such folder\)"
    with pytest.raises(LibraryUnreachableError, match=pattern) as exc:
        onboard(lib, tmp_path / "store", "ray")
    assert "\n" not in str(exc.value)
    assert Store.open(tmp_path / "store").read("errors").num_rows == 0
