"""Multi-process test harness: agents (``uma agent``) and scripted services
(``tests.agent_helpers.svc``) on loopback, their output collected by reader threads.

Every process is registered with the ``processes`` fixture, which stops it by PID.
Waits are bounded by both a time limit and the events seen (no sleeps that assume speed).
"""

from __future__ import annotations

import contextlib
import io
import json
import os
import signal
import subprocess
import sys
import threading
import time
from collections.abc import Callable, Sequence
from pathlib import Path
from typing import Any

from agent.cli.agent import STALLED_START, START_LIMIT_S
from agent.cli.main import status
from agent.errors import UmaError
from agent.runtime.session import ZENOH_CONFIG_ENV

ROOT = str(Path(__file__).resolve().parents[2])
WAIT_S = 20.0  # generous: 2 shared cores, many test processes
#: an agent's own start-up limit, plus its imports on a loaded machine
START_WAIT_S = START_LIMIT_S + 15.0


class Proc:
    """A child process whose stdout JSON lines become ``events`` and stderr ``log``."""

    def __init__(self, popen: subprocess.Popen) -> None:
        self.popen = popen
        self.events: list[dict[str, Any]] = []
        self.lines: list[str] = []
        self.log: list[str] = []
        self._cond = threading.Condition()
        threading.Thread(target=self._read_out, daemon=True).start()
        self._err_reader = threading.Thread(target=self._read_err, daemon=True)
        self._err_reader.start()

    def _read_out(self) -> None:
        for line in self.popen.stdout:
            with self._cond:
                self.lines.append(line.rstrip("\n"))
                try:
                    ev = json.loads(line)
                    if isinstance(ev, dict):
                        ev["_mono"] = time.monotonic()
                        self.events.append(ev)
                except ValueError:
                    pass
                self._cond.notify_all()

    def _read_err(self) -> None:
        for line in self.popen.stderr:
            with self._cond:
                self.log.append(line.rstrip("\n"))
                self._cond.notify_all()

    def wait_for(self, pred: Callable[[dict[str, Any]], bool], timeout: float = WAIT_S,
                 after: int = 0) -> dict[str, Any]:
        """The first event (from index ``after``) satisfying ``pred``."""
        deadline = time.monotonic() + timeout
        with self._cond:
            while True:
                for ev in self.events[after:]:
                    if pred(ev):
                        return ev
                left = deadline - time.monotonic()
                if left <= 0:
                    raise AssertionError(
                        f"no matching event within {timeout} s; exit={self.popen.poll()}; "
                        f"last events: {self.events[-5:]}; log tail: {self.log[-15:]}")
                self._cond.wait(min(left, 0.2))

    def wait_line(self, text: str, timeout: float = WAIT_S) -> str:
        deadline = time.monotonic() + timeout
        with self._cond:
            while True:
                for line in self.lines:
                    if text in line:
                        return line
                left = deadline - time.monotonic()
                if left <= 0 or self.popen.poll() is not None:
                    break
                self._cond.wait(min(left, 0.2))
        raise AssertionError(f"no line with {text!r} within {timeout} s; {self._post_mortem()}")

    def _post_mortem(self) -> str:
        """Exit status and log tail; a process still running is hung, so it is aborted
        first and (PYTHONFAULTHANDLER, set by ``spawn``) prints every thread's stack."""
        status = self.popen.poll()
        if status is None:
            self.popen.send_signal(signal.SIGABRT)
            with contextlib.suppress(subprocess.TimeoutExpired):
                self.popen.wait(5)
            self._err_reader.join(2)
            status = f"hung, aborted ({self.popen.poll()})"
        with self._cond:
            return f"exit={status}; log tail: {self.log[-60:]}"

    def wait_log(self, text: str, timeout: float = WAIT_S) -> str:
        deadline = time.monotonic() + timeout
        with self._cond:
            while True:
                for line in self.log:
                    if text in line:
                        return line
                left = deadline - time.monotonic()
                if left <= 0:
                    raise AssertionError(f"no log line with {text!r}; log tail: "
                                         f"{self.log[-15:]}")
                self._cond.wait(min(left, 0.2))

    def send(self, line: str) -> None:
        self.popen.stdin.write(line + "\n")
        self.popen.stdin.flush()

    @property
    def mark(self) -> int:
        with self._cond:
            return len(self.events)


def poll(fn: Callable[[], Any], timeout: float = WAIT_S, what: str = "condition") -> Any:
    """``fn()``'s value once it neither raises (a lookup, an assertion, an uma error) nor
    returns False; bounded in time and in count."""
    deadline = time.monotonic() + timeout
    last: Exception | None = None
    for _ in range(500):
        try:
            result = fn()
            if result is not False:
                return result
        except (LookupError, AssertionError, UmaError) as exc:
            last = exc
        if time.monotonic() > deadline:
            break
        time.sleep(0.05)
    raise AssertionError(f"{what} not reached within {timeout} s: {last}")


def freeze(proc: Proc, timeout: float = WAIT_S) -> None:
    """SIGSTOP ``proc`` and return once every one of its threads has stopped: a process's
    threads stop one after the other, and on a loaded machine a Zenoh thread may still
    answer a query for a while after the signal was sent."""
    os.kill(proc.popen.pid, signal.SIGSTOP)
    tasks = Path(f"/proc/{proc.popen.pid}/task")
    deadline = time.monotonic() + timeout
    for _ in range(10_000):
        states = []
        for stat in tasks.glob("*/stat"):
            with contextlib.suppress(OSError):  # a thread that just ended
                states.append(stat.read_text().rsplit(")", 1)[1].split()[0])
        if states and all(state in "tT" for state in states):
            return
        if time.monotonic() > deadline:
            break
        time.sleep(0.005)
    raise AssertionError(f"pid {proc.popen.pid} not stopped within {timeout} s: {states}")


def spawn(processes: Any, args: list[str], env: dict[str, str] | None = None,
          prefix: Sequence[str] = ()) -> Proc:
    """``python ARGS`` with pipes (and ``env`` on top of ours), registered with the
    ``processes`` fixture; ``prefix`` runs it through another command (``ip netns exec
    NS``, which execs python in place, so the PID registered is python's)."""
    env = dict(os.environ, PYTHONUNBUFFERED="1", PYTHONFAULTHANDLER="1",
               PYTHONPATH=os.pathsep.join([ROOT, os.environ.get("PYTHONPATH", "")]),
               **(env or {}))
    p = subprocess.Popen([*prefix, sys.executable, *args], env=env, cwd=ROOT,
                         stdin=subprocess.PIPE, stdout=subprocess.PIPE, stderr=subprocess.PIPE,
                         text=True)
    processes.procs.append(p)
    return Proc(p)


def agent_command(realm: str, agent_id: str, endpoint: str, connect: Sequence[str] = (),
                  extra: Sequence[str] = ()) -> list[str]:
    """The arguments of ``python`` that run ``uma agent`` listening on ``endpoint``."""
    args = ["-m", "agent.cli", "agent", "--realm", realm, "--id", agent_id,
            "--listen", endpoint]
    for ep in connect:
        args += ["--connect", ep]
    return [*args, *extra]


def start_agents(processes: Any, commands: Sequence[tuple[list[str], Sequence[str]]],
                 env: dict[str, str] | None = None) -> list[Proc]:
    """Start every ``(agent_command, prefix)`` at once (their imports overlap), then return
    once each says it listens.

    An agent whose Zenoh session stalled at start (it says so and exits) is started once
    more, as its supervisor would: the stall is Zenoh's, not the test's subject."""
    procs = [spawn(processes, args, env, prefix) for args, prefix in commands]
    for i, (args, prefix) in enumerate(commands):
        try:
            procs[i].wait_line("listening on", START_WAIT_S)
        except AssertionError as exc:
            if STALLED_START not in str(exc):
                raise
            procs[i] = spawn(processes, args, env, prefix)
            procs[i].wait_line("listening on", START_WAIT_S)
    return procs


def agent(processes: Any, realm: str, agent_id: str, endpoint: str,
          connect: tuple[str, ...] = (), extra: tuple[str, ...] = (),
          env: dict[str, str] | None = None) -> Proc:
    """``uma agent`` listening on ``endpoint``; returns once it says it listens (see
    :func:`start_agents`)."""
    command = agent_command(realm, agent_id, endpoint, connect, extra)
    return start_agents(processes, [(command, ())], env)[0]


def service(processes: Any, realm: str, sid: str, agent_id: str, endpoint: str,
            *extra: str, env: dict[str, str] | None = None) -> Proc:
    """The scripted test service registered with ``agent_id`` at ``endpoint``."""
    return spawn(processes, ["-m", "tests.agent_helpers.svc", "--id", sid, "--realm", realm,
                             "--agent", agent_id, "--connect", endpoint, *extra], env)


def uma_here(*args: str) -> subprocess.CompletedProcess:
    """``uma ARGS`` run in this process, its output captured: the executable's own exit
    status (:func:`agent.cli.main.status`) without a fresh interpreter's imports, about
    half a CPU-second a command.  For commands that end by themselves (not ``uma agent``);
    what a command sets for its process is put back: ``--zenoh-config``'s variable and the
    SIGINT and SIGTERM handlers of a long-running command."""
    out, err = io.StringIO(), io.StringIO()
    config = os.environ.get(ZENOH_CONFIG_ENV)
    handlers = {sig: signal.getsignal(sig) for sig in (signal.SIGINT, signal.SIGTERM)}
    try:
        with contextlib.redirect_stdout(out), contextlib.redirect_stderr(err):
            code = status(list(args))
    finally:
        if config is None:
            os.environ.pop(ZENOH_CONFIG_ENV, None)
        else:
            os.environ[ZENOH_CONFIG_ENV] = config
        for sig, handler in handlers.items():
            signal.signal(sig, handler)
    return subprocess.CompletedProcess(["uma", *args], code, out.getvalue(), err.getvalue())


def services_json(realm: str, endpoint: str) -> dict[str, Any]:
    """``uma services --json`` as a dict (run in this process: :func:`uma_here`; the
    command in a process of its own is tested in test_cli and on the sites)."""
    out = uma_here("services", "--realm", realm, "--connect", endpoint, "--json")
    assert out.returncode == 0, out.stderr
    return json.loads(out.stdout.strip().splitlines()[-1])


def matched_to(ev: dict[str, Any], need: str, *sources: str) -> bool:
    """A ``match`` event of ``need`` naming exactly these services (in order)."""
    return (ev.get("event") == "match" and ev.get("need") == need
            and [k.split("/")[4] for k in ev["keys"]] == list(sources))


def first_from(ev: dict[str, Any], source: str) -> bool:
    return ev.get("event") == "first" and ev.get("source") == source
