"""The path of one remote pose query through uma's files: not a timing, a map.

``python bench/query_path.py [TREE] [-v]`` starts an agent, a service publishing a measured
edge at 100 Hz and a client in this process (loopback, a unique realm), asks 20 warm-up
queries, then follows one ``Client.pose`` in the client's thread (``sys.setprofile``):
how many functions of uma it calls (and how many of those calls go into another file),
how many files it crosses, and how often it comes back to a file it had left (the
collapsed sequence of files execution is in, each step after the first visit counted).
``TREE`` (default: this checkout) measures another checkout of uma the same way, e.g. an
older commit unpacked by ``git archive``; ``-v`` lists every call.  The agents' side of the
query runs in Zenoh's threads and is not followed.
"""

from __future__ import annotations

import os
import socket
import sys
import threading
import time
from pathlib import Path

ROOT = Path(next((a for a in sys.argv[1:] if a != "-v"), Path(__file__).parents[1])).resolve()
sys.path.insert(0, str(ROOT))
os.environ["UMA_SRG_PURE_PYTHON"] = "1"  # a tree without the compiled kernel follows alike

from agent import Client, Service  # noqa: E402  (after the tree is chosen)
from agent.daemon.agent import Agent  # noqa: E402
from agent.daemon.settings import AgentSettings  # noqa: E402

WARMUP = 20


def free_endpoint() -> str:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return f"tcp/127.0.0.1:{s.getsockname()[1]}"


def follow(call, *args: object, **kwargs: object) -> list[tuple[str, str, str]]:
    """(event, file relative to the tree, function) of every call and return into the tree
    while ``call(*args, **kwargs)`` runs in this thread."""
    events: list[tuple[str, str, str]] = []

    def profile(frame, event, arg) -> None:
        name = frame.f_code.co_filename
        if event in ("call", "return") and name.startswith(str(ROOT)) and (
                "/.venv/" not in name):
            events.append((event, os.path.relpath(name, ROOT), frame.f_code.co_name))
    sys.setprofile(profile)
    try:
        call(*args, **kwargs)
    finally:
        sys.setprofile(None)
    return events


def figures(events: list[tuple[str, str, str]]) -> dict[str, int]:
    calls = [e for e in events if e[0] == "call"]
    stack: list[str] = []
    timeline: list[str] = []
    crossing = 0
    for event, name, _ in events:
        if event == "call":
            crossing += bool(stack) and stack[-1] != name
            stack.append(name)
        elif stack:
            stack.pop()
        here = stack[-1] if stack else "<caller>"
        if not timeline or timeline[-1] != here:
            timeline.append(here)
    seen: set[str] = set()
    returns = 0
    for name in timeline:
        returns += name in seen
        seen.add(name)
    return {"calls": len(calls), "calls_into_another_file": crossing,
            "files": len({e[1] for e in calls}), "returns": returns}


def main() -> int:
    ep, realm = free_endpoint(), f"path{os.getpid()}"
    agent = Agent(AgentSettings(realm=realm, agent_id="hostA", listen=[ep], static_edges=[
        {"parent": "ivy/world", "child": "ivy/cam", "position": [0.0, 0.0, 2.4],
         "quaternion": [0.0, 0.0, 0.0, 1.0]}]))
    agent.start()
    stop = threading.Event()
    svc = Service("head", realm=realm, agent="hostA", connect=[ep])
    out = svc.ability("pose", type="pose6d", edge=("ivy/cam", "alice/head"),
                      frequency_hz=100, latency_s=0.005, pos_std_m=0.002)
    svc.start()

    def publish() -> None:
        while not stop.is_set():
            out.publish(time.time_ns(), [0.0, 0.1, -0.8], [0.0, 0.0, 0.0, 1.0])
            stop.wait(0.01)
    publisher = threading.Thread(target=publish, daemon=True)
    publisher.start()
    client = Client(realm=realm, connect=[ep])
    try:
        deadline = time.monotonic() + 20.0
        while True:
            try:
                client.pose("ivy/world", "alice/head", error="hops")
                break
            except Exception:
                if time.monotonic() > deadline:
                    raise
                time.sleep(0.2)
        for _ in range(WARMUP):
            client.pose("ivy/world", "alice/head", error="hops")
        events = follow(client.pose, "ivy/world", "alice/head", error="hops")
    finally:
        stop.set()
        publisher.join(1.0)
        client.close()
        svc.close()
        agent.close()
    f = figures(events)
    print(f"{ROOT}: {f['calls']} calls ({f['calls_into_another_file']} into another file) "
          f"over {f['files']} files, {f['returns']} returns to a file left before")
    print("files:", ", ".join(sorted({e[1] for e in events})))
    if "-v" in sys.argv:
        for event, name, function in events:
            if event == "call":
                print(f"  {name} {function}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
