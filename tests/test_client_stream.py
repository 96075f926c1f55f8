"""Streaming subscriptions across agents, and a deliberately skewed agent clock.

Agent ``A`` runs with ``UMA_CLOCK_SKEW_NS`` (its clock 3 s ahead) and hosts a tracker
service (this file run as a script) that publishes an analytic head trajectory stamped with
the same skewed clock, as a service on a skewed host would.  Agent ``B`` holds a static
edge head -> eye.  The client must estimate A's offset and answer on its own clock.
"""

from __future__ import annotations

import argparse
import os
import sys
import threading
import time
from pathlib import Path

import numpy as np
import pytest
from agent_helpers.harness import agent, poll
from conftest import endpoint, free_port

from agent import geometry as geo

WORLD, HEAD, EYE = "ivy/world", "alice/head", "alice/eye"
SKEW_NS = 3_000_000_000
EYE_P, EYE_Q = [0.03, 0.06, 0.05], geo.rotvec_to_quat(np.array([0.0, 0.2, 0.0])).tolist()
#: a lease longer than the default 1 s: on a loaded CI machine a process stalled for a
#: second would otherwise lose its links and its tokens (not what these tests are about)
LEASE = {"UMA_LEASE_MS": "5000"}


def motion(t_s: float) -> tuple[np.ndarray, np.ndarray]:
    """Constant velocity and body rate: lerp + slerp reproduce it exactly."""
    p = np.array([0.2, 0.1, 1.6]) + np.array([0.05, -0.02, 0.01]) * t_s
    q = geo.quat_multiply(geo.rotvec_to_quat(np.array([0.0, 0.0, 0.3])),
                          geo.rotvec_to_quat(np.array([0.1, 0.4, -0.2]) * t_s))
    return p, q


def expected_eye(t_real_ns: int, t0_ns: int) -> np.ndarray:
    p, q = motion((t_real_ns - t0_ns) / 1e9)
    return geo.to_matrix(p, q) @ geo.to_matrix(np.array(EYE_P), np.array(EYE_Q))


def run_tracker(argv: list[str]) -> None:
    """The tracker service: publishes ``motion`` at 100 Hz on world -> head, its stamps
    ``--skew`` ns off (a tracker on a skewed host clock)."""
    from agent_helpers.tracker import options, pose_tracker, publish_until

    def extra(ap: argparse.ArgumentParser) -> None:
        ap.add_argument("--t0", type=int, required=True)
        ap.add_argument("--skew", type=int, default=0)
        ap.add_argument("--seconds", type=float, default=60.0)
        ap.add_argument("--pause-file", type=Path, default=None,
                        help="publish nothing while this file exists")
    a = options(argv, extra)
    paused = (lambda: a.pause_file.exists()) if a.pause_file else None
    with pose_tracker(a, (WORLD, HEAD)) as (_, out, stop):
        publish_until(out, stop, lambda t: motion((t - a.t0) / 1e9), a.seconds, a.skew,
                      paused)


def tracker_env() -> dict[str, str]:
    return {"PYTHONPATH": os.pathsep.join([str(Path(__file__).parent), *sys.path]), **LEASE}


@pytest.fixture
def skewed_world(processes, tmp_path, realm):
    pa, pb = free_port(), free_port()
    cfg = tmp_path / "b.toml"
    cfg.write_text(f'[[static]]\nparent = "{HEAD}"\nchild = "{EYE}"\nposition = {EYE_P}\n'
                   f"quaternion = {EYE_Q}\npos_std_m = 0.001\n")
    # each agent up (and started once more if its Zenoh session stalled) before the next
    agent(processes, realm, "A", endpoint(pa), env={"UMA_CLOCK_SKEW_NS": str(SKEW_NS), **LEASE})
    agent(processes, realm, "B", endpoint(pb), connect=(endpoint(pa),),
          extra=("--config", str(cfg)), env=LEASE)
    t0 = time.time_ns()
    processes.start("--realm", realm, "--agent", "A", "--connect", endpoint(pa),
                    "--t0", str(t0), "--skew", str(SKEW_NS), module="test_client_stream",
                    env=tracker_env())
    return [endpoint(pa), endpoint(pb)], t0


def test_skewed_agent_clock_is_estimated_and_applied(skewed_world, realm):
    from agent.sdk.client import Client

    eps, t0 = skewed_world
    with Client(realm=realm, connect=eps[1:], timeout=2.0) as c:
        poll(lambda: c.pose(WORLD, EYE), what="a pose across A and B")
        # round trips for the minimum-delay filter (its window is 16): through the client's
        # agent each has one more hop, so on a loaded machine a few may all be skewed
        for _ in range(15):
            c.pose(WORLD, EYE)
        at = time.time_ns() - 50_000_000  # 50 ms ago on the client's (unskewed) clock
        r = c.pose(WORLD, EYE, at=at, error="hops")
        assert abs(c.clock.offset("A") - SKEW_NS) < 20_000_000  # loaded CI: within 20 ms
        assert r.t_ns == at and r.path == [WORLD, HEAD, EYE]
        # the answer is the pose at `at`, not 3 s away from it: the eye moves < 0.1 m/s,
        # so 2 mm allows ~20 ms of offset error while an uncorrected 3 s skew is ~0.2 m off
        T = expected_eye(at, t0)
        np.testing.assert_allclose(r.position, T[:3, 3], atol=2e-3)
        assert np.linalg.norm(expected_eye(at + SKEW_NS, t0)[:3, 3] - T[:3, 3]) > 0.05
        # the remote timestamps came back on our clock too (the sample after `at`: 10 ms
        # later at 100 Hz, more if the loaded machine delayed the tracker)
        assert -20_000_000 < r.edges[0]["t_ns"] - at < 300_000_000
        # a time the tracker has not reached: the error names the agent's segment, the edge
        # and why (the data has not arrived yet)
        with pytest.raises(LookupError, match=r"ivy/world -> alice/head of agent 'A'.*"
                                              r"tracker/head.*not yet arrived"):
            c.pose(WORLD, EYE, at=time.time_ns() + 10_000_000_000, error="hops")


def test_streaming_delivers_composed_poses_as_the_edges_update(skewed_world, realm):
    from agent.sdk.client import Client

    eps, t0 = skewed_world
    got: list = []
    enough = threading.Event()

    def on_pose(r):
        got.append(r)
        if len(got) >= 20:
            enough.set()

    with Client(realm=realm, connect=eps[1:], timeout=2.0) as c:
        poll(lambda: c.pose(WORLD, EYE), what="a pose across A and B")
        sub = c.subscribe(WORLD, EYE, on_pose=on_pose, error="hops")
        assert enough.wait(10.0), f"only {len(got)} poses streamed ({sub.last_error})"
        sub.close()
        count = len(got)
        # a second subscription to the same poses as witness: once it has had five, the
        # closed one would have had more too if it still pushed
        witnessed = threading.Semaphore(0)
        witness = c.subscribe(WORLD, EYE, on_pose=lambda r: witnessed.release(), error="hops")
        assert all(witnessed.acquire(timeout=10.0) for _ in range(5)), witness.last_error
        witness.close()
        assert len(got) <= count + 1  # closed: no more pushes (one may have been under way)
    times = [r.t_ns for r in got]
    assert times == sorted(times) and len(set(times)) == len(times)  # one per new sample
    for r in got:
        assert r.path == [WORLD, HEAD, EYE]
        T = expected_eye(r.t_ns, t0)
        np.testing.assert_allclose(r.position, T[:3, 3], atol=1e-6 + 2e-3)
        assert r.covariance is not None
    # pushed at sample times: the pulled static edge needs no extrapolation
    assert all(r.extrapolated_s == 0.0 for r in got)


def test_a_silent_route_is_reported_as_stalled_and_streams_again(processes, realm, tmp_path):
    """The tracker stays alive (its route with it) but publishes nothing: no other route would
    do better, so the subscription stays, says "stalled" once, and resumes by itself."""
    from agent.sdk.client import Client
    from agent.sdk.subscription import STALL_MIN_S

    ep = endpoint(free_port())
    agent(processes, realm, "A", ep, env=LEASE)
    pause = tmp_path / "pause"
    processes.start("--realm", realm, "--agent", "A", "--connect", ep, "--t0",
                    str(time.time_ns()), "--pause-file", str(pause),
                    module="test_client_stream", env=tracker_env())
    got: list = []
    errors: list = []
    with Client(realm=realm, connect=[ep], timeout=2.0) as c:
        poll(lambda: c.pose(WORLD, HEAD), what="the tracker's edge")
        with pytest.raises(ValueError, match="stall_s must be a positive number"):
            c.subscribe(WORLD, HEAD, on_pose=got.append, stall_s=0)
        default = c.subscribe(WORLD, HEAD, on_pose=lambda r: None)
        assert default.stall_limit_s == STALL_MIN_S  # 10 periods of 100 Hz are less
        default.close()
        sub = c.subscribe(WORLD, HEAD, on_pose=got.append, on_error=errors.append,
                          error="hops", stall_s=1.0)
        poll(lambda: len(got) >= 20, what="20 poses")
        stalls = sub.stalls  # a loaded machine may already have paused the tracker once
        pause.touch()
        poll(lambda: sub.status == "stalled", what="status 'stalled'")
        assert sub.stalls > stalls and sub.route[0].agent == "A"
        assert "no sample of its fastest edge ivy/world -> alice/head for" in str(
            sub.last_error) and "(A) are alive" in str(sub.last_error)
        quiet = len(got)
        pause.unlink()
        poll(lambda: sub.status == "streaming" and len(got) >= quiet + 20,
             what="streaming again")
        assert errors == []  # not an outage of the route: on_error is not told
        sub.close()
        assert sub.status == "closed"


if __name__ == "__main__":
    run_tracker(sys.argv[1:])
