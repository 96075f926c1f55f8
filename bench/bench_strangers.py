"""What strangers on a plain realm (or members of the secured site) cost an agent: its
memory, CPU and query latency before and after four floods a plain Zenoh session sends (no
uma code on the wire side but the tree's own message builders):

- **summaries**: forged supernode summaries of invented agents (no token), ``--frames``
  frame ids each, as fast as the session puts them for ``--seconds``;
- **fake agents**: ``--fakes`` invented agents with a liveliness token each, whose
  snapshots (about ``--snapshot-kb`` KiB each) are published and answered when asked;
- **registrations**: registrations with ``h0`` of 0.6 MB descriptors and of new service
  ids, alternately, as fast as the session asks, ``--registrations`` at most (a tree that
  keeps them could take gigabytes);
- **token churn**: liveliness tokens of new agent ids declared and dropped as fast as the
  session can for ``--seconds``.

The realm: agent ``h0`` and agent ``h1`` (connected to ``h0``) with one static edge each,
a tracker on ``h1`` publishing ``h1/world`` -> ``h1/s0`` at 50 Hz, and a client on ``h0``
querying ``world`` -> ``h1/s0`` across both (a moving pose: asked of the agents each
time).  Each flood runs in its own process (``--attack``).  Figures: ``h0``'s RSS growth
(MB) and CPU (% of one core) during each flood, and query latency (median, p99) before the
floods and 3 s after each.  ``--tree`` runs the agents and the client from another
checkout (a worktree of an older commit) to compare; the anchor is the query latency
before any flood, in the same run.

    python bench/bench_strangers.py [--tree PATH] [--seconds 10] [--json]
"""

from __future__ import annotations

import argparse
import json
import os
import sys
import tempfile
import time
from pathlib import Path

import bench_host_load
from bench_host_load import Child, cpu_s, free_endpoint, rss_mb
from summary import cpu_model, median_p99, report

FLOODS = ("summaries", "registrations", "fake_agents", "churn")
STATIC = '[[static]]\nparent = "{p}"\nchild = "{c}"\nposition = [1.0, 0.0, 0.0]\n' \
         'quaternion = [0.0, 0.0, 0.0, 1.0]\npos_std_m = 0.001\n'


def start_realm(realm: str, tmp: Path) -> tuple[list[Child], str]:
    eps = [free_endpoint(), free_endpoint()]
    agents = []
    for i, (parent, child) in enumerate((("world", "h0/world"), ("h0/world", "h1/world"))):
        cfg = tmp / f"h{i}.toml"
        cfg.write_text(STATIC.format(p=parent, c=child))
        agents.append(Child("-m", "agent.cli", "agent", "--realm", realm, "--id", f"h{i}",
                            "--config", str(cfg), "--listen", eps[i],
                            *(["--connect", eps[0]] if i else [])))
    deadline = time.monotonic() + 60
    for a in agents:
        a.wait_for("listening on", deadline)
    tracker = Child("-m", "tests.agent_helpers.many_services", "--realm", realm, "--agent",
                    "h1", "--connect", eps[1], "--count", "1", "--rate", "50")
    tracker.wait_for("started", deadline)
    return [*agents, tracker], eps[0]


def query_figures(client, count: int) -> dict[str, float]:
    ms, errors = [], []
    for _ in range(count):
        t = time.perf_counter()
        try:
            client.pose("world", "h1/s0")
            ms.append((time.perf_counter() - t) * 1e3)
        except Exception as exc:  # the figure counts every failure
            errors.append(f"{type(exc).__name__}: {exc}"[:200])
    if errors:
        print(f"{len(errors)} queries failed, the first: {errors[0]}", file=sys.stderr)
    return median_p99(ms or [float("nan")], "ms") | {"failed": count - len(ms)}


def summaries_flood(session, realm: str, frames: int, seconds: float) -> dict[str, float]:
    import msgpack

    from agent.protocol import keys
    sent = nbytes = 0
    end = time.monotonic() + seconds
    while time.monotonic() < end:  # bounded: seconds
        data = msgpack.packb({"v": 1, "agent": f"ghost{sent}", "rev": 1, "frames": [
            f"ghost{sent}/frame-with-a-long-name-{k:06d}" for k in range(frames)]})
        session.put(keys.agent_supernode(realm, f"ghost{sent}"), data)
        sent += 1
        nbytes += len(data)
    return {"sent": sent, "sent_mb": nbytes / 1e6}


def fake_agents_flood(session, realm: str, fakes: int, snapshot_kb: int) -> dict[str, float]:
    """Tokens of ``fakes`` invented agents, their snapshots published and answered (kept
    until the attacker is stopped)."""
    from agent.protocol import keys
    from agent.protocol.registration import snapshot_message
    pad = "x" * 1000
    snaps = {}
    for i in range(fakes):
        info = {"agent_id": f"fake{i}", "realm": realm, "endpoints": [], "pad": [
            pad for _ in range(snapshot_kb)]}
        snaps[keys.agent_services(realm, f"fake{i}")] = snapshot_message(info, 1000 + i, 1, [])
    queryable = session.declare_queryable(keys.all_agent_services(realm), lambda q: (
        q.reply(str(q.key_expr), snaps[str(q.key_expr)]) if str(q.key_expr) in snaps
        else None, q.drop()))
    tokens = [session.liveliness().declare_token(keys.agent_token(realm, f"fake{i}"))
              for i in range(fakes)]
    time.sleep(1.0)
    for key, data in snaps.items():
        session.put(key, data)
    time.sleep(3.0)
    print(json.dumps({"fakes": len(tokens),
                      "sent_mb": sum(len(d) for d in snaps.values()) / 1e6}), flush=True)
    time.sleep(60)  # bounded: the bench stops this process after measuring
    queryable.undeclare()
    return {}


def registrations_flood(session, realm: str, seconds: float, most: int) -> dict[str, float]:
    """Registrations with ``h0``: one of a 0.6 MB descriptor, then one small one of a new
    service id, over and over, not waiting for the answers."""
    from agent.protocol import keys
    from agent.protocol.registration import register_request
    from schemas.codec import encode_descriptor
    from schemas.models import ServiceDescriptor

    def request(sid: str, blob: list[str]) -> bytes:
        return register_request(encode_descriptor(ServiceDescriptor(
            service_id=sid, agent_id="h0", attributes={"blob": blob}, abilities=[
                {"name": "pose", "type": "pose6d", "edge": [f"{sid}/a", f"{sid}/b"]}])),
            f"{len(sid):04d}{sid[-12:]:0>12}", 1, {})
    big = request("big", ["x" * 600] * 1000)
    sent = nbytes = 0
    end = time.monotonic() + seconds
    while time.monotonic() < end and sent < most:  # bounded: seconds, count
        payload = big if sent % 2 == 0 else request(f"junk{sent}", [])
        session.get(keys.agent_register(realm, "h0"), lambda reply: None, payload=payload,
                    timeout=2.0)
        sent += 1
        nbytes += len(payload)
    return {"sent": sent, "sent_mb": nbytes / 1e6}


def churn_flood(session, realm: str, seconds: float) -> dict[str, float]:
    from agent.protocol import keys
    n = 0
    end = time.monotonic() + seconds
    while time.monotonic() < end:  # bounded: seconds
        session.liveliness().declare_token(keys.agent_token(realm, f"churn{n}")).undeclare()
        n += 1
    return {"tokens": n}


def attack(args: argparse.Namespace) -> None:
    """The attacker's process (``--attack``): one flood, its figures as a JSON line."""
    import zenoh
    from loopback import zenoh_config
    with zenoh.open(zenoh_config("client", connect=args.connect)) as session:
        time.sleep(1.0)  # its links
        if args.attack == "summaries":
            out = summaries_flood(session, args.realm, args.frames, args.seconds)
        elif args.attack == "registrations":
            out = registrations_flood(session, args.realm, args.seconds, args.registrations)
        elif args.attack == "fake_agents":
            out = fake_agents_flood(session, args.realm, args.fakes, args.snapshot_kb)
        else:
            out = churn_flood(session, args.realm, args.seconds)
        print(json.dumps(out), flush=True)


def phase(name: str, target: Child, client, args: argparse.Namespace, ep: str,
          realm: str) -> dict:
    """One flood by an attacker process: the target's CPU while it runs, its RSS growth
    and the query latency 3 s after it."""
    rss0, cpu0, t0 = rss_mb(target.pid), cpu_s(target.pid), time.monotonic()
    attacker = Child(str(Path(__file__).resolve()), "--tree", str(bench_host_load.ROOT),
                     "--attack", name, "--connect", ep,
                     "--realm", realm, "--seconds", str(args.seconds), "--frames",
                     str(args.frames), "--fakes", str(args.fakes), "--snapshot-kb",
                     str(args.snapshot_kb), "--registrations", str(args.registrations))
    out = json.loads(attacker.wait_for("{", time.monotonic() + args.seconds + 60))
    cpu_pct = 100 * (cpu_s(target.pid) - cpu0) / (time.monotonic() - t0)
    time.sleep(3.0)  # what the agent does after the flood is part of its cost
    after = query_figures(client, args.queries)
    fig = {f"{name}_{k}": v for k, v in out.items()} | {
        f"{name}_agent_cpu_pct": round(cpu_pct, 1),
        f"{name}_rss_growth_mb": round(rss_mb(target.pid) - rss0, 1),
        f"{name}_query_after_median_ms": after["median_ms"],
        f"{name}_query_after_p99_ms": after["p99_ms"],
        f"{name}_query_after_failed": after["failed"]}
    attacker.proc.terminate()
    attacker.proc.wait(10)
    return fig


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--tree", default=None, help="checkout whose agents and client to run")
    ap.add_argument("--seconds", type=float, default=10.0, help="length of each flood")
    ap.add_argument("--frames", type=int, default=2000, help="frame ids per forged summary")
    ap.add_argument("--fakes", type=int, default=60, help="invented agents with tokens")
    ap.add_argument("--snapshot-kb", type=int, default=512, help="KiB per fake snapshot")
    ap.add_argument("--registrations", type=int, default=300,
                    help="most registrations sent (half of them 0.6 MB)")
    ap.add_argument("--queries", type=int, default=40)
    ap.add_argument("--floods", nargs="+", choices=FLOODS, default=list(FLOODS),
                    help="which floods, in this order (default: all)")
    ap.add_argument("--json", action="store_true")
    ap.add_argument("--attack", choices=FLOODS,
                    help=argparse.SUPPRESS)
    ap.add_argument("--connect", help=argparse.SUPPRESS)
    ap.add_argument("--realm", help=argparse.SUPPRESS)
    args = ap.parse_args()
    tree = Path(args.tree or Path(__file__).resolve().parent.parent).resolve()
    if os.environ.get("PYTHONPATH") != str(tree):  # the tree's agent package, not this one
        os.execve(sys.executable, [sys.executable, __file__, *sys.argv[1:]],
                  dict(os.environ, PYTHONPATH=str(tree)))
    sys.path.insert(0, str(tree))  # before bench_host_load's own tree, whose modules go
    for name in [m for m in sys.modules if m.split(".")[0] in ("agent", "schemas")]:
        del sys.modules[name]
    bench_host_load.ROOT = tree
    if args.attack:
        attack(args)
        return
    import agent
    from agent import Client
    realm = f"strangers{int(time.time())}"
    with tempfile.TemporaryDirectory() as tmp:
        agents, ep = start_realm(realm, Path(tmp))
        try:
            with Client(realm=realm, connect=[ep]) as client:
                for _ in range(100):  # bounded: the realm forms within ~10 s
                    if query_figures(client, 1)["failed"] == 0:
                        break
                    time.sleep(0.1)
                before = query_figures(client, args.queries)
                fig: dict = {"tree": str(Path(agent.__file__).parent.parent),
                             "cpu": cpu_model(),
                             "agent_rss_mb_start": round(rss_mb(agents[0].pid), 1),
                             "query_before_median_ms": before["median_ms"],
                             "query_before_p99_ms": before["p99_ms"]}
                for name in args.floods:
                    fig |= phase(name, agents[0], client, args, ep, realm)
                fig["query_after_all_ratio"] = round(fig[
                    f"{args.floods[-1]}_query_after_median_ms"] / before["median_ms"], 2)
        finally:
            for a in agents:
                a.proc.terminate()
            for a in agents:
                a.proc.wait(10)
    report(fig, args.json)


if __name__ == "__main__":
    main()
