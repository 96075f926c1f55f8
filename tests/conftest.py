"""Shared fixtures: free loopback ports, a unique realm per test, and child processes that
are always stopped (by the PID we started, never by name)."""

from __future__ import annotations

import inspect
import itertools
import os
import random
import signal
import socket
import subprocess
import sys
import types
import uuid
from collections.abc import Callable, Iterator
from pathlib import Path

import pytest
from agent_helpers.site import Site, unavailable
from hypothesis import settings

from agent.runtime.processes import stop_processes

# Repeatable property tests (the same examples on every run and machine) with no per-example
# deadline: CI machines are shared and slow, and a deadline there fails for the wrong reason.
settings.register_profile("uma", derandomize=True, deadline=None)
settings.load_profile("uma")


def pytest_sessionstart(session: pytest.Session) -> None:
    """Compile uma's own sources once, in the controller: the suite starts some hundreds of
    processes (agents, services, commands), and where bytecode is not written on import
    (``PYTHONDONTWRITEBYTECODE``, as on shared CI hosts) each of them compiled every module
    it imports again, about 0.15 s of CPU apiece."""
    if hasattr(session.config, "workerinput"):
        return
    import compileall

    root = Path(__file__).resolve().parent.parent
    for package in ("agent", "schemas", "services", "tests/agent_helpers"):
        compileall.compile_dir(root / package, quiet=1)
    _write_rewritten_test_modules(session.config, root / "tests")


def _write_rewritten_test_modules(config: pytest.Config, tests: Path) -> None:
    """Write pytest's assertion-rewritten bytecode of the test modules once, in the
    controller: where bytecode is not written on import, each xdist worker otherwise
    rewrites every test module it collects (about 3.5 s of CPU per worker, before its first
    test). Workers read these files through pytest's own check of the source, so a stale or
    missing one is rewritten there as usual.

    This is an optimisation over pytest's private rewrite functions (the same ones its
    import hook calls, with the same arguments from pytest 8.0 on): where a pytest lacks them
    or takes other arguments, nothing is written and the workers rewrite as pytest always
    does. A module that does not parse is left to the worker that collects it, which reports
    it as that module's collection error instead of failing the whole session here."""
    rewrite = _rewrite_api()
    if rewrite is None:
        return
    state = config.stash.get(rewrite.assertstate_key, None)
    if state is None:  # --assert=plain: nothing is rewritten
        return
    for source in sorted(tests.glob("test_*.py")):
        cache = rewrite.get_cache_dir(source)
        pyc = cache / (source.name[:-3] + rewrite.PYC_TAIL)
        if rewrite._read_pyc(source, pyc) is not None or not rewrite.try_makedirs(cache):
            continue
        try:
            rewritten = rewrite._rewrite_test(source, config)
        except SyntaxError:
            continue
        if not (isinstance(rewritten, tuple) and len(rewritten) == 2
                and isinstance(rewritten[1], types.CodeType)):
            return
        source_check, code = rewritten
        rewrite._write_pyc(state, code, source_check, pyc)


def _rewrite_api() -> types.ModuleType | None:
    """pytest's assertion-rewrite module where it has the private functions
    ``_write_rewritten_test_modules`` calls, taking the arguments it passes; None where
    not (another pytest), so the optimisation is skipped rather than the session failed."""
    try:
        from _pytest.assertion import rewrite
    except ImportError:
        return None
    calls = {"_read_pyc": 2, "_rewrite_test": 2, "_write_pyc": 4, "get_cache_dir": 1,
             "try_makedirs": 1}
    for name, arguments in calls.items():
        function = getattr(rewrite, name, None)
        if not callable(function):
            return None
        try:
            inspect.signature(function).bind(*range(arguments))
        except (TypeError, ValueError):
            return None
    if not hasattr(rewrite, "assertstate_key") or not isinstance(
            getattr(rewrite, "PYC_TAIL", None), str):
        return None
    return rewrite


def _port_block() -> range:
    """This test worker's own ports: below the kernel's ephemeral range (where bind(0) and
    every outgoing connection take theirs, so a port found free there can be taken by
    another worker's client before an agent listens on it), one block per xdist worker."""
    try:
        low = int(Path("/proc/sys/net/ipv4/ip_local_port_range").read_text().split()[0])
    except (OSError, ValueError, IndexError):
        low = 32768
    workers = max(1, int(os.environ.get("PYTEST_XDIST_WORKER_COUNT", "1")))
    worker = os.environ.get("PYTEST_XDIST_WORKER", "gw0")[2:]
    size = max(1, (low - 10000) // workers)
    start = 10000 + (int(worker) % workers if worker.isdigit() else 0) * size
    return range(start, start + size)


_PORTS = _port_block()
_next_port = itertools.count(random.randrange(len(_PORTS)) if len(_PORTS) > 1 else 0)


def free_port() -> int:
    """A TCP port on 127.0.0.1 that nobody listens on right now, from this worker's block
    (``_port_block``); bind(0)'s when the block has none."""
    for _ in range(min(len(_PORTS), 500)):
        port = _PORTS[next(_next_port) % len(_PORTS)]
        with socket.socket(socket.AF_INET, socket.SOCK_STREAM) as s:
            try:
                s.bind(("127.0.0.1", port))
            except OSError:
                continue
            return port
    with socket.socket(socket.AF_INET, socket.SOCK_STREAM) as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def endpoint(port: int) -> str:
    """The Zenoh endpoint string of a loopback TCP port."""
    return f"tcp/127.0.0.1:{port}"


def seeds(n: int, default: int = 2) -> list:
    """``range(n)`` as test parameters for an equivalence checked over many seeds: the
    first ``default`` seeds in the default run, the rest marked slow (CI's second step)."""
    return [s if s < default else pytest.param(s, marks=pytest.mark.slow) for s in range(n)]


@pytest.fixture
def realm() -> str:
    """A realm no other test uses, so concurrent tests never see each other."""
    return f"t{uuid.uuid4().hex[:12]}"


class Processes:
    """Starts ``uma`` (or any Python module) in child processes and stops them all."""

    def __init__(self) -> None:
        self.procs: list[subprocess.Popen] = []

    def start(self, *args: str, module: str = "agent.cli", env: dict | None = None,
              ) -> subprocess.Popen:
        """``python -m MODULE ARGS...`` with unbuffered output captured to pipes."""
        e = dict(os.environ, PYTHONUNBUFFERED="1", **(env or {}))
        p = subprocess.Popen([sys.executable, "-m", module, *args], env=e,
                             stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
        self.procs.append(p)
        return p

    def kill(self, p: subprocess.Popen, sig: int = signal.SIGKILL) -> None:
        """Send ``sig`` to a process this fixture started."""
        if p.poll() is None:
            p.send_signal(sig)

    def stop_all(self, timeout: float = 5.0) -> None:
        stop_processes(self.procs, timeout)
        for p in self.procs:
            for stream in (p.stdout, p.stderr):
                if stream:
                    stream.close()


@pytest.fixture
def processes() -> Iterator[Processes]:
    """Child processes that are stopped (SIGTERM, then SIGKILL) when the test ends."""
    procs = Processes()
    try:
        yield procs
    finally:
        procs.stop_all()


@pytest.fixture
def site() -> Iterator[Callable[[int], Site]]:
    """``site(n)`` builds a site of ``n`` hosts in network namespaces
    (:mod:`agent_helpers.site`); every site is torn down when the test ends, also on failure.
    Skips when this machine cannot build one (not root, no ``ip``)."""
    reason = unavailable()
    if reason:
        pytest.skip(reason)
    built: list[Site] = []

    def build(n: int) -> Site:
        built.append(Site(n))
        return built[-1].build()

    try:
        yield build
    finally:
        for s in built:
            s.close()
