"""Kept routes: ``Client.keep`` mirrors a route and ``pose`` on it is answered locally.

Agent ``A`` (its clock 3 s ahead) hosts a tracker publishing world -> head at 100 Hz with the
same skewed stamps; agents ``B`` and ``C`` both hold a static head -> eye (different values),
so the route has a second way when the agent of the first leaves.  Every agent and the
tracker are separate processes.
"""

from __future__ import annotations

import threading
import time

import numpy as np
import pytest
from agent_helpers.harness import agent_command, poll, start_agents
from conftest import endpoint, free_port
from test_client_stream import EYE, HEAD, LEASE, SKEW_NS, WORLD, tracker_env

from agent.errors import UmaError

EYE_B = [0.03, 0.06, 0.05]
EYE_C = [0.04, 0.05, 0.06]


def _config(tmp_path, name: str, position: list[float]) -> str:
    cfg = tmp_path / f"{name}.toml"
    cfg.write_text(f'[[static]]\nparent = "{HEAD}"\nchild = "{EYE}"\nposition = {position}\n'
                   "quaternion = [0.0, 0.0, 0.0, 1.0]\npos_std_m = 0.001\n")
    return str(cfg)


@pytest.fixture
def world(processes, tmp_path, realm):
    """Agents A (skewed, with the tracker), B and C; their endpoints, the tracker's pause
    file and the agent processes by id."""
    ports = {name: free_port() for name in "ABC"}
    eps = {name: endpoint(p) for name, p in ports.items()}
    commands = [(agent_command(realm, "A", eps["A"]), ())]
    for name, eye in (("B", EYE_B), ("C", EYE_C)):
        commands.append((agent_command(realm, name, eps[name], (eps["A"],),
                                       ("--config", _config(tmp_path, name, eye))), ()))
    procs = start_agents(processes, commands, env={"UMA_CLOCK_SKEW_NS": str(SKEW_NS), **LEASE})
    pause = tmp_path / "pause"
    processes.start("--realm", realm, "--agent", "A", "--connect", eps["A"], "--t0",
                    str(time.time_ns()), "--skew", str(SKEW_NS), "--pause-file", str(pause),
                    module="test_client_stream", env=tracker_env())
    return eps, pause, dict(zip("ABC", procs, strict=True))


def _samples(kept) -> int:
    return sum(e.get("samples", 0) for e in kept.graph.edges())


def _same(a, b) -> None:
    """Two answers equal to 1e-12: pose, covariance, time, path, extrapolation."""
    np.testing.assert_allclose(a.position, b.position, rtol=0, atol=1e-12)
    np.testing.assert_allclose(a.quaternion, b.quaternion, rtol=0, atol=1e-12)
    np.testing.assert_allclose(a.covariance, b.covariance, rtol=0, atol=1e-12)
    assert (a.t_ns, a.path, a.extrapolated_s) == (b.t_ns, b.path, b.extrapolated_s)


def test_kept_answers_equal_the_agents_and_fall_back_outside_the_buffer(world, realm):
    from agent.sdk.client import Client

    eps, pause, _ = world
    with Client(realm=realm, connect=[eps["A"]], timeout=2.0) as c:
        poll(lambda: c.pose(WORLD, EYE), what="a pose across A and B or C")
        with pytest.raises(ValueError, match="buffer_s must be a positive number"):
            c.keep(WORLD, EYE, buffer_s=0)
        kept = c.keep(WORLD, EYE, buffer_s=1.0, stall_s=0.5)
        assert kept.clock_agent == "A" and kept.on_pose is None
        # nothing waits for a kept route's samples: no thread is woken per sample
        assert "uma-subscription" not in {t.name for t in threading.enumerate()}
        poll(lambda: _samples(kept) >= 60, what="60 samples kept")
        poll(lambda: c.pose(WORLD, EYE, at=time.time_ns() - 1_600_000_000),
             what="the tracker's first 1.6 s")
        c.clock.add = lambda *args: None  # the same offsets for both answers from here on
        now = time.time_ns()
        for back_ms in (150, 230, 310, 470):
            at = now - back_ms * 1_000_000
            answered = kept.answered
            mine = c.pose(WORLD, EYE, at=at)
            assert kept.answered == answered + 1, "not answered from the kept route"
            _same(mine, c.queries.ask(WORLD, EYE, at, "latency").pose)
            assert mine.t_ns == at and mine.covariance is not None
        latest = c.pose(WORLD, EYE)  # the latest time the mirror holds, answered here too
        assert kept.answered == answered + 2 and latest.t_ns > now - 500_000_000
        # older than the kept second: the agents answer (they keep 10 s)
        answered = kept.answered
        before = now - 1_500_000_000
        assert c.pose(WORLD, EYE, at=before).t_ns == before
        assert kept.answered == answered
        # a time nobody has reached: the agents are asked, and say so
        with pytest.raises(LookupError, match="not yet arrived"):
            c.pose(WORLD, EYE, at=time.time_ns() + 5_000_000_000)
        assert kept.answered == answered
        # a silent tracker: the stalled route is left to the agents until samples return
        pause.touch()
        poll(lambda: kept.status == "stalled", what="status 'stalled'")
        c.pose(WORLD, EYE, at=time.time_ns() - 1_200_000_000)
        assert kept.answered == answered
        pause.unlink()
        poll(lambda: kept.status == "streaming", what="streaming again")
        poll(lambda: c.pose(WORLD, EYE) is not None and kept.answered > answered,
             what="answered from the kept route again")
        kept.close()
        answered = kept.answered
        c.pose(WORLD, EYE)
        assert kept.answered == answered and kept.status == "closed"


def test_a_kept_route_follows_its_agents(world, realm, processes):
    """The agent of the static segment leaves: the route moves to the other one and the
    kept answers with it; the tracker's agent leaves: no route, nothing answered here."""
    from agent.sdk.client import Client

    eps, _, procs = world
    with Client(realm=realm, connect=[eps["A"]], timeout=2.0) as c:
        poll(lambda: c.pose(WORLD, EYE), what="a pose across A and B or C")
        kept = c.keep(WORLD, EYE, buffer_s=2.0)
        poll(lambda: _samples(kept) >= 20, what="20 samples kept")
        first = kept.route[-1].agent
        other, eye = ("C", EYE_C) if first == "B" else ("B", EYE_B)
        processes.kill(procs[first].popen)
        poll(lambda: kept.route[-1].agent == other and kept.status == "streaming",
             what=f"the route through {other}")
        assert kept.replans >= 1
        poll(lambda: _samples(kept) >= 20, what="20 samples kept on the new route")
        at = time.time_ns() - 100_000_000
        answered = kept.answered
        r = c.pose(WORLD, EYE, at=at)
        assert kept.answered == answered + 1
        head = c.pose(WORLD, HEAD, at=at)  # no kept route of its own: asked of A
        np.testing.assert_allclose(r.position, head.matrix[:3, :3] @ eye + head.position,
                                   atol=1e-9)
        processes.kill(procs["A"].popen)
        poll(lambda: kept.status == "no route", what="no route once A left")
        with pytest.raises((LookupError, UmaError)):
            c.pose(WORLD, EYE, at=at)
        assert kept.answered == answered + 1
