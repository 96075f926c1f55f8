"""``uma view``: wires a :class:`agent.Client`, the realm watch, the stream taps and a viser
server, then redraws the page at most ``--hz`` times a second until stopped.

The draw loop reads the watch's latest look and the taps' newest samples; it never waits
on the network (the watch and the query box do that on their own threads), so a slow or
silent agent slows nothing but its own part of the page.
"""

from __future__ import annotations

import argparse
import logging
import math
import socket
import threading
import time
from typing import Any

import numpy as np

from agent import Client
from agent.errors import UmaError
from agent.protocol import keys
from agent.view import panels
from agent.view.space import Placed, Space, Trails
from agent.view.taps import Taps
from agent.view.watch import Look, Watch

log = logging.getLogger("uma.view")

#: what to install when viser is missing
INSTALL = "pip install 'uma-tracking[view]'"
#: seconds between attempts to reach the realm's endpoint
RETRY_S = 1.0
#: at most this many redraws a second, whatever --hz says
MAX_HZ = 30.0
#: labels, trails, ellipsoids and the match table move at this rate (Hz): they cost one
#: message per changed node
SLOW_HZ = 5.0


def main(args: argparse.Namespace) -> int:
    """Handler of ``uma view``: the page is served at once; until the realm's endpoint
    answers it says so and tries again every ``RETRY_S``."""
    check_arguments(args)
    viser = import_viser()
    _check_port_free(args.host, args.port)
    logging.getLogger("uma").setLevel(logging.WARNING)
    from agent.runtime import stop_on_signals
    from agent.view.scene import Page

    stop = stop_on_signals()
    end = math.inf if args.seconds is None else time.monotonic() + args.seconds
    server = viser.ViserServer(host=args.host, port=args.port, verbose=False)
    try:
        page = Page(server, args.root)
        print(f"uma view: http://{args.host}:{server.get_port()}/ (realm {args.realm}; "
              "Ctrl-C stops)", flush=True)
        client = _connect(args, page, stop, end)
        if client is None:
            return 0
        with client:
            view = View(client, page, args.hz, args.trail)
            try:
                view.run(stop, end)
            finally:
                view.close()
    finally:
        server.stop()
    return 0


def _connect(args: argparse.Namespace, page: Any, stop: threading.Event,
             end: float) -> Client | None:
    """A client of the realm, once its endpoint answers (None if stopped before)."""
    while not stop.is_set() and time.monotonic() < end:
        try:
            return Client(realm=args.realm, connect=args.connect, timeout=1.0)
        except UmaError as exc:
            page.text(page.realm, f"**No agents in realm `{args.realm}` yet** ({exc}); trying "
                                  f"again every {RETRY_S:g} s. This page updates by itself.")
        stop.wait(RETRY_S)
    return None


def check_arguments(args: argparse.Namespace) -> None:
    """Refuse bad values with a message naming the option."""
    keys.check_name("realm", args.realm)
    if not 0 <= args.port <= 65535:
        raise UmaError(f"--port must be in 0..65535, got {args.port}")
    if not (math.isfinite(args.hz) and 0 < args.hz <= MAX_HZ):
        raise UmaError(f"--hz must be in (0, {MAX_HZ:g}], got {args.hz}")
    if not (math.isfinite(args.trail) and 0 <= args.trail <= 60):
        raise UmaError(f"--trail must be in [0, 60] s, got {args.trail}")
    if args.seconds is not None and not (math.isfinite(args.seconds) and args.seconds > 0):
        raise UmaError(f"--seconds must be positive, got {args.seconds}")


def import_viser() -> Any:
    """viser, or an error saying exactly what to install."""
    try:
        import viser
    except ImportError as exc:
        raise UmaError(f"'uma view' needs the optional 'view' extra ({exc}); install it with: "
                       f"{INSTALL}") from None
    return viser


def _check_port_free(host: str, port: int) -> None:
    """viser would move to the next free port by itself; the user asked for this one."""
    if port == 0:
        return
    with socket.socket(socket.AF_INET, socket.SOCK_STREAM) as s:
        try:
            s.bind((host, port))
        except OSError as exc:
            raise UmaError(f"cannot serve on {host}:{port} ({exc.strerror}); choose another "
                           "--port (0: any free port)") from None


class View:
    """The live page of one realm (module docstring)."""

    def __init__(self, client: Client, page: Any, hz: float, trail_s: float) -> None:
        self.client = client
        self.hz = min(float(hz), MAX_HZ)
        self.taps = Taps(client.session, log, client.realm)
        self.watch = Watch(client)
        self.page = page
        page.on_query = self.query
        self.space = Space()
        self.trails = Trails(trail_s)
        self._seen = -1
        self._next_slow = 0.0
        self._aimed = False
        #: redraws done and the seconds they took (for the bench and the page)
        self.redraws = 0
        self.draw_s = 0.0

    def close(self) -> None:
        self.watch.close()
        self.taps.close()

    def run(self, stop: threading.Event, end: float = math.inf) -> None:
        """Redraw at ``hz`` until ``stop`` is set (or until monotonic time ``end``)."""
        period = 1.0 / self.hz
        next_at = time.monotonic()
        while not stop.is_set() and time.monotonic() < end:
            t0 = time.perf_counter()
            self.redraw()
            self.draw_s += time.perf_counter() - t0
            self.redraws += 1
            next_at = max(next_at + period, time.monotonic())
            stop.wait(max(0.0, next_at - time.monotonic()))

    def redraw(self) -> None:
        look, page = self.watch.look, self.page
        now = time.monotonic()
        slow = now >= self._next_slow
        if slow:
            self._next_slow = now + 1.0 / SLOW_HZ
        changed, self._seen = look.seq != self._seen, look.seq
        if changed:
            self.taps.follow((e.key, e.type) for e in look.edges.values() if e.key)
            page.text(page.realm, panels.realm_md(look))
            page.text(page.services, panels.services_md(look))
            page.text(page.events, panels.events_md(look))
            page.edge_choices(sorted(look.edges))
        if slow or changed:  # stream states and ages move without a new look
            page.text(page.matches, panels.matches_md(look, self.taps.facts))
            page.text(page.edge_info, panels.edge_md(page.edge.value, look, self.taps.facts))
        values, covariances, newest = self._values(look)
        placed = self.space.place(page.root.value.strip(), look.edges, values)
        if not self._aimed and len(placed.frames) > 1:
            page.aim(placed.positions)
            self._aimed = True
        page.frames(placed, labels=slow)
        page.edges(placed, look.edges)
        page.path(placed)
        if slow:
            self.trails.add(now, placed)
            page.trails(self.trails.segments())
            page.ellipsoids(placed, {f: c for f, c in covariances.items()
                                     if placed.via.get(f) in values})
        page.text(page.placed_info, _placed_md(placed, look, newest))

    def _values(self, look: Look) -> tuple[dict[str, tuple[np.ndarray, np.ndarray]],
                                           dict[str, tuple[np.ndarray, str]], int | None]:
        """Each edge's latest value; position covariances by child frame; the newest
        sample's time (ns, on its publisher's clock)."""
        values, covs, newest = {}, {}, None
        for name, e in look.edges.items():
            if e.key is None:
                values[name] = (np.asarray(e.attributes["position"]),
                                np.asarray(e.attributes["quaternion"]))
                continue
            m = self.taps.latest(e.key)
            if m is None:
                continue
            p = m.position if m.position is not None else np.zeros(3)
            q = m.quaternion if m.quaternion is not None else np.array([0.0, 0.0, 0.0, 1.0])
            values[name] = (p, q)
            newest = m.t_ns if newest is None else max(newest, m.t_ns)
            if m.covariance is not None and m.covariance.shape[0] >= 3:
                covs[e.child] = (m.covariance[:3, :3], e.parent)
        return values, covs, newest

    def query(self, source: str, target: str, error: str) -> tuple[str, list[str]]:
        """The query box: the pose, the path, extrapolation and covariance, or why not."""
        if not source or not target:
            return "give a source and a target frame", []
        try:
            r = self.client.pose(source, target, at=None, error=error)
        except UmaError as exc:
            return f"**no answer**: {exc}", []
        cov = ("none" if r.covariance is None else
               f"position std {1e3 * np.sqrt(np.trace(r.covariance[:3, :3]) / 3):.2f} mm")
        return (f"**{target} in {source}** ({error})\n\n"
                f"- position: {np.array2string(np.asarray(r.position), precision=4)} m\n"
                f"- quaternion (x y z w): "
                f"{np.array2string(np.asarray(r.quaternion), precision=4)}\n"
                f"- path: {' -> '.join(r.path)}\n"
                f"- extrapolated: {1e3 * (r.extrapolated_s or 0.0):.1f} ms\n"
                f"- covariance: {cov}"), list(r.path)


def _placed_md(placed: Placed, look: Look, newest: int | None) -> str:
    """How much of the SRG is drawn, and the newest sample drawn (its time in ns: the
    page-latency benchmark reads it)."""
    unplaced = len({f for e in look.edges.values() for f in (e.parent, e.child)}
                   - set(placed.frames))
    lines = [f"{len(placed.frames)} frame(s) placed from `{placed.frames[0]}`, "
             f"{len(look.edges)} edge(s); {unplaced} frame(s) not connected to it"]
    if newest is not None:
        lines.append(f"newest sample drawn: t={newest} ns "
                     f"({(time.time_ns() - newest) / 1e6:.0f} ms old)")
    return "\n\n".join(lines)
