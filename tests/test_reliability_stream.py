"""A streaming subscription follows its route: the agent of the route in use dies, and the
poses keep coming over the other route; a better route appears, and it moves to it; with no
route left it says so, and it resumes when a route comes back.

Agents A and B both know ``ivy/world -> marvin/rig`` (A's survey is the more accurate);
agent C hosts a tracker (this file run as a script) publishing ``marvin/rig -> alice/head``
at 100 Hz.  The composed position tells which route a pose came over.
"""

from __future__ import annotations

import signal
import sys
import threading
import time

WORLD, RIG, HEAD = "ivy/world", "marvin/rig", "alice/head"
HEAD_IN_RIG = [0.0, 0.0, 0.12]
RIG_IN_WORLD = {"A": ([1.0, 0.0, 0.0], 0.001), "B": ([0.0, 1.0, 0.0], 0.05)}


def run_tracker(argv: list[str]) -> int:
    """A tracker on RIG -> HEAD at 100 Hz, registered with agent ``--agent``."""
    from agent_helpers.tracker import options, pose_tracker, publish_until

    with pose_tracker(options(argv), (RIG, HEAD)) as (_, out, stop):
        publish_until(out, stop, lambda t: (HEAD_IN_RIG, [0.0, 0.0, 0.0, 1.0]))
    return 0


if __name__ == "__main__":
    sys.exit(run_tracker(sys.argv[1:]))


import numpy as np  # noqa: E402
from agent_helpers.harness import agent, freeze, spawn  # noqa: E402
from conftest import endpoint, free_port  # noqa: E402

from agent.sdk.client import Client  # noqa: E402

WAIT_S = 20.0


def config(tmp_path, name: str) -> str:
    p, std = RIG_IN_WORLD[name]
    path = tmp_path / f"{name}.toml"
    path.write_text(f'[[static]]\nparent = "{WORLD}"\nchild = "{RIG}"\nposition = {p}\n'
                    f"quaternion = [0.0, 0.0, 0.0, 1.0]\npos_std_m = {std}\n")
    return str(path)


class Poses:
    """What the subscription delivered, and when (bounded waits on new deliveries)."""

    def __init__(self) -> None:
        self.got: list = []
        self.errors: list[Exception] = []
        self.cond = threading.Condition()
        self.sub = None  # the subscription, named in a failure

    def on_pose(self, r) -> None:
        with self.cond:
            self.got.append(r)
            self.cond.notify_all()

    def on_error(self, exc: Exception) -> None:
        with self.cond:
            self.errors.append(exc)
            self.cond.notify_all()

    def wait(self, test, what: str, timeout: float = WAIT_S):
        deadline = time.monotonic() + timeout
        with self.cond:
            while not test():
                left = deadline - time.monotonic()
                if left <= 0:
                    last = self.got[-1].position if self.got else None
                    state = (None if self.sub is None
                             else (self.sub.status, self.sub.last_error))
                    raise AssertionError(f"{what} not seen within {timeout} s ({len(self.got)} "
                                         f"poses, last at {last}; errors {self.errors}; "
                                         f"subscription's status and last error {state})")
                self.cond.wait(min(left, 0.2))

    def via(self, names: str, after: int, count: int = 20) -> None:
        """``count`` poses delivered after index ``after`` over the route of agent ``names``
        (or of any of several, e.g. "AB")."""
        def enough() -> bool:
            return sum(route in names for route in self.routes(after)) >= count
        self.wait(enough, f"{count} poses over the route of agent {' or '.join(names)}")

    def routes(self, after: int) -> list[str]:
        """Over whose route (agent A's or B's survey, "?" neither) each pose delivered
        after index ``after`` came."""
        return [next((name for name, (p, _) in RIG_IN_WORLD.items()
                      if np.allclose(r.position, np.add(p, HEAD_IN_RIG), atol=1e-9)), "?")
                for r in self.got[after:]]


def start_site(processes, realm: str, tmp_path) -> tuple[dict, dict]:
    """Agents C (with the tracker), A and B (each with its survey): processes (the
    tracker's under "tracker"), endpoints."""
    ep = {name: endpoint(free_port()) for name in "ABC"}
    procs = {"C": agent(processes, realm, "C", ep["C"])}
    for name in "AB":
        procs[name] = agent(processes, realm, name, ep[name], connect=(ep["C"],),
                            extra=("--config", config(tmp_path, name)))
    procs["tracker"] = start_tracker(processes, realm, ep["C"])
    return procs, ep


def start_tracker(processes, realm: str, ep: str):
    return spawn(processes, [__file__, "--realm", realm, "--agent", "C", "--connect", ep])


def subscribe_via_a(client: Client, poses: Poses):
    """A subscription on the better route, over A and C (once the realm is complete)."""
    deadline = time.monotonic() + WAIT_S
    while True:  # until the tracker's edge and both surveys are in the realm
        try:
            sub = client.subscribe(WORLD, HEAD, on_pose=poses.on_pose,
                                   on_error=poses.on_error, error="accuracy")
            if [s.agent for s in sub.route] == ["A", "C"]:
                poses.sub = sub
                poses.via("A", 0)
                return sub
            sub.close()
        except LookupError:
            if time.monotonic() > deadline:
                raise
        assert time.monotonic() < deadline, "no route over A and C"
        time.sleep(0.2)


def test_subscription_follows_its_route_when_an_agent_dies_and_comes_back(
        processes, realm, tmp_path, monkeypatch) -> None:
    # a long lease: only the killed agents may look gone (a SIGKILL is seen at once)
    monkeypatch.setenv("UMA_LEASE_MS", "5000")
    procs, ep = start_site(processes, realm, tmp_path)
    poses = Poses()
    with Client(realm=realm, connect=[ep["C"]], timeout=2.0) as client:
        sub = subscribe_via_a(client, poses)

        # the route's agent dies: the other route takes over
        procs["A"].popen.kill()
        procs["A"].popen.wait(10)
        mark = len(poses.got)
        poses.via("B", mark)
        assert [s.agent for s in sub.route] == ["B", "C"] and sub.status == "streaming"
        assert sub.replans >= 1 and poses.errors == []

        # a better route appears (A restarts): the stream moves back to it
        procs["A"] = agent(processes, realm, "A", ep["A"], connect=(ep["C"],),
                           extra=("--config", config(tmp_path, "A")))
        poses.via("A", len(poses.got))
        assert [s.agent for s in sub.route] == ["A", "C"] and poses.errors == []

        # the route's agents die but its samples still arrive (the tracker's agent lives):
        # no new plan, but the working stream goes on over a mirrored route.  Which one:
        # the subscription moves to B's within some 50 ms of A's death, and on a loaded
        # machine B may die later than that; once both are gone, its poses come over the
        # route it names, and over that one alone
        for name in "AB":
            procs[name].popen.kill()
            procs[name].popen.wait(10)
        mark = len(poses.got)
        poses.via("AB", mark, count=200)  # 2 s at 100 Hz: longer than a lease
        named, mark = sub.route[0].agent, len(poses.got)
        poses.via(named, mark)
        assert set(poses.routes(mark)) == {named}, (named, poses.routes(mark))
        assert sub.status == "streaming" and poses.errors == []

        # and its samples stop too: no route, reported once
        procs["tracker"].popen.kill()
        procs["tracker"].popen.wait(10)
        poses.wait(lambda: poses.errors, "on_error")
        assert sub.status == "no route"
        # the last planning failure is reported: the tracker's frame is gone (or, if its
        # departure was not known yet, the dead agents' segment)
        assert isinstance(poses.errors[0], LookupError) and any(
            text in str(poses.errors[0]) for text in ("alice/head", "ivy/world -> marvin/rig")
        ), poses.errors
        quiet = len(poses.got)  # the tracker is dead: nothing more can come

        # a route comes back (B and the tracker restart): the stream resumes over it
        agent(processes, realm, "B", ep["B"], connect=(ep["C"],),
              extra=("--config", config(tmp_path, "B")))
        start_tracker(processes, realm, ep["C"])
        poses.via("B", quiet)
        assert sub.status == "streaming" and len(poses.errors) == 1
        sub.close()
        assert sub.status == "closed"


def test_an_agent_that_was_only_slow_gets_the_stream_back(
        processes, realm, tmp_path, monkeypatch) -> None:
    """Agent A freezes for a few seconds, well within its lease: a query finds it silent and
    goes over B, and the stream follows; once A answers the client's probe again the stream
    moves back to the better route over A."""
    monkeypatch.setenv("UMA_LEASE_MS", "20000")  # A keeps its token while frozen
    procs, ep = start_site(processes, realm, tmp_path)
    poses = Poses()
    with Client(realm=realm, connect=[ep["C"]], timeout=2.0) as client:
        sub = subscribe_via_a(client, poses)
        client.cache_static_segments = False  # else A's static segment is not asked for
        freeze(procs["A"])
        try:
            # asked of the agents (client.pose would answer from the subscription's
            # mirror): A does not answer, so over B
            r = client.queries.ask(WORLD, HEAD, None, "accuracy").pose
            assert [e["owner"] for e in r.edges] == ["B", "C"], r.edges
            assert client.agents()["A"]["alive"] is False
            poses.via("B", len(poses.got))
        finally:
            procs["A"].popen.send_signal(signal.SIGCONT)
        poses.via("A", len(poses.got))
        assert [s.agent for s in sub.route] == ["A", "C"] and sub.status == "streaming"
        assert sub.replans >= 2 and poses.errors == []
