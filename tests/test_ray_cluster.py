"""The Ray engine on a real multi-node cluster: a head without CPUs and two 1-CPU worker nodes, each a
raylet of its own on this machine (``ray.cluster_utils.Cluster``). A worker node is killed at a known
point of a run (an actor waits on a mesh until the test kills its node, or the driver's commit kills
it): the run finishes on the survivor, no mesh is failed, and the tables equal the local engine's with
no duplicate rows. Losing every worker, the driver or the head stops the run; the store stays
consistent and a plain re-run completes. The module took 401 s on this repository's 2-CPU machine shared with
other jobs (load about 15): marked slow."""

from __future__ import annotations

import json
import os
import shutil
import signal
import subprocess
import sys
import tempfile
import threading
import time
from pathlib import Path

import pytest
from conftest import REPO, SAMPLE_LIBRARY
from ray_helpers import assert_no_duplicates, assert_same_store

from pipeline.fsck import fsck
from pipeline.mesh.settings import RenderConfig
from pipeline.onboard.config import OnboardConfig
from pipeline.onboard.engines.ray_cluster import RayEngineError
from pipeline.onboard.engines.ray_options import RayOptions
from pipeline.onboard.run import run_onboarding
from pipeline.onboard.supervise import EXIT_DRIVER_LOST
from pipeline.profiles import default_elevations
from pipeline.store import Store

ray = pytest.importorskip("ray", reason="the ray extra is not installed (pip install 'oscar-pipeline[ray]')")
pytestmark = [pytest.mark.ray, pytest.mark.slow]

MESHES = ["003_cracker_box", "005_tomato_soup_can", "006_mustard_bottle", "011_banana"]
RESOLUTION = 64
WORKERS = 2


def config(engine: str, **ray_kw) -> OnboardConfig:
    opts = RayOptions(render_batch_size=1, caption_batch_size=2, embed_batch_size=2, stall_s=20, **ray_kw)
    render = RenderConfig(resolution=RESOLUTION, elevations_deg=default_elevations("offline"))  # as the CLI's
    return OnboardConfig(render=render, engine=engine, workers=0, batch_size=2, ray=opts)


class Nodes:
    """The test cluster: kill worker nodes by Ray node id, and bring the workers back to full strength."""

    def __init__(self, cluster):
        self.cluster = cluster
        self.workers = []
        self.refill()

    @property
    def address(self) -> str:
        return self.cluster.address

    def refill(self) -> None:
        while len(self.workers) < WORKERS:
            self.workers.append(self.cluster.add_node(num_cpus=1))
        self.cluster.wait_for_nodes()

    def kill(self, node_id: str | None = None) -> str:
        """Kill the worker node ``node_id`` (default: the first); return its id."""
        node = next(n for n in self.workers if node_id in (None, n.node_id))
        self.workers.remove(node)
        self.cluster.remove_node(node, allow_graceful=False)
        return node.node_id


class KillWhenPaused(threading.Thread):
    """Kills the node whose actor wrote its node id to ``marker`` (``RayOptions.pause_at``), or every
    worker node with ``everyone``."""

    def __init__(self, nodes: Nodes, marker: Path, everyone: bool = False):
        super().__init__(daemon=True)
        self.nodes, self.marker, self.everyone = nodes, marker, everyone
        self.killed: list[str] = []
        self.start()

    def run(self) -> None:
        deadline = time.monotonic() + 300
        while time.monotonic() < deadline and not (self.marker.exists() and self.marker.read_text()):
            time.sleep(0.05)
        if not self.marker.exists():
            return
        self.killed.append(self.nodes.kill(self.marker.read_text()))
        while self.everyone and self.nodes.workers:
            self.killed.append(self.nodes.kill())


@pytest.fixture(scope="module")
def nodes():
    # a private Ray folder: /tmp/ray is shared, and a test cluster must not become anyone's default
    tmp = tempfile.mkdtemp(prefix="oscar-ray-", dir="/tmp")
    from ray.cluster_utils import Cluster

    with pytest.MonkeyPatch.context() as mp:
        mp.setenv("RAY_TMPDIR", tmp)
        if ray.is_initialized():
            ray.shutdown()
        cluster = Cluster(initialize_head=True, head_node_args={"num_cpus": 0, "include_dashboard": False})
        try:
            yield Nodes(cluster)
        finally:
            try:
                if ray.is_initialized():
                    ray.shutdown()
                cluster.shutdown()
            finally:
                shutil.rmtree(tmp, ignore_errors=True)


@pytest.fixture
def cluster(nodes):
    nodes.refill()
    return nodes


@pytest.fixture(scope="module")
def library(tmp_path_factory):
    lib = tmp_path_factory.mktemp("clusterlib") / "lib"
    for name in MESHES:
        shutil.copytree(SAMPLE_LIBRARY / name, lib / name)
    return lib


@pytest.fixture(scope="module")
def reference(library, tmp_path_factory):
    store = tmp_path_factory.mktemp("clusterref") / "store"
    summary = run_onboarding(str(library), str(store), config("local"), progress=False)
    assert summary.rendered == len(MESHES) and summary.failed == 0
    return store


def mesh_id(reference, name: str) -> str:
    rows = Store.open(reference).read("meshes").to_pylist()
    return next(r["mesh_id"] for r in rows if r["name"] == name)


def assert_recovered(summary, killed: list[str], store, reference, err: str) -> None:
    """The run finished on the survivors: nothing failed, the lost node is named, tables as the local
    engine's, no duplicates, no Ray traceback on the console, the runs row names the node."""
    assert summary.failed == 0 and summary.rendered == len(MESHES)
    assert [n.split("(")[1][:8] for n in summary.lost_nodes] == [k[:8] for k in killed]
    assert any("lost Ray node(s)" in line for line in summary.lines())
    assert_same_store(reference, store)
    assert_no_duplicates(store)
    assert "Traceback" not in err and "constructor arguments" not in err
    runs = Store.open(store).read("runs").to_pylist()
    cluster = json.loads(runs[-1]["config_json"])["cluster"]
    assert cluster == {"lost_nodes": summary.lost_nodes, "meshes_redone": summary.redone}


@pytest.mark.parametrize("stage", ["render", "caption"])
def test_worker_node_lost_mid_stage(cluster, library, reference, tmp_path, capfd, stage):
    marker = tmp_path / "paused"
    killer = KillWhenPaused(cluster, marker)
    victim = mesh_id(reference, "006_mustard_bottle")
    cfg = config("ray", address=cluster.address, pause_at=f"{stage}:{victim}:{marker}")
    summary = run_onboarding(str(library), str(tmp_path / "store"), cfg, progress=False)
    killer.join(timeout=5)
    assert killer.killed and summary.redone >= 1  # the paused mesh at least was redone
    assert_recovered(summary, killer.killed, tmp_path / "store", reference, capfd.readouterr().err)


def test_worker_node_lost_while_the_driver_commits(cluster, library, reference, tmp_path, capfd, monkeypatch):
    killed: list[str] = []
    real = Store.commit

    def commit(store, tables, run_id):
        if "views" in tables and not killed:  # the first batch of finished meshes
            killed.append(cluster.kill())
        return real(store, tables, run_id)

    monkeypatch.setattr(Store, "commit", commit)
    cfg = config("ray", address=cluster.address)
    summary = run_onboarding(str(library), str(tmp_path / "store"), cfg, progress=False)
    monkeypatch.undo()
    assert_recovered(summary, killed, tmp_path / "store", reference, capfd.readouterr().err)


# Ray Data's executor thread used to end in SystemExit when the run shut Ray down under it
@pytest.mark.filterwarnings("error::pytest.PytestUnhandledThreadExceptionWarning")
def test_every_worker_lost_stops_the_run(cluster, library, reference, tmp_path, capfd):
    store, marker = tmp_path / "store", tmp_path / "paused"
    killer = KillWhenPaused(cluster, marker, everyone=True)
    victim = mesh_id(reference, "011_banana")
    cfg = config("ray", address=cluster.address, pause_at=f"render:{victim}:{marker}")
    with pytest.raises(RayEngineError, match="cannot finish: no node with CPUs is left") as exc:
        run_onboarding(str(library), str(store), cfg, progress=False)
    assert "\n" not in str(exc.value)
    err = capfd.readouterr().err
    assert "Traceback" not in err, err[:3000]
    assert len(killer.killed) == WORKERS
    assert not fsck(store).problems
    assert Store.open(store).read("errors").num_rows == 0  # nothing blamed on the meshes
    cluster.refill()
    summary = run_onboarding(str(library), str(store), config("ray", address=cluster.address), progress=False)
    assert summary.failed == 0 and summary.failed_before == 0
    assert_same_store(reference, store)
    assert_no_duplicates(store)


def cli(library, store, *extra) -> subprocess.Popen:
    cmd = [sys.executable, "-m", "pipeline.onboard", str(library), "--store", str(store), "--engine", "ray"]
    cmd += ["--resolution", str(RESOLUTION), "--workers", "0", "--batch-size", "2", "--no-progress", *extra]
    env = {**os.environ, "PYTHONPATH": os.pathsep.join([str(REPO), os.environ.get("PYTHONPATH", "")])}
    return subprocess.Popen(cmd, env=env, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)


def wait_for_commit(store: Path, proc: subprocess.Popen) -> None:
    """Until the first batch of finished meshes is committed (its last table, view_features, exists)."""
    deadline = time.monotonic() + 300
    while not (store / "view_features" / "_delta_log" / f"{0:020d}.json").exists():
        assert proc.poll() is None, proc.communicate()
        assert time.monotonic() < deadline
        time.sleep(0.1)


def test_driver_killed_rerun_completes(cluster, library, reference, tmp_path):
    store = tmp_path / "store"
    proc = cli(library, store, "--address", cluster.address)
    wait_for_commit(store, proc)
    proc.send_signal(signal.SIGKILL)
    proc.communicate(timeout=60)
    assert not fsck(store).problems
    summary = run_onboarding(str(library), str(store), config("local"), progress=False)  # either engine
    assert summary.failed == 0 and summary.rendered < len(MESHES)  # the committed batch is kept
    assert_same_store(reference, store)
    assert_no_duplicates(store)


def test_head_lost_stops_the_driver_and_rerun_completes(nodes, library, reference, tmp_path):
    """Last in this module: the cluster does not survive it. The driver runs on the head's raylet (as on a
    real cluster, where it runs on the head node), so Ray's core worker ends the driver's process as
    soon as that raylet dies, and the supervising CLI (pipeline/onboard/supervise.py) says so; or the
    engine's probe of the head's GCS port notices first. Either way one line, no Python traceback, a
    consistent store, and a re-run that completes."""
    nodes.refill()
    store, marker = tmp_path / "store", tmp_path / "paused"
    # the last mesh's render waits (a minute) once reached, so the head dies mid-run, not after it
    pause = f"render:{mesh_id(reference, MESHES[-1])}:{marker}"
    proc = cli(library, store, "--address", nodes.address, "--ray-pause-at", pause)
    deadline = time.monotonic() + 300
    while not marker.exists():
        assert proc.poll() is None, proc.communicate()
        assert time.monotonic() < deadline
        time.sleep(0.1)
    nodes.cluster.remove_node(nodes.cluster.head_node, allow_graceful=False)
    out, err = proc.communicate(timeout=180)
    # whichever notices first says so in one line: the engine's probe of the head's GCS port (exit 2), or,
    # when Ray's core worker ends the driver first, the supervising CLI (exit 75)
    assert proc.returncode in (2, EXIT_DRIVER_LOST), (out[-3000:], err[-3000:])
    assert "Traceback" not in err, err[-3000:]
    lines = [ln for ln in err.splitlines() if ln.startswith("error:")]
    said = "lost the Ray head node" if proc.returncode == 2 else "ended abruptly"
    assert len(lines) == 1 and said in lines[0] and "Ray logs" in lines[0], err[-3000:]
    assert not fsck(store).problems
    summary = run_onboarding(str(library), str(store), config("local"), progress=False)
    assert summary.failed == 0 and summary.rendered <= len(MESHES)
    assert_same_store(reference, store)
    assert_no_duplicates(store)
