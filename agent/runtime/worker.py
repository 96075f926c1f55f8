"""One worker thread that owns a component's state, used by the agent daemon and the SDK's
``Service``.

Zenoh calls its callbacks on its own threads, concurrently.  Rather than lock every piece
of state, a component lets its callbacks only :meth:`Worker.put` calls; the worker thread
runs them in arrival order, so all state is touched by one thread.  Between batches of
calls it runs ``tick`` every ``tick_s`` (time-driven work: retries, measurements,
re-sends) and then each ``settle`` callable (work a batch may have made due, done once per
batch rather than once per call, e.g. a re-match).  A call that raises is logged and the
worker goes on: one bug or one Zenoh error must not stop the component.

The queue holds at most ``MAX_QUEUED`` calls: callbacks are driven by what peers send, and
a peer flooding an agent or a service (forged control, tokens, snapshots) must not grow it
without bound.  A call that does not fit is refused, counted (``refused``) and said in a
rate-limited line; the components repair what a lost call missed by their periodic
re-sends and resyncs.  What peers send unasked (``put_peer``) may take only
``PEER_SHARE`` of the queue: the rest stays for the component's own work.
"""

from __future__ import annotations

import contextlib
import logging
import queue
import threading
import time
from collections.abc import Callable, Sequence
from typing import Any

import zenoh

from agent.runtime.logs import RateLimitedLog

#: calls run per batch at most before ``tick`` and ``settle`` get their turn
BATCH = 1000
#: calls waiting at most (about 10 s of a busy agent's callbacks)
MAX_QUEUED = 10_000
#: the share of the queue that what peers send unasked may take (``Worker.put_peer``)
PEER_SHARE = 0.5


class Worker:
    """The thread that runs a component's calls, ticks and settles (module docstring)."""

    def __init__(self, name: str, owner: str, log: logging.Logger, tick: Callable[[], None],
                 tick_s: float, settle: Sequence[Callable[[], None]] = (),
                 max_queued: int = MAX_QUEUED) -> None:
        self.owner = owner  # who, in log lines ("agent A", "service S")
        self._logger = log
        self._log = RateLimitedLog(log)
        self._tick, self._tick_s, self._settle = tick, tick_s, tuple(settle)
        self._q: queue.Queue[tuple[Callable[..., None], tuple[Any, ...]] | None] = queue.Queue(
            max_queued)
        #: calls refused because the queue was full
        self.refused = 0
        self._stopping = threading.Event()
        self._thread = threading.Thread(target=self._run, name=name, daemon=True)
        #: the call running now and when it began (read by other threads: see ``stuck``)
        self._running: tuple[str, float] | None = None

    def put(self, fn: Callable[..., None], *args: Any) -> bool:
        """Have the worker call ``fn(*args)`` (from any thread, never blocking); refused
        and counted when ``max_queued`` calls wait already.  True if queued."""
        return self._put(fn, args, self._q.maxsize)

    def put_peer(self, fn: Callable[..., None], *args: Any) -> bool:
        """``put`` for what peers send unasked (their published snapshots, summaries):
        refused once ``PEER_SHARE`` of the queue is taken, so the component's own work
        (registrations, answers to its queries, re-sends) always finds room."""
        return self._put(fn, args, int(self._q.maxsize * PEER_SHARE))

    def _put(self, fn: Callable[..., None], args: tuple[Any, ...], room: int) -> bool:
        try:
            if self._q.qsize() >= room:
                raise queue.Full
            self._q.put_nowait((fn, args))
            return True
        except queue.Full:
            self.refused += 1
            self._log.warning(self.owner, f"work queue full ({room} of {self._q.maxsize} "
                              f"calls): {_name(fn)} refused ({self.refused} refused so far)")
            return False

    def start(self) -> None:
        self._thread.start()

    def pace(self, tick_s: float) -> None:
        """Tick every ``tick_s`` from the next tick on (the worker's thread: a component
        with nothing time-driven to watch ticks less often, each tick a wake-up)."""
        self._tick_s = tick_s

    def alive(self) -> bool:
        return self._thread.is_alive()

    def stop(self, timeout: float) -> None:
        """Stop after the current call; wait for it up to ``timeout`` s (not from itself)."""
        self._stopping.set()
        with contextlib.suppress(queue.Full):  # a full queue wakes the worker anyway
            self._q.put_nowait(None)
        self.join(timeout)

    def join(self, timeout: float) -> None:
        if self._thread.is_alive() and self._thread is not threading.current_thread():
            self._thread.join(timeout)

    def stuck(self, limit_s: float) -> tuple[str, float] | None:
        """The call that has run for more than ``limit_s`` seconds and for how long, or
        None.  The worker's calls are short; one that does not return is blocked inside
        Zenoh (a session whose routing tables deadlocked), and the component cannot go on."""
        running = self._running  # one read: the worker thread replaces it, never mutates
        if running is None:
            return None
        took = time.monotonic() - running[1]
        return (running[0], took) if took > limit_s else None

    def call(self, fn: Callable[..., None], *args: Any) -> None:
        """Run one call; log what it raises (a Zenoh error while stopping is expected)."""
        self._running = (_name(fn), time.monotonic())
        try:
            fn(*args)
        except zenoh.ZError as exc:
            if not self._stopping.is_set():
                self._log.warning(self.owner, f"{_name(fn)}: Zenoh: {exc}")
        except Exception:  # a bug must not stop the component; log it with its traceback
            self._logger.exception("%s: %s failed", self.owner, _name(fn))
        finally:
            self._running = None

    def _run(self) -> None:
        next_tick = time.monotonic()
        while not self._stopping.is_set():
            self._run_batch(max(0.0, next_tick - time.monotonic()))
            now = time.monotonic()
            if now >= next_tick:
                self.call(self._tick)
                next_tick = now + self._tick_s
            for fn in self._settle:
                self.call(fn)

    def _run_batch(self, wait_s: float) -> None:
        """The calls that arrive within ``wait_s``, and those queued meanwhile."""
        try:
            item = self._q.get(timeout=wait_s)
            for _ in range(BATCH):
                if item is None or self._stopping.is_set():
                    return
                self.call(item[0], *item[1])
                item = self._q.get_nowait()
        except queue.Empty:
            pass


def _name(fn: Callable[..., None]) -> str:
    return getattr(fn, "__name__", repr(fn))


class WakeLoop:
    """A thread that catches up with what changed: it runs ``step`` when woken, and at
    least every ``period_s``, until closed.

    For work where many wake-ups mean the same as one (republish a summary, keep the
    segments asked for since the last run), so a wake-up is a flag, not a queued call.
    ``pause_s`` after each step bounds how often it runs however often it is woken.  A step
    that raises is said in a rate-limited line (``what``) and the loop goes on; a long step
    checks :attr:`stopping` to end early.
    """

    def __init__(self, name: str, step: Callable[[], None], log: RateLimitedLog, what: str,
                 period_s: float = 1.0, pause_s: float = 0.0) -> None:
        self._step = step
        self._log = log
        self._what = what
        self._period_s = period_s
        self._pause_s = pause_s
        self._wake = threading.Event()
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._run, name=name, daemon=True)

    def start(self) -> None:
        self._thread.start()

    def wake(self) -> None:
        """Have ``step`` run soon (once, however often this is called meanwhile)."""
        self._wake.set()

    @property
    def stopping(self) -> bool:
        return self._stop.is_set()

    def close(self, timeout_s: float) -> None:
        """Stop after the current step; wait for it at most ``timeout_s``."""
        self._stop.set()
        self._wake.set()
        if self._thread.is_alive():
            self._thread.join(timeout_s)

    def _run(self) -> None:
        while not self._stop.is_set():
            self._wake.wait(self._period_s)
            self._wake.clear()
            if self._stop.is_set():
                return
            try:
                self._step()
            except Exception as exc:  # keep the process alive; say why once in a while
                self._log.warning(self._what, f"{type(exc).__name__}: {exc}")
            if self._pause_s:
                self._stop.wait(self._pause_s)
