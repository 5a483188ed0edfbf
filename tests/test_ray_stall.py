"""A Ray round that stops moving after a node loss is abandoned and planned again (RayOptions.stall_s):
the decision, without a cluster (the cluster tests in test_ray_cluster.py run the real thing)."""

from __future__ import annotations

import types

import pytest

pytest.importorskip("ray")

from pipeline.onboard.engines import ray as engine  # noqa: E402
from pipeline.onboard.engines.ray_options import RayOptions  # noqa: E402


class Watch:
    def __init__(self, lost=()):
        self.lost = dict.fromkeys(lost)

    def check(self):
        return []

    def describe_lost(self):
        return [f"node ({k})" for k in self.lost]


def bare_engine(stall_s=30.0, started=True):
    e = object.__new__(engine.RayEngine)
    e.cfg = types.SimpleNamespace(ray=RayOptions(stall_s=stall_s))
    e._started, e._pumps = started, []
    return e


@pytest.mark.parametrize(
    ("waited", "lost_now", "waiting", "stalled"),
    [
        (31, 1, 2, True),  # a node lost in this round, no batch for longer than stall_s, actors waiting
        (29, 1, 2, False),  # not long enough
        (31, 0, 2, False),  # no node lost in this round: a slow stage is not a stall
        (31, 1, 0, False),  # every actor placed: the work is just slow
        (150, 1, 0, True),  # ... but not for 5 x stall_s after a node loss: a wait Ray does not show
        (150, 0, 0, False),  # no node lost in the whole run: never abandoned, however slow
    ],
)
def test_a_round_is_stalled_only_after_a_node_loss(monkeypatch, waited, lost_now, waiting, stalled):
    monkeypatch.setattr(engine, "waiting_actors", lambda: waiting)
    monkeypatch.setattr(engine.time, "monotonic", lambda: 1000.0 + waited)
    e, watch = bare_engine(), Watch([f"n{i}" for i in range(lost_now)])
    if stalled:
        with pytest.raises(engine.RoundStalled) as exc:
            e._check_stalled(watch, 0, 1000.0, {"m1"})
        assert exc.value.received == {"m1"}
    else:
        e._check_stalled(watch, 0, 1000.0, {"m1"})


def test_a_node_lost_before_the_round_abandons_it_only_after_stall_placed_s(monkeypatch):
    """A round planned after the loss (``lost_before`` counts it) that hangs with every actor placed."""
    monkeypatch.setattr(engine, "waiting_actors", lambda: 3)
    e, watch = bare_engine(), Watch(["n0"])
    e.cfg = types.SimpleNamespace(ray=RayOptions(stall_s=30, stall_placed_s=60))
    monkeypatch.setattr(engine.time, "monotonic", lambda: 1059.0)
    e._check_stalled(watch, 1, 1000.0, set())  # waiting actors alone do not count for an old loss
    monkeypatch.setattr(engine.time, "monotonic", lambda: 1061.0)
    with pytest.raises(engine.RoundStalled, match="no batch for 61 s after a node loss, every actor placed"):
        e._check_stalled(watch, 1, 1000.0, set())


def test_a_callers_own_ray_session_is_not_dropped():
    """Stalled on a Ray session the caller opened: the run stops with one line instead of reconnecting."""
    e = bare_engine(started=False)
    pending = [{"mesh_id": "m1"}, {"mesh_id": "m2"}, {"mesh_id": "m3"}]
    with pytest.raises(engine.RayEngineError, match="cannot finish") as exc:
        e._reconnect(Watch(["n1"]), pending, {"m1"})
    assert "2 meshes are not done" in str(exc.value) and "\n" not in str(exc.value)


def test_reconnecting_ends_the_old_connection_first(monkeypatch):
    import ray

    calls = []
    monkeypatch.setattr(ray, "shutdown", lambda: calls.append("shutdown"))
    monkeypatch.setattr(engine, "_start_ray", lambda opts: calls.append("start") or True)
    e = bare_engine()
    e._reconnect(Watch(["n1"]), [{"mesh_id": "m1"}], set())
    assert calls == ["shutdown", "start"] and e._started


class SettlingWatch(Watch):
    """A watch whose lost node Ray's table marks dead (or not: ``settles``), with one 1-CPU node alive."""

    def __init__(self, lost=(), settles=True):
        super().__init__(lost)
        self.settles, self.settled = settles, 0

    def settle(self):
        self.settled += 1
        return self.settles

    def resources(self):
        return {"CPU": 1.0, "GPU": 0.0}


def test_a_round_after_a_node_loss_is_planned_on_the_nodes_alive(monkeypatch):
    """Ray's cluster_resources() still counts a killed node until its health check notices: a round
    planned on it placed actors there that restarted for ever (a hang seen in the cluster test)."""
    import ray

    monkeypatch.setattr(ray, "cluster_resources", lambda: {"CPU": 2.0})
    e = bare_engine()
    assert e._resources(SettlingWatch()) == ({"CPU": 2.0}, True)  # nothing lost: Ray's own count
    watch = SettlingWatch(["n1"])
    assert e._resources(watch) == ({"CPU": 1.0, "GPU": 0.0}, True) and watch.settled == 1


def test_planning_goes_on_when_ray_never_marks_the_node_dead(monkeypatch, caplog):
    e, watch = bare_engine(), SettlingWatch(["n1"], settles=False)
    with caplog.at_level("WARNING", logger=engine.__name__):
        assert e._resources(watch) == ({"CPU": 1.0, "GPU": 0.0}, False)  # the round then watches for a stall
    assert "still lists lost node(s) node (n1) as alive" in caplog.text


def ray_nodes(alive_after: int):
    """ray.nodes() whose node n1 is reported alive for the first ``alive_after`` calls."""
    calls = []

    def nodes():
        calls.append(1)
        return [{"NodeID": "n1", "Alive": len(calls) <= alive_after}, {"NodeID": "n2", "Alive": True}]

    return nodes, calls


def settling_watch(monkeypatch, alive_after: int):
    """A ClusterWatch that lost node n1, over a ray.nodes() that reports it alive ``alive_after`` times,
    with sleeps skipped; and the list of ray.nodes() calls."""
    import ray

    from pipeline.onboard.engines import ray_cluster

    nodes, calls = ray_nodes(alive_after)
    monkeypatch.setattr(ray, "nodes", nodes)
    monkeypatch.setattr(ray_cluster.time, "sleep", lambda s: None)
    watch = object.__new__(ray_cluster.ClusterWatch)
    watch.lost = {"n1": None}
    return watch, calls


def test_settle_waits_for_rays_node_table(monkeypatch):
    watch, calls = settling_watch(monkeypatch, alive_after=3)
    assert watch.settle(timeout_s=60) and len(calls) == 4


def test_settle_gives_up_after_its_timeout(monkeypatch):
    from pipeline.onboard.engines import ray_cluster

    watch, calls = settling_watch(monkeypatch, alive_after=10**6)
    clock = iter(range(0, 10**6, 10))
    monkeypatch.setattr(ray_cluster.time, "monotonic", lambda: float(next(clock)))
    assert not watch.settle(timeout_s=60) and len(calls) == 6  # at 10, 20, ..., 60 s: the deadline


def test_meshes_of_abandoned_rounds_are_not_blamed(monkeypatch):
    """A stalled round is abandoned after a node loss that its own stall check recorded, so the watch sees
    no new loss afterwards: its meshes are redone as infrastructure failures, never given strikes (two
    strikes would record them as failed meshes)."""
    items = [{"mesh_id": "m1", "todo": []}, {"mesh_id": "m2", "todo": []}]
    rounds = iter([engine.RoundStalled(set(), 30, 1), engine.RoundStalled({"m1"}, 30, 1), {"m2"}])

    def a_round(plan, pending, bars, summary, watch, isolate):
        assert not isolate  # no mesh was suspected, so no one-mesh batches
        r = next(rounds)
        if isinstance(r, Exception):
            raise r
        return r

    class LostOne(Watch):
        def __init__(self, gcs=None):
            super().__init__(["n1"])

        def cpus_left(self):
            return 1.0

    e = bare_engine()
    e.cfg = types.SimpleNamespace(ray=RayOptions(stall_s=30, address="auto"))
    e.stop = types.SimpleNamespace(requested=False)
    failed = []
    monkeypatch.setattr(engine, "ClusterWatch", LostOne)
    monkeypatch.setattr(engine, "gcs_address", lambda: "h:1")
    monkeypatch.setattr(engine, "check_reachable", lambda paths: None)
    monkeypatch.setattr(e, "_reach", lambda plan, items: {}, raising=False)
    monkeypatch.setattr(e, "_round", a_round, raising=False)
    monkeypatch.setattr(e, "_reconnect", lambda watch, pending, received: None, raising=False)
    monkeypatch.setattr(e, "_commit_lost", lambda plan, bad: failed.extend(bad) or len(bad), raising=False)
    summary = types.SimpleNamespace(failed=0, redone=0, lost_nodes=[])
    e._stream(None, items, {}, summary)
    assert failed == [] and summary.failed == 0
    assert summary.redone == 3 and summary.lost_nodes == ["node (n1)"]


class ExecutorLoop:
    """A stand-in for Ray Data's ``StreamingExecutor`` thread: a loop that checks ``_shutdown`` each step."""

    def __init__(self, step_s: float = 0.05):
        import threading

        self._shutdown = False
        self.steps = 0
        self.thread = threading.Thread(target=self.run, daemon=True)
        self.step_s = step_s
        self.thread.start()

    def run(self):
        import time

        while not self._shutdown:
            self.steps += 1
            time.sleep(self.step_s)

    def join(self, timeout=None):
        self.thread.join(timeout)

    def is_alive(self):
        return self.thread.is_alive()


def test_an_aborted_rounds_executor_loops_end_before_ray_is_shut_down():
    loops = [ExecutorLoop(), ExecutorLoop()]
    engine.end_executor_loops(loops, timeout_s=5.0)
    assert not any(t.is_alive() for t in loops)


def test_a_loop_that_does_not_stop_costs_at_most_the_timeout():
    import time

    stuck = ExecutorLoop(step_s=60.0)  # blocked in a step (as in ray.wait on a lost head)
    t0 = time.monotonic()
    engine.end_executor_loops([stuck], timeout_s=0.3)
    assert time.monotonic() - t0 < 5.0 and stuck._shutdown
