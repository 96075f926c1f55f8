"""One Zenoh subscriber per data key in the daemon process, shared by all who listen.

Two parts of the daemon read the same local streams: the stream monitor (the time of
every sample, ``agent.daemon.monitor``) and the SRG node (every local pose sample,
``agent.daemon.srg_node``).  Subscribing twice to one key would have Zenoh deliver and
copy every sample twice; a :class:`StreamHub` declares one subscriber per key, takes each
sample's bytes once and hands them to every listener of that key, in Zenoh's thread (the
local streams: in the thread that drains their ring, below).
Listeners must therefore be quick (append to a queue, or a few microseconds of work) and
should not raise: what one raises is logged (rate-limited) and the others still get the
sample.  The subscriber goes when the key's last listener stops listening.

The agent's own services' keys (``uma/R/data/A/*/*``, given as ``local``) share a single
wildcard subscriber instead, declared while any of them is listened to: Zenoh calls one
subscriber's callback at a fraction of the cost of a hundred (about half the receiving
process's CPU with a hundred keys).  Its samples go through a bounded ring channel
(``LOCAL_RING``) that one thread of ours drains, calling the listeners there: an
unbounded hand-off let an agent short of CPU fall seconds behind its own streams (200
streams at 100 Hz on a loaded 2-core host: the digest's samples 1-3.5 s old; with the
ring 0.2 s), where dropping the oldest keeps it current.  Samples of local keys nobody
listens to (images, raw accelerometer data) are dropped by key before their payload is
read.

That thread wakes for every sample only while a listener of a local key must see each
sample when it arrives (``timely``: the stream monitor measures latency as arrival time
minus sample time), or while the samples come too fast to gather (a batch of
``LOCAL_BATCH`` or more).  Otherwise (the SRG node, which reads the samples in batches
anyway) it takes what waits in the ring, then pauses ``LOCAL_PAUSE_S``: one wake-up per
pause instead of one per sample, a wake-up costing about what the sample's own handling
does (and taking a core from whatever routes the sample on), and whoever reads what the
listeners keep calls :meth:`StreamHub.flush_local` first.  That takes only what waits
during a pause, and never waits: while the thread hands samples over, it leaves them to
it (the caller may be a Zenoh thread answering a query, which must not block, nor take
on the draining of a busy agent's streams).
"""

from __future__ import annotations

import contextlib
import logging
import threading
from collections.abc import Callable
from typing import Any

import zenoh

from agent.runtime.callbacks import guarded
from agent.runtime.logs import RateLimitedLog

log = logging.getLogger("uma.agent")

#: local samples queued for the draining thread before the oldest is dropped: ~50 ms at
#: 20,000 samples/s (200 streams at 100 Hz), five times a burst of one sample per stream.
#: An agent starved of CPU thus stays current, its digest and graph at most this far
#: behind, instead of queueing seconds of samples; what it drops shows as sequence gaps
#: in the stream monitor
LOCAL_RING = 1024
#: how long the local streams' thread lets samples gather while no listener is timely:
#: the SRG node's batch period (``agent.daemon.srg_node.PUBLISH_CHECK_S``)
LOCAL_PAUSE_S = 0.05
#: a batch this large means the ring fills faster than the pause allows: no pause then
LOCAL_BATCH = LOCAL_RING // 8
#: what a listener is given: the sample's payload
Listener = Callable[[bytes], None]


class _Key:
    """One key's subscriber and listeners (a tuple, replaced on change: Zenoh's thread
    iterates it without a lock)."""

    def __init__(self) -> None:
        self.listeners: tuple[Listener, ...] = ()
        #: the listeners that must see each sample when it arrives
        self.timely: tuple[Listener, ...] = ()
        self.subscriber: Any = None


class StreamHub:
    """Data keys of this process and who listens to each (module docstring)."""

    def __init__(self, session: zenoh.Session | None = None, local: str | None = None) -> None:
        self._session = session
        self._keys: dict[str, _Key] = {}
        self._lock = threading.Lock()
        self._log = RateLimitedLog(log)
        #: the key expression of this agent's own data (``uma/R/data/A/*/*``), if any
        self._local = local
        self._local_prefix = None if local is None else local.split("*", 1)[0]
        self._local_subscriber: Any = None
        #: listeners of local keys that are timely (``listen``), and the lock that keeps
        #: the local samples in order when another thread takes them (``flush_local``)
        self._timely_local = 0
        self._draining = threading.Lock()
        #: the draining thread is pausing: samples wait in the ring for flush_local
        self._pausing = False
        #: ends the local streams' thread's pause (a timely listener came, or closing)
        self._resume = threading.Event()

    def open(self, session: zenoh.Session) -> None:
        """Subscribe with ``session`` from now on (the daemon opens it after creating us)."""
        self._session = session

    def listen(self, key: str, listener: Listener, timely: bool = True) -> Callable[[], None]:
        """Call ``listener(payload)`` for every sample on ``key`` until the returned
        function is called.  ``timely`` False: the listener may be called late, in batches
        (a local key's samples; module docstring)."""
        if self._session is None:
            raise RuntimeError("StreamHub.listen before open(session)")
        with self._lock:
            entry = self._keys.get(key)
            if entry is None:
                entry = self._keys[key] = _Key()
                if self._is_local(key):
                    self._declare_local()
                else:
                    entry.subscriber = self._session.declare_subscriber(key, guarded(
                        lambda sample: self._dispatch(key, entry, sample), f"data {key}",
                        self._log))
            entry.listeners = (*entry.listeners, listener)
            if timely:
                entry.timely = (*entry.timely, listener)
                self._timely_local += self._is_local(key)
                self._resume.set()
        return lambda: self._stop_listening(key, entry, listener)

    def _is_local(self, key: str) -> bool:
        return self._local_prefix is not None and key.startswith(self._local_prefix)

    def _declare_local(self) -> None:
        if self._local_subscriber is None:
            assert self._session is not None and self._local is not None
            sub = self._session.declare_subscriber(self._local,
                                                   zenoh.handlers.RingChannel(LOCAL_RING))
            self._local_subscriber = sub
            threading.Thread(target=self._drain_local, args=(sub,), daemon=True,
                             name="uma-local-streams").start()

    def _drain_local(self, sub: zenoh.Subscriber) -> None:
        """Hand the local streams' samples to their listeners on this thread, until ``sub``
        is undeclared (Zenoh's thread only queues them, module docstring)."""
        try:
            for sample in sub:
                with self._draining:
                    self._dispatch_local(sample)
                    taken = self._take_waiting(sub)
                if taken < 0:
                    return
                if not self._timely_local and taken < LOCAL_BATCH:
                    self._pausing = True
                    self._resume.wait(LOCAL_PAUSE_S)
                    self._pausing = False
                    self._resume.clear()
        except zenoh.ZError as exc:
            self._log.warning(f"data {self._local}", f"reading samples: {exc}")

    def flush_local(self) -> None:
        """Hand the local samples waiting in the ring to their listeners now, on this
        thread (before reading what the listeners keep), if the draining thread is pausing
        (otherwise it hands them over itself; never waits: module docstring)."""
        sub = self._local_subscriber
        if sub is not None and self._pausing and self._draining.acquire(blocking=False):
            try:
                self._take_waiting(sub)
            finally:
                self._draining.release()

    def _take_waiting(self, sub: zenoh.Subscriber) -> int:
        """Dispatch the samples waiting in ``sub``'s ring, at most a ring's worth (lock
        held: others may want it); how many, -1 once ``sub`` is undeclared."""
        taken = 0
        try:
            while taken < LOCAL_RING and (sample := sub.try_recv()) is not None:
                self._dispatch_local(sample)
                taken += 1
        except zenoh.ZError:
            return -1
        return taken

    def _dispatch_local(self, sample: zenoh.Sample) -> None:
        key = str(sample.key_expr)
        entry = self._keys.get(key)
        if entry is None:
            return
        try:
            self._dispatch(key, entry, sample)
        except Exception as exc:  # the next sample must still be read
            self._log.warning(f"data {key}", f"{type(exc).__name__}: {exc}")

    def subscribed(self) -> set[str]:
        """The keys subscribed to now."""
        with self._lock:
            return set(self._keys)

    def close(self) -> None:
        """Undeclare every subscriber (before the session closes)."""
        self._resume.set()
        with self._lock:
            entries, self._keys = list(self._keys.values()), {}
            local, self._local_subscriber = self._local_subscriber, None
        for entry in entries:
            _undeclare(entry)
        _undeclare_subscriber(local)

    def _stop_listening(self, key: str, entry: _Key, listener: Listener) -> None:
        with self._lock:
            rest = list(entry.listeners)
            if listener in rest:
                rest.remove(listener)
            entry.listeners = tuple(rest)
            if listener in entry.timely:
                entry.timely = tuple(t for t in entry.timely if t is not listener)
                self._timely_local -= self._is_local(key)
            if rest or self._keys.get(key) is not entry:
                return
            del self._keys[key]
            local = None
            if self._is_local(key) and not any(map(self._is_local, self._keys)):
                local, self._local_subscriber = self._local_subscriber, None
        _undeclare(entry)
        _undeclare_subscriber(local)

    def _dispatch(self, key: str, entry: _Key, sample: zenoh.Sample) -> None:
        data = sample.payload.to_bytes()
        for listener in entry.listeners:
            try:
                listener(data)
            except Exception as exc:  # never into Zenoh's thread
                self._log.warning(f"data {key}", f"{type(exc).__name__}: {exc}")


def _undeclare(entry: _Key) -> None:
    _undeclare_subscriber(entry.subscriber)
    entry.subscriber = None


def _undeclare_subscriber(subscriber: Any) -> None:
    if subscriber is not None:
        with contextlib.suppress(zenoh.ZError):
            subscriber.undeclare()
