"""The client SDK: pose queries and streaming subscriptions over every agent of a realm.

::

    from agent import Client
    with Client(realm="lab", connect=["tcp/127.0.0.1:7447"]) as c:
        r = c.pose("ivy/world", "alice/head", at=None, error="latency")
        r.position, r.quaternion, r.matrix, r.covariance, r.path, r.attributes, r.extrapolated_s
        sub = c.subscribe("ivy/world", "alice/head", on_pose=handle)
        ...
        sub.close()
        kept = c.keep("ivy/world", "alice/head", buffer_s=10.0)
        c.pose("ivy/world", "alice/head", at=t)  # answered here, no network
        kept.close()

``pose`` plans a route over the agents' supernode summaries (:mod:`agent.sdk.planner`), asks
each owning agent for its segment at ``t`` (all at once, one round trip), and composes the
answers with their covariances: one query's life, in :mod:`agent.sdk.query`.  ``at`` is
on this process's clock; each agent's clock offset is estimated from the round trips
(:mod:`agent.sdk.clock`) and applied both ways.
``at=None`` means the latest time at which every measured edge of the route has data.
If an agent does not answer, the next route without it is tried; if none is left the
error names the missing segment and agent.  An agent that missed an answer counts as gone
until it shows life again: a new token or summary, or an answer to the probe it gets every
``PROBE_S`` while its token is still there (it may only have been slow): what the client
knows of its realm, in :mod:`agent.sdk.realm`.

``subscribe`` runs the query once with edge details, then mirrors the route's edges in a
local :class:`agent.srg.Graph`: static edges from the answers, measured ones fed by
subscribing directly to their services' data keys.  Each sample of the fastest edge pushes
a composed pose at its time; the other edges are interpolated (or boundedly
extrapolated) at that time: Ubitrack's push/pull rule.  ``on_pose`` runs on the
subscription's own thread, never on a Zenoh thread (:mod:`agent.sdk.subscription`).

A subscribed or kept route answers ``pose`` locally, as tf2's buffer does: ``keep`` mirrors
a route as ``subscribe`` does, without a callback, and ``pose`` on that route (the same
source, target and error function) at any time inside the mirror's buffer is interpolated
here, with covariance, without asking any agent (:meth:`Subscription.answer` says when the
agents are asked instead).

A subscription follows the realm: whenever an agent leaves or joins or a supernode summary
changes, it plans again, and if the best route (or any edge of it) differs it rebuilds its
mirror on the new route and goes on delivering.  When no route is left it says so (a log
line, ``status == "no route"``, ``last_error``, and ``on_error(exc)`` once per outage),
stops delivering, and retries every ``RETRY_S`` and at every change until a route is back.
A route that is alive but silent -- its fastest edge sent nothing for ``stall_s`` (by default
``STALL_PERIODS`` of its sample periods, at least ``STALL_MIN_S``): the tracker lost its
target or hung, or the network drops its data -- is a different outage, since no other route
would do better: the subscription stays on it, says so once (a log line,
``status == "stalled"``, ``stalls``) and goes back to ``"streaming"`` at the next sample.
"""

from __future__ import annotations

import contextlib
import math
from collections.abc import Callable, Iterable, Sequence
from typing import Any

import zenoh

from agent.errors import InvalidInputError
from agent.protocol import keys
from agent.result import PoseResult
from agent.runtime.session import acquire_session, release_session, sdk_mode
from agent.sdk.clock import ClockOffsets
from agent.sdk.query import NoAgentsError, Queries, check_time
from agent.sdk.realm import RealmTracker
from agent.sdk.subscription import Subscription

__all__ = ["Client", "NoAgentsError", "Subscription"]


class Client:
    """A connection to a realm for pose queries and subscriptions (module docstring).

    It wires three parts together: ``tracker`` (:class:`agent.sdk.realm.RealmTracker`:
    what the realm holds), ``queries`` (:class:`agent.sdk.query.Queries`: one query's
    life) and the running subscriptions (:mod:`agent.sdk.subscription`).
    """

    def __init__(self, realm: str = "default", connect: Iterable[str] = (), *,
                 listen: Sequence[str] | None = None, mode: str | None = None,
                 timeout: float = 2.0, session: zenoh.Session | None = None,
                 shared: bool = True, zenoh_config: str | None = None) -> None:
        keys.check_name("realm", realm)
        if not timeout > 0:
            raise InvalidInputError(f"timeout must be > 0 s, got {timeout!r}")
        self.realm = realm
        self.timeout = float(timeout)
        self.connect = list(connect)
        self._own_session = session is None
        # an agent started a moment ago may not listen yet: wait for it as for an answer
        self.session = session or acquire_session(sdk_mode(mode, self.connect), listen,
                                                  self.connect, realm, shared=shared,
                                                  wait_s=self.timeout,
                                                  base_file=zenoh_config)
        self.clock = ClockOffsets()
        self.tracker = RealmTracker(self.session, realm, self.timeout,
                                    probe=lambda agent: self.queries.probe(agent))
        self.queries = Queries(self.session, realm, self.timeout, self.tracker, self.clock,
                               self.connect)
        self._subscriptions: list[Subscription] = []
        #: the running mirrors by (source, target, error), for ``pose`` to answer from
        self._mirrors: dict[tuple[str, str, str], list[Subscription]] = {}
        self._closed = False

    @property
    def topology(self) -> int:
        """Moves whenever the summaries or the set of live agents change."""
        return self.tracker.topology

    @property
    def cache_static_segments(self) -> bool:
        """False: ask for every segment every time (the benchmark's uncached figure)."""
        return self.queries.cache_static_segments

    @cache_static_segments.setter
    def cache_static_segments(self, on: bool) -> None:
        self.queries.cache_static_segments = on

    # ------------------------------------------------------------------ life cycle

    def __enter__(self) -> Client:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()

    def close(self) -> None:
        """Stop every subscription and leave; never raises (a session that cannot close in
        time is logged, see :func:`agent.runtime.session.close_session`), and a second call
        does nothing."""
        if self._closed:
            return
        self._closed = True
        for sub in list(self._subscriptions):
            sub.close()
        self.tracker.close()
        self.queries.close()
        if self._own_session:
            release_session(self.session)

    # ------------------------------------------------------------------ the realm

    def refresh(self) -> None:
        """Ask every agent for its summary now (also learns who is alive)."""
        self.tracker.refresh()

    def agents(self) -> dict[str, dict[str, Any]]:
        """The agents this client knows: alive or not, and their frames."""
        return self.tracker.agents()

    # ------------------------------------------------------------------ queries

    def pose(self, source: str, target: str, at: int | None = None,
             error: str = "latency") -> PoseResult:
        """The pose of ``target`` in ``source``'s frame at ``at`` (ns on this clock; None:
        the latest common time): from a subscribed or kept route's mirror where it can
        answer, else composed across agents (module docstring)."""
        mirrors = self._mirrors.get((source, target, error))
        if mirrors:
            at = check_time(at)
            for mirror in mirrors:
                r = mirror.answer(at)
                if r is not None:
                    return r
        return self.queries.ask(source, target, at, error).pose

    def subscribe(self, source: str, target: str, on_pose: Callable[[PoseResult], Any],
                  error: str = "latency",
                  on_error: Callable[[Exception], Any] | None = None,
                  stall_s: float | None = None) -> Subscription:
        """Push a composed pose to ``on_pose`` at every sample of the route's fastest edge,
        following route changes; ``on_error(exc)`` is told when no route is left, and a
        route silent for ``stall_s`` is reported as stalled (module docstring).  Raises like
        :meth:`pose` if there is no route to begin with."""
        if not callable(on_pose):
            raise InvalidInputError("on_pose must be callable")
        return self._mirror(source, target, on_pose, error, on_error, stall_s, 5.0)

    def keep(self, source: str, target: str, buffer_s: float = 10.0,
             error: str = "latency", on_error: Callable[[Exception], Any] | None = None,
             stall_s: float | None = None) -> Subscription:
        """Mirror the route from ``source`` to ``target`` here, ``buffer_s`` of it, so that
        ``pose(source, target, at, error)`` is answered locally at any time inside it (tf2's
        buffer); it follows route changes and stalls as a subscription does, and
        ``close()`` ends it.  Raises like :meth:`pose` if there is no route to begin with."""
        if not (isinstance(buffer_s, int | float) and math.isfinite(buffer_s)
                and buffer_s > 0):
            raise InvalidInputError(f"buffer_s must be a positive number of seconds, got "
                                    f"{buffer_s!r}")
        return self._mirror(source, target, None, error, on_error, stall_s, float(buffer_s))

    def _mirror(self, source: str, target: str,
                on_pose: Callable[[PoseResult], Any] | None, error: str,
                on_error: Callable[[Exception], Any] | None, stall_s: float | None,
                buffer_s: float) -> Subscription:
        """A subscription (``on_pose`` None: a kept route), registered for ``pose``."""
        if on_error is not None and not callable(on_error):
            raise InvalidInputError("on_error must be callable or None")
        if stall_s is not None and not (isinstance(stall_s, int | float)
                                        and math.isfinite(stall_s) and stall_s > 0):
            raise InvalidInputError(f"stall_s must be a positive number of seconds or None, got "
                                    f"{stall_s!r}")
        seen = self.topology
        first = self.queries.ask(source, target, None, error, details=True)
        sub = Subscription(self.queries, source, target, on_pose, error, on_error, first, seen,
                           stall_s, on_close=self._forget, buffer_s=buffer_s)
        self._subscriptions.append(sub)
        self._mirrors.setdefault((source, target, error), []).append(sub)
        return sub

    def _forget(self, sub: Subscription) -> None:
        """A subscription closed."""
        with contextlib.suppress(ValueError):
            self._subscriptions.remove(sub)
        key = (sub.source, sub.target, sub.error)
        with contextlib.suppress(ValueError):
            self._mirrors.get(key, []).remove(sub)
        if not self._mirrors.get(key, True):
            del self._mirrors[key]
