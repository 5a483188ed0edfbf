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
    ],
)
def test_a_round_is_stalled_only_after_a_node_loss_with_actors_waiting(monkeypatch, waited, lost_now, waiting, stalled):
    monkeypatch.setattr(engine, "waiting_actors", lambda: waiting)
    monkeypatch.setattr(engine.time, "monotonic", lambda: 1000.0 + waited)
    e, watch = bare_engine(), Watch(["a"] * lost_now)
    if stalled:
        with pytest.raises(engine.RoundStalled) as exc:
            e._check_stalled(watch, 0, 1000.0, {"m1"})
        assert exc.value.received == {"m1"}
    else:
        e._check_stalled(watch, 0, 1000.0, {"m1"})


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
