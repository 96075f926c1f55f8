"""Whole routes asked of one agent (``{"op": "route"}``) and its supernode cache.

The world of ``test_client_keep``: agent ``A`` (clock 3 s ahead) with the tracker on
world -> head, ``B`` and ``C`` each with a static head -> eye; separate processes.  Asked
eye -> world, a route starts at B or C, which answers its own segment and A's: first by
asking A, then, once asked often, from its cache of A's segment, fed by the tracker's
samples.  A segment cache opened in the test's own process checks keeping and eviction.
"""

from __future__ import annotations

import time

from agent_helpers.harness import poll
from test_client_keep import _same, world  # noqa: F401  (the fixture)
from test_client_stream import EYE, HEAD, WORLD

from agent.protocol import query as proto


def test_a_route_answered_by_its_first_agent_equals_the_fan_out(world, realm):  # noqa: F811
    from agent.sdk.client import Client

    eps, _, procs = world
    with Client(realm=realm, connect=[eps["A"]], timeout=2.0) as c:
        c.cache_static_segments = False  # else B's or C's segment is not asked: A alone is
        poll(lambda: c.pose(EYE, WORLD, at=time.time_ns() - 600_000_000),
             what="a pose across B or C and A, 0.6 s back")
        kept = "segment cache: keeping alice/head -> ivy/world of agent 'A'"
        for _ in range(3):  # asked often: the route's first agent (B or C) keeps A's segment
            c.pose(EYE, WORLD, at=time.time_ns() - 100_000_000)
        poll(lambda: any(kept in line for name in "BC" for line in procs[name].log),
             what="A's segment kept by B or C")
        time.sleep(0.6)  # samples reach the new mirror
        c.clock.add = lambda *args: None  # the same offsets for both answers from here on
        now = time.time_ns()
        for back_ms in (120, 190, 260):
            at = now - back_ms * 1_000_000
            c.queries.relay = True
            cached = c.queries.cached_parts
            relayed = c.pose(EYE, WORLD, at=at)
            assert c.queries.cached_parts == cached + 1, "A's segment not from the cache"
            c.queries.relay = False
            _same(relayed, c.pose(EYE, WORLD, at=at))
            assert relayed.t_ns == at and relayed.covariance is not None
        c.queries.relay = True
        procs["A"].popen.kill()

        def gone() -> bool:
            try:
                c.pose(EYE, WORLD)
            except LookupError:
                return True
            return False
        poll(gone, what="no pose once A left")


def test_the_segment_cache_keeps_hot_segments_and_drops_unused_ones(world, realm,  # noqa: F811
                                                                     monkeypatch):
    from agent import Client
    from agent.daemon import relay
    from agent.runtime.session import acquire_session, release_session

    monkeypatch.setattr(relay, "UNUSED_S", 1.0)
    monkeypatch.setattr(relay, "MAX_KEPT", 1)
    eps, _, _ = world
    session = acquire_session("client", None, [eps["A"]], realm, shared=False, wait_s=2.0)
    cache = relay.SegmentCache(session, realm, Client)
    try:
        head = proto.SegmentRequest(HEAD, WORLD, "latency", None)
        world_ = proto.SegmentRequest(WORLD, HEAD, "latency", None)
        assert cache.answer("A", head) is None  # asked once: not kept yet

        def hot(req) -> bool:
            hit = cache.answer("A", req)
            return hit is not None and hit["source"] == req.source
        poll(lambda: hot(head), what="A's segment kept after a few requests")
        assert cache.kept == [("A", HEAD, WORLD, "latency")]
        # a second hot segment takes the only place: the least recently used goes
        poll(lambda: hot(world_), what="the other direction kept")
        assert cache.kept == [("A", WORLD, HEAD, "latency")]
        # unused for a second: dropped
        poll(lambda: cache.kept == [], what="the unused segment dropped")
        # an unknown frame is never kept, and says why in its log line
        bogus = proto.SegmentRequest("nowhere", WORLD, "latency", None)
        for _ in range(4):
            assert cache.answer("A", bogus) is None
        time.sleep(0.5)
        assert cache.kept == []
        assert cache.hits > 0
    finally:
        cache.close()
        release_session(session)
