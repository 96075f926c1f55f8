"""A service's liveliness token lost while the service runs on (issue: "service tracker left
agent C" with the tracker alive, and its SRG edge never fed again).

On a loaded machine a transport whose lease expires between starved processes is closed and
re-established: the agent sees the service token's DELETE then its PUT, and these can reach
the agent's worker out of order with the service's own re-registration.  Here the tracker
(this file run as a script) drops its token (and, in the second case, its descriptor
queryable too) and declares it again, without re-registering: what the agent sees in that
failure, made deterministic.  The agent must keep a service that still answers, and re-adopt
one whose token comes back after it dropped it.
"""

from __future__ import annotations

import sys
import threading
import time

from agent_helpers.svc import emit

WORLD, HEAD = "ivy/world", "alice/head"


def flap(svc, gap_s: float, with_queryable: bool) -> None:
    """Undeclare the service's token (and its descriptor queryable), wait, declare them again.

    Reaches into the SDK's private declarations on purpose: no public API drops a token of a
    running service, which is exactly the failure being simulated.
    """
    import zenoh

    from agent.protocol import keys
    key = keys.service_token(svc.realm, svc.agent_id, svc.service_id)
    queryables = [d for d in svc._decls if isinstance(d, zenoh.Queryable)]
    assert len(queryables) == 1, svc._decls
    if with_queryable:  # first, so that the agent's check finds nobody
        queryables[0].undeclare()
    svc.presence.token.undeclare()
    time.sleep(gap_s)
    if with_queryable:
        fresh = svc.session.declare_queryable(
            key, lambda q: svc._enqueue(svc.presence.on_descriptor_query, q))
        svc._decls[svc._decls.index(queryables[0])] = fresh
    svc.presence.token = svc.session.liveliness().declare_token(key)


def run_tracker(argv: list[str]) -> int:
    """A tracker on WORLD -> HEAD at 100 Hz; stdin ``flap-token GAP`` / ``flap-all GAP``."""
    from agent_helpers.tracker import options, pose_tracker, publish_until

    with pose_tracker(options(argv), (WORLD, HEAD)) as (svc, out, stop):
        emit(event="started", registered=svc.wait_registered(10.0))

        def commands() -> None:
            for line in sys.stdin:
                words = line.split()
                if len(words) == 2 and words[0] in ("flap-token", "flap-all"):
                    flap(svc, float(words[1]), words[0] == "flap-all")
                    emit(event="flapped", command=words[0], t_ns=time.time_ns())
        threading.Thread(target=commands, daemon=True).start()
        publish_until(out, stop, lambda t: ([0.1, 0.2, 1.6], [0.0, 0.0, 0.0, 1.0]))
    return 0


if __name__ == "__main__":
    sys.exit(run_tracker(sys.argv[1:]))


from agent_helpers.harness import agent, matched_to, service, spawn  # noqa: E402
from conftest import endpoint, free_port  # noqa: E402

from agent.daemon.agent import STARTUP_HOLD_S  # noqa: E402
from agent.errors import UmaError  # noqa: E402
from agent.sdk.client import Client  # noqa: E402


def fresh_pose(client: Client, since_ns: int, timeout: float = 20.0):
    """A pose of HEAD from agent C's SRG whose sample is newer than ``since_ns``."""
    deadline = time.monotonic() + timeout
    last: object = None
    for _ in range(400):
        try:
            r = client.pose(WORLD, HEAD, error="hops")
            if [e["owner"] for e in r.edges] == ["C"] and r.edges[0]["t_ns"] > since_ns:
                return r
            last = f"edges {r.edges}: no sample of agent C after {since_ns}"
        except (LookupError, UmaError) as exc:
            last = exc
        if time.monotonic() > deadline:
            break
        time.sleep(0.1)
    raise AssertionError(f"agent C's SRG not fed again within {timeout} s: {last}")


def test_lost_token_of_a_live_service_is_kept_or_readopted(processes, realm,
                                                            monkeypatch) -> None:
    # a long lease, so that only the simulated token loss happens (no real expiry)
    monkeypatch.setenv("UMA_LEASE_MS", "5000")
    ep = {name: endpoint(free_port()) for name in "ABC"}
    agent(processes, realm, "A", ep["A"])
    a_up = time.monotonic()
    agent(processes, realm, "B", ep["B"], connect=(ep["A"],))
    agent_c = agent(processes, realm, "C", ep["C"], connect=(ep["A"],))
    tracker = spawn(processes, [__file__, "--realm", realm, "--agent", "C",
                                "--connect", ep["C"]])
    assert tracker.wait_for(lambda e: e.get("event") == "started")["registered"]
    consumer = service(processes, realm, "fusion", "A", ep["A"], "--need", "head")
    consumer.wait_for(lambda e: matched_to(e, "head", "tracker"))

    with Client(realm=realm, connect=[ep["B"]], timeout=2.0) as client:
        fresh_pose(client, 0)

        # 1. the token goes and comes back while the service answers all along: kept
        tracker.send("flap-token 0.3")
        done = tracker.wait_for(lambda e: e.get("event") == "flapped")
        fresh_pose(client, done["t_ns"])
        agent_c.wait_log("still answers; kept")
        assert not [line for line in agent_c.log if "left agent C" in line]

        # 2. token and queryable gone (unreachable), then back: dropped, then re-adopted.
        # Agent A must be past its start-up hold, or it keeps the consumer's connection
        time.sleep(max(0.0, STARTUP_HOLD_S + 0.2 - (time.monotonic() - a_up)))
        mark = consumer.mark
        tracker.send("flap-all 0.5")
        done = tracker.wait_for(lambda e: e.get("event") == "flapped"
                                and e["command"] == "flap-all")
        agent_c.wait_log("service tracker left agent C")
        agent_c.wait_log("service tracker re-adopted by agent C")
        fresh_pose(client, done["t_ns"])
        # the remote consumer (which saw the DELETE as well) is matched and fed
        consumer.wait_for(lambda e: matched_to(e, "head", "tracker"), after=mark)
        mark = consumer.mark
        base = max([e["counts"].get("tracker", 0) for e in consumer.events[:mark]
                    if e.get("event") == "counts"], default=0)
        consumer.wait_for(lambda e: e.get("event") == "counts"
                          and e["counts"].get("tracker", 0) > base + 20, after=mark)
