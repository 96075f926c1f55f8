"""Pose queries whose path crosses three agent processes, and what happens when the middle
one is killed: another route if one exists, else an error naming the missing segment."""

from __future__ import annotations

import contextlib
import json
import signal
import subprocess
import sys
from collections.abc import Iterator
from pathlib import Path

import numpy as np
import pytest
from agent_helpers.harness import agent, poll, uma_here
from conftest import endpoint, free_port

from agent import geometry as geo
from agent.sdk.client import Client
from agent.sdk.planner import RouteError

WORLD, CAM, RIG, IMU, HEAD = "ivy/world", "cam/nw", "marvin/rig", "marvin/imu", "alice/head"
Q_CAM = geo.rotvec_to_quat(np.array([0.1, -0.4, 0.2])).tolist()
Q_RIG = geo.rotvec_to_quat(np.array([0.0, 0.3, -0.1])).tolist()
Q_HEAD = geo.rotvec_to_quat(np.array([0.5, 0.0, 0.0])).tolist()
# the agents' static edges: (parent, child, position, quaternion, pos_std_m, rot_std_rad)
EDGES = {
    "A": [(WORLD, CAM, [1.2, -0.5, 2.3], Q_CAM, 0.01, 0.002)],
    "B": [(CAM, RIG, [0.3, 0.8, -1.1], Q_RIG, 0.002, 0.001),
          (RIG, IMU, [0.0, 0.05, 0.0], [0, 0, 0, 1], 0.001, None)],
    "C": [(RIG, HEAD, [0.0, 0.0, 0.12], Q_HEAD, 0.003, None)],
}
# C's survey of the rig in the world: a worse route that avoids B
SURVEY = (WORLD, RIG, None, None, 0.05, 0.02)


def write_config(path: Path, edges) -> Path:
    lines = []
    for parent, child, p, q, pos_std, rot_std in edges:
        lines += ["[[static]]", f'parent = "{parent}"', f'child = "{child}"',
                  f"position = {list(map(float, p))}", f"quaternion = {list(map(float, q))}"]
        if pos_std is not None:
            lines.append(f"pos_std_m = {pos_std}")
        if rot_std is not None:
            lines.append(f"rot_std_rad = {rot_std}")
    path.write_text("\n".join(lines) + "\n")
    return path


def chain(edges):
    """Expected pose and covariance: compose edge by edge with geometry's functions."""
    p, q, cov = np.zeros(3), geo.quat_identity(), None
    for _, _, ep, eq, pos_std, rot_std in edges:
        ep, eq = np.array(ep, float), np.array(eq, float)
        cov = geo.compose_covariance(p, q, cov, geo.covariance_from_std(ep, pos_std, rot_std))
        p, q = geo.compose(p, q, ep, eq)
    return p, q, cov


def survey_edge():
    p, q, _ = chain([EDGES["A"][0], EDGES["B"][0]])
    return (SURVEY[0], SURVEY[1], (p + 0.02).tolist(), q.tolist(), SURVEY[4], SURVEY[5])


def start_agents(processes, tmp_path, realm, configs):
    """Each agent up (the harness waits for it, and starts a stalled one once more) before
    the next; the first is everybody's peer."""
    ports = {name: free_port() for name in configs}
    procs = {}
    first = None
    for name, edges in configs.items():
        # a 5 s lease: a loaded machine must not make a stalled agent look gone (a killed
        # one is still seen at once: its sockets close)
        procs[name] = agent(processes, realm, name, endpoint(ports[name]),
                            connect=() if first is None else (endpoint(ports[first]),),
                            extra=("--config", str(write_config(tmp_path / f"{name}.toml",
                                                                edges))),
                            env={"UMA_LEASE_MS": "5000"}).popen
        first = first or name
    return procs, [endpoint(p) for p in ports.values()]


@pytest.fixture
def three_agents(processes, tmp_path, realm):
    configs = {"A": EDGES["A"], "B": EDGES["B"], "C": [*EDGES["C"], survey_edge()]}
    procs, eps = start_agents(processes, tmp_path, realm, configs)
    return procs, eps


def test_query_across_three_agents_and_reroute_when_the_middle_one_dies(
        three_agents, realm, processes):
    procs, eps = three_agents
    with Client(realm=realm, connect=eps[:1], timeout=2.0) as c:
        def across():
            r = c.pose(WORLD, HEAD, error="accuracy")
            assert r.path == [WORLD, CAM, RIG, HEAD], r.path
            return r
        r = poll(across, what="a route across A, B and C")
        p, q, cov = chain([EDGES["A"][0], EDGES["B"][0], EDGES["C"][0]])
        np.testing.assert_allclose(r.position, p, atol=1e-12)
        assert geo.quat_angle(r.quaternion, q) < 1e-9
        np.testing.assert_allclose(r.covariance, cov, rtol=1e-9, atol=1e-18)
        assert [e["owner"] for e in r.edges] == ["A", "B", "C"]
        assert r.attributes["hops"] == 3 and r.attributes["static"] is True
        # the fewest hops go through C's survey alone
        assert c.pose(WORLD, HEAD, error="hops").path == [WORLD, RIG, HEAD]

        procs["B"].send_signal(signal.SIGKILL)
        procs["B"].wait(timeout=10)

        def rerouted():
            r = c.pose(WORLD, HEAD, error="accuracy")
            assert r.path == [WORLD, RIG, HEAD], r.path
            return r
        r = poll(rerouted, what="the route around B")
        p, q, cov = chain([survey_edge(), EDGES["C"][0]])
        np.testing.assert_allclose(r.position, p, atol=1e-12)
        np.testing.assert_allclose(r.covariance, cov, rtol=1e-9, atol=1e-18)
        # only B knew the IMU: every route needs it, and once the client has seen B leave
        # (its token's removal can lag on a loaded machine) the error says which segment
        def b_left():
            assert not c.agents()["B"]["alive"]
        poll(b_left, what="B's departure seen by the client")
        with pytest.raises(RouteError,
                           match=r"segment\(s\) \S+ -> marvin/imu of agent 'B'.*left the realm"):
            c.pose(WORLD, IMU, error="accuracy")


def test_uma_query_command(three_agents, realm):
    _, eps = three_agents
    cmd = [sys.executable, "-m", "agent.cli", "query", WORLD, HEAD, "--realm", realm,
           "--error", "accuracy", "--json", "--connect", eps[0]]

    def run():
        out = subprocess.run(cmd, capture_output=True, text=True, timeout=30)
        if out.returncode != 0:
            raise LookupError(out.stderr)
        d = json.loads(out.stdout.strip().splitlines()[-1])
        if d["path"] != [WORLD, CAM, RIG, HEAD]:
            raise LookupError(f"path {d['path']}")
        return d
    d = poll(run, what="uma query across three agents")
    p, _, cov = chain([EDGES["A"][0], EDGES["B"][0], EDGES["C"][0]])
    np.testing.assert_allclose(d["position"], p, atol=1e-12)
    np.testing.assert_allclose(np.array(d["covariance"]), cov, rtol=1e-9, atol=1e-18)
    bad = subprocess.run([*cmd[:4], WORLD, "nowhere/frame", *cmd[6:]], capture_output=True,
                         text=True, timeout=30)
    assert bad.returncode == 1
    assert "unknown frame 'nowhere/frame'" in bad.stderr and "ivy/world" in bad.stderr
    assert "Traceback" not in bad.stderr


@contextlib.contextmanager
def zenoh_peer(ep: str) -> Iterator[None]:
    """A bare Zenoh peer listening on ``ep``: reachable, but no agent of any realm."""
    from agent.runtime.session import open_session
    s = open_session("peer", [ep], [])
    try:
        yield
    finally:
        s.close()


def test_uma_query_without_agents_is_a_clear_error(realm):
    ep = endpoint(free_port())
    out = uma_here("query", WORLD, HEAD, "--realm", realm, "--timeout", "0.3", "--connect", ep)
    assert out.returncode == 1
    # a client of its host's agent: nothing at the endpoint is named as such
    assert f"cannot reach {ep}" in out.stderr and "is the agent" in out.stderr
    assert "Traceback" not in out.stderr
    # a listening peer that finds the endpoint but no agent of the realm says so
    with zenoh_peer(ep):
        out = uma_here("query", WORLD, HEAD, "--realm", realm, "--timeout", "0.3", "--connect",
                       ep)
    assert out.returncode == 1
    assert f"no agent answered in realm {realm!r}" in out.stderr and "Traceback" not in out.stderr
    bad = uma_here("query", WORLD, HEAD, "--at", "yesterday")
    assert bad.returncode == 1 and "--at 'yesterday'" in bad.stderr
