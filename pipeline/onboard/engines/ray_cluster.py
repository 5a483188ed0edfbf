"""What the Ray engine watches on the cluster: which nodes are alive, which were lost during a run, whether
every node can read the library and the store, and where Ray's own logs are.

A lost node is an infrastructure failure, not a mesh failure: the engine uses :class:`ClusterWatch` to
tell the two apart (a batch lost while a node died is re-submitted; only a batch lost on its own counts
against its meshes), and to name the lost nodes in the run summary.
"""

from __future__ import annotations

import logging
import os
import socket
import time
import warnings
from contextlib import contextmanager
from dataclasses import dataclass

log = logging.getLogger(__name__)

#: seconds the reachability probe waits for every node to answer
PROBE_TIMEOUT_S = 120.0
#: seconds a new round waits for Ray's node table to mark the nodes this run lost as dead (Ray's health
#: check takes several seconds; until then Ray still places actors on them)
SETTLE_S = 60.0


class RayEngineError(RuntimeError):
    """The Ray engine cannot run or finish (Ray missing, cluster unreachable or lost, every batch failed)."""


class LibraryUnreachableError(RayEngineError):
    """A Ray node cannot read the library (or the store) at the driver's path."""


@dataclass(frozen=True)
class NodeInfo:
    """One Ray node, as the run summary names it."""

    node_id: str
    ip: str
    cpus: float
    gpus: float = 0.0

    def describe(self) -> str:
        return f"{self.ip} ({self.node_id[:8]})"


def alive_nodes() -> dict[str, NodeInfo]:
    """node id -> the node, for every node Ray reports alive whose raylet still accepts connections (a
    killed node refuses them at once; Ray's own health check takes several seconds to notice)."""
    import ray

    out = {}
    for n in ray.nodes():
        ip, port = n.get("NodeManagerAddress", "?"), n.get("NodeManagerPort")
        if n.get("Alive") and (not port or reachable(ip, port)):
            res = n.get("Resources", {})
            out[n["NodeID"]] = NodeInfo(n["NodeID"], ip, res.get("CPU", 0.0), res.get("GPU", 0.0))
    return out


def reachable(host: str, port: int | str) -> bool:
    """Whether ``host:port`` accepts a TCP connection (within 2 s)."""
    try:
        with socket.create_connection((host, int(port)), timeout=2.0):
            return True
    except (OSError, ValueError):
        return False


def log_dir() -> str:
    """Where this Ray session writes its logs (Ray Data's, the raylets', the workers')."""
    try:
        from ray.data._internal.logging import get_log_directory

        d = get_log_directory()
        if d:
            return os.path.dirname(d)
    except Exception:  # noqa: BLE001 - an internal helper; the default below is Ray's documented place
        pass
    return "/tmp/ray/session_latest/logs"


class ClusterWatch:
    """The nodes alive when the run started (and those that joined since), and those lost since."""

    def __init__(self, gcs_address: str | None = None):
        self.known: dict[str, NodeInfo] = alive_nodes()
        self.lost: dict[str, NodeInfo] = {}
        self.gcs_address = gcs_address

    def check(self) -> list[NodeInfo]:
        """Nodes lost since the last check (newly joined nodes are remembered)."""
        alive = alive_nodes()
        gone = [n for nid, n in self.known.items() if nid not in alive and nid not in self.lost]
        for n in gone:
            self.lost[n.node_id] = n
        for nid, n in alive.items():
            self.known.setdefault(nid, n)
        return gone

    def cpus_left(self) -> float:
        """CPUs of the nodes alive now."""
        return self.resources()["CPU"]

    def resources(self) -> dict[str, float]:
        """CPUs and GPUs of the nodes alive now (``ray.cluster_resources()`` still counts a killed node
        until Ray's health check has noticed it)."""
        nodes = alive_nodes().values()
        return {"CPU": sum(n.cpus for n in nodes), "GPU": sum(n.gpus for n in nodes)}

    def settle(self, timeout_s: float = SETTLE_S) -> bool:
        """Wait until Ray's own node table marks every node this run lost as dead, so that the next
        round's actors are not placed on a node that is gone (they would restart for ever, waiting for
        room the survivors lack). False when Ray still lists one alive after ``timeout_s``."""
        import ray

        deadline = time.monotonic() + timeout_s
        while True:
            alive = {n["NodeID"] for n in ray.nodes() if n.get("Alive")}
            if not alive & self.lost.keys():
                return True
            if time.monotonic() >= deadline:
                return False
            time.sleep(0.5)

    def head_reachable(self) -> bool:
        """Whether the cluster's head (its GCS port) still accepts connections; a quick TCP probe, so a
        dead head is noticed without waiting for Ray's own reconnect timeout."""
        if not self.gcs_address:
            return True
        host, _, port = self.gcs_address.rpartition(":")
        return reachable(host, port)

    def describe_lost(self) -> list[str]:
        return [n.describe() for n in self.lost.values()]


def gcs_address() -> str | None:
    """HOST:PORT of the connected cluster's GCS (None when unknown)."""
    try:
        import ray

        return ray.get_runtime_context().gcs_address
    except Exception:  # noqa: BLE001
        return None


def unreadable(path: str) -> str | None:
    """Why ``path`` (a folder) cannot be read on this machine, or None when it can."""
    if not os.path.exists(path):
        return "no such folder"
    if not os.path.isdir(path):
        return "not a folder"
    try:
        os.listdir(path)
    except OSError as exc:
        return exc.strerror or type(exc).__name__
    return None


def unreachable_message(node: str, what: str, path: str, why: str) -> str:
    return (
        f"Ray node {node} cannot read the {what} at {path} ({why}): mount it at the same path on every "
        "node (docs/scaling.md, Files)"
    )


def check_reachable(paths: dict[str, str]) -> None:
    """Raise :class:`LibraryUnreachableError` naming the first node and path that cannot be read.

    ``paths``: what (``library``, ``store``) -> the folder every node must read. One zero-CPU task runs
    on each alive node, so the check neither waits for nor takes resources from the actors."""
    if not paths:
        return
    import ray
    from ray.util.scheduling_strategies import NodeAffinitySchedulingStrategy

    @ray.remote(num_cpus=0, max_retries=0)
    def probe(paths: dict[str, str]) -> tuple[str, str, str] | None:
        for what, path in paths.items():
            why = unreadable(path)
            if why:
                return what, path, why
        return None

    nodes = list(alive_nodes().values())
    refs = {
        probe.options(scheduling_strategy=NodeAffinitySchedulingStrategy(n.node_id, soft=False)).remote(
            paths
        ): n
        for n in nodes
    }
    ready, _ = ray.wait(list(refs), num_returns=len(refs), timeout=PROBE_TIMEOUT_S)
    for ref in ready:
        try:
            found = ray.get(ref)
        except ray.exceptions.RayError:  # a node that died meanwhile is the run's business, not the probe's
            continue
        if found:
            raise LibraryUnreachableError(unreachable_message(refs[ref].describe(), *found))


def this_node() -> str:
    """This worker's node, as messages name it."""
    import ray

    ctx = ray.get_runtime_context()
    return NodeInfo(ctx.get_node_id(), ray.util.get_node_ip_address(), 0.0).describe()


@contextmanager
def quiet_console():
    """Keep Ray's internal tracebacks and notices off the console for the duration: Ray Data's console
    handler is silenced (its file handler keeps everything, under :func:`log_dir`/ray-data) and the
    raylet notices Ray prints on the driver (node marked dead, raylet terminated) go to this module's
    logger at DEBUG level; Ray keeps them in its own logs too."""
    import ray._private.worker as ray_worker
    import ray.data  # noqa: F401 - Ray Data sets up its loggers when first imported: silence those

    handlers = [h for h in logging.getLogger("ray.data").handlers if isinstance(h, logging.StreamHandler)]
    levels = [h.level for h in handlers]
    for h in handlers:
        h.setLevel(logging.CRITICAL + 1)
    printer = ray_worker.print_to_stdstream

    def to_log(data, ignore_prefix: bool = False):
        if data.get("pid") == "raylet":
            for line in data.get("lines", []):
                log.debug("ray: %s", line)
            return
        printer(data, ignore_prefix)

    ray_worker.print_to_stdstream = to_log
    with warnings.catch_warnings():
        # Ray Data's note that a pool got no input (a mesh set that needs no captioning, a retry round)
        warnings.filterwarnings("ignore", message="The minimum number of concurrent actors")
        try:
            yield
        finally:
            ray_worker.print_to_stdstream = printer
            for h, lv in zip(handlers, levels, strict=True):
                h.setLevel(lv)


@contextmanager
def quiet_driver_core():
    """Start Ray's C++ core worker of the driver (inside ``ray.init``) with its log threshold at FATAL.

    The driver's core worker copies its ERROR and WARNING lines to stderr: one per actor start ("has
    constructor arguments in the object store and max_restarts > 0", harmless here: Ray Data puts each
    pool's arguments in the driver's object store, which lives as long as the run), and a stream of
    "Failed to connect to GCS" while a lost head is noticed. The threshold is set only while the driver
    connects, after a local instance's own processes have started, so the raylets, the GCS and the
    workers keep logging as usual; the run's messages say where those logs are."""
    import ray._private.worker as ray_worker

    real = ray_worker.connect

    def connect(*args, **kwargs):
        import sys
        import tempfile

        old = os.environ.get(CORE_LOG_LEVEL)
        os.environ[CORE_LOG_LEVEL] = "fatal"
        sys.stderr.flush()
        saved = os.dup(2)
        with tempfile.TemporaryFile() as held:  # Ray's line saying it read the threshold, and the like
            os.dup2(held.fileno(), 2)
            try:
                return real(*args, **kwargs)
            except BaseException:
                os.dup2(saved, 2)
                held.seek(0)
                sys.stderr.write(held.read().decode(errors="replace"))  # a failed connect keeps its output
                raise
            finally:
                os.dup2(saved, 2)
                os.close(saved)
                if old is None:
                    os.environ.pop(CORE_LOG_LEVEL, None)
                else:
                    os.environ[CORE_LOG_LEVEL] = old

    ray_worker.connect = connect
    try:
        yield
    finally:
        ray_worker.connect = real


#: the environment variable Ray's C++ logging reads its threshold from
CORE_LOG_LEVEL = "RAY_BACKEND_LOG_LEVEL"


def waiting_actors() -> int:
    """Actors of this driver's job waiting to be placed or restarted (Ray's GCS actor table; no
    dashboard needed). 0 when the table cannot be read."""
    import ray

    try:
        from ray._private.state import actors

        job = ray.get_runtime_context().get_job_id()
        table = actors()
    except Exception:  # noqa: BLE001 - an internal table: without it no round is taken for stalled
        return 0
    waiting = ("PENDING_CREATION", "RESTARTING", "DEPENDENCIES_UNREADY")
    return sum(1 for a in table.values() if a.get("State") in waiting and a.get("JobID") == job)

