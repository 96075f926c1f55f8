"""A pose tracker for multi-process tests: a service with one ``pose6d`` ability that a
test file runs as a script (``python tests/test_x.py --realm R --agent A --connect EP``).

Each test decides what its tracker publishes; this holds what they all share: the
command line, the Service and its 100 Hz ability, and a clean stop on SIGTERM.
"""

from __future__ import annotations

import argparse
import signal
import threading
import time
from collections.abc import Callable, Iterator, Sequence
from contextlib import contextmanager
from typing import Any

RATE_HZ = 100.0


def options(argv: Sequence[str],
            extra: Callable[[argparse.ArgumentParser], None] | None = None,
            ) -> argparse.Namespace:
    """``--realm``, ``--agent`` and ``--connect`` (required), plus a test's own options."""
    ap = argparse.ArgumentParser()
    ap.add_argument("--realm", required=True)
    ap.add_argument("--agent", required=True)
    ap.add_argument("--connect", required=True)
    if extra is not None:
        extra(ap)
    return ap.parse_args(list(argv))


@contextmanager
def pose_tracker(a: argparse.Namespace, edge: tuple[str, str],
                 ) -> Iterator[tuple[Any, Any, threading.Event]]:
    """The running service, its ``head`` ability on ``edge`` and the event SIGTERM sets."""
    from agent import Service

    stop = threading.Event()
    signal.signal(signal.SIGTERM, lambda *_: stop.set())
    with Service("tracker", realm=a.realm, agent=a.agent, connect=[a.connect]) as svc:
        out = svc.ability("head", type="pose6d", edge=edge, frequency_hz=RATE_HZ,
                          latency_s=0.001, pos_std_m=0.002)
        svc.start()
        yield svc, out, stop


def publish_until(out: Any, stop: threading.Event,
                  pose_at: Callable[[int], tuple[Sequence[float], Sequence[float]]],
                  seconds: float = 600.0, skew_ns: int = 0,
                  paused: Callable[[], bool] | None = None) -> None:
    """Publish ``pose_at(now_ns)`` at RATE_HZ, stamped now + ``skew_ns``, until stopped
    (or ``seconds``); nothing while ``paused()`` (a tracker alive but silent)."""
    end = time.monotonic() + seconds
    while not stop.is_set() and time.monotonic() < end:
        t = time.time_ns()
        if paused is None or not paused():
            out.publish(t + skew_ns, *pose_at(t))
        stop.wait(1.0 / RATE_HZ)
