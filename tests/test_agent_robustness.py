"""Bad input, duplicate ids, agents that start late or restart: the agent keeps running
and says what was wrong."""

from __future__ import annotations

import signal
import time

import msgpack
import pytest
import zenoh
from agent_helpers.harness import (
    agent,
    first_from,
    matched_to,
    service,
    services_json,
    spawn,
)
from conftest import endpoint, free_port

from agent.protocol import keys
from agent.protocol.registration import control_message, parse_reply, register_request
from agent.runtime.session import SDK_MODE_ENV, open_session, query

PRODUCER = ("--ability", "pose", "--edge", "ivy/world", "alice/head")


def register_raw(session: zenoh.Session, realm: str, agent_id: str, payload: bytes,
                 ) -> tuple[bool, str]:
    """Send a registration and return the agent's (ok, error)."""
    for reply in query(session, keys.agent_register(realm, agent_id), 10.0, payload=payload):
        data = reply.ok.payload.to_bytes() if reply.ok else reply.err.payload.to_bytes()
        reply = parse_reply(data)
        return reply.ok, reply.error
    raise AssertionError("the agent did not answer the registration")


def wait_token(session: zenoh.Session, key: str, timeout: float = 20.0) -> None:
    deadline = time.monotonic() + timeout
    while not any(r.ok is not None for r in query(session, key, 1.0, liveliness=True)):
        assert time.monotonic() < deadline, f"token {key} not seen"
        time.sleep(0.05)


def descriptor(**fields) -> bytes:
    return msgpack.packb({"v": 1, "service_id": "evil", "agent_id": "hostA", **fields})


def test_bad_input_is_refused_with_reasons_and_the_agent_keeps_working(processes,
                                                                       realm) -> None:
    ep = endpoint(free_port())
    host = agent(processes, realm, "hostA", ep)
    cam = service(processes, realm, "cam", "hostA", ep, *PRODUCER)
    consumer = service(processes, realm, "fusion", "hostA", ep, "--need", "head")
    consumer.wait_for(lambda e: first_from(e, "cam"))

    with open_session(connect=[ep]) as s:
        # linked to the agent and (by gossip) to the services before sending them anything
        for token in (keys.agent_token(realm, "hostA"),
                      keys.service_token(realm, "hostA", "fusion"),
                      keys.service_token(realm, "hostA", "cam")):
            wait_token(s, token)
        cases = {
            b"\xc1garbage": "not valid msgpack",
            register_request(descriptor(needs=[{"name": "n", "type": "pose6d",
                                                "edge": ["a/b", "*/c"],
                                                "where": "frequency_hz >>= 3"}]),
                             "i1", 1, {}): "service 'evil': invalid service descriptor: "
                                           "needs.0.where",
            register_request(descriptor(abilities=[{"name": "x", "type": "teleport",
                                                    "edge": ["a/b", "c/d"]}]),
                             "i2", 1, {}): "service 'evil': invalid service descriptor: "
                                           "abilities.0.type",
            register_request(msgpack.packb({"v": 1, "service_id": "evil",
                                            "agent_id": "hostZ"}), "i3", 1, {}): "hostZ",
            msgpack.packb({"v": 1, "op": "register"}): "lacks field",
        }
        for payload, reason in cases.items():
            ok, error = register_raw(s, realm, "hostA", payload)
            assert not ok and reason in error, (reason, error)
        # malformed messages on the other uma keys
        s.put(keys.agent_services(realm, "evil"), b"\x93\x01\x02")
        s.put(keys.agent_services(realm, "evil"), msgpack.packb(
            {"v": 1, "agent": {"agent_id": "evil"}, "epoch": 1, "revision": 1,
             "services": [{"descriptor": b"junk"}]}))
        s.put(keys.control(realm, "hostA", "fusion"), b"not msgpack at all")
        s.put(keys.control(realm, "hostA", "fusion"), msgpack.packb(
            {"v": 1, "op": "connect", "epoch": 1, "seq": 1, "need": "nope", "matches": []}))
        s.put(keys.control(realm, "hostA", "fusion"),
              control_message(bytes(16), 1, 1, "head", [], True))
        s.put(keys.data(realm, "hostA", "cam", "pose"), msgpack.packb({"v": 1, "k": "pose6d"}))
        token = s.liveliness().declare_token(f"uma/{realm}/agent/evil")
        answer = s.declare_queryable(keys.agent_services(realm, "evil"),
                                     lambda q: (q.reply(q.key_expr, b"\xff\xfe"), q.drop()))
        host.wait_log("registration on")
        host.wait_log("snapshot uma/" + realm + "/agent/evil/services")
        host.wait_log("malformed sample")
        consumer.wait_log("control uma/" + realm + "/ctl/hostA/fusion")
        consumer.wait_log("lacks field(s) body, mac")
        consumer.wait_log("refused (signature")
        consumer.wait_log("data uma/" + realm + "/data/hostA/cam/pose")
        answer.undeclare()
        token.undeclare()

    # everyone is still working: new samples, a new need matched, the realm listed
    mark = consumer.mark
    consumer.wait_for(lambda e: e.get("event") == "counts" and e["counts"]["cam"] > 0,
                      after=mark)
    late = service(processes, realm, "late", "hostA", ep, "--need", "head")
    late.wait_for(lambda e: first_from(e, "cam"))
    listed = services_json(realm, ep)
    assert [a["agent_id"] for a in listed["agents"]] == ["hostA"]
    assert host.popen.poll() is None and cam.popen.poll() is None


def test_duplicate_service_id_is_refused_and_the_first_keeps_running(processes,
                                                                     realm) -> None:
    ep = endpoint(free_port())
    agent(processes, realm, "hostA", ep)
    first = service(processes, realm, "cam", "hostA", ep, *PRODUCER)
    first.wait_for(lambda e: e.get("event") == "started" and e["registered"])
    second = service(processes, realm, "cam", "hostA", ep, *PRODUCER)
    ev = second.wait_for(lambda e: e.get("event") in ("refused", "started"))
    assert ev["event"] == "refused", ev
    assert "duplicate service id 'cam'" in ev["error"]
    assert second.popen.wait(timeout=20) == 3
    consumer = service(processes, realm, "fusion", "hostA", ep, "--need", "head")
    consumer.wait_for(lambda e: first_from(e, "cam"))
    assert first.popen.poll() is None

    # a killed holder does not block its id: the restarted service takes it over
    processes.kill(first.popen, signal.SIGKILL)
    first.popen.wait(timeout=10)
    again = service(processes, realm, "cam", "hostA", ep, *PRODUCER)
    again.wait_for(lambda e: e.get("event") == "started")
    mark = consumer.mark
    consumer.wait_for(lambda e: e.get("event") == "counts" and e["counts"]["cam"] > 0,
                      after=mark)


@pytest.mark.parametrize("topology", ["client", "peer"])
def test_services_wait_for_their_agent_and_survive_its_restart(processes, realm,
                                                               topology) -> None:
    ep = endpoint(free_port())
    env = {SDK_MODE_ENV: topology}
    cam = service(processes, realm, "cam", "hostA", ep, *PRODUCER, env=env)
    consumer = service(processes, realm, "fusion", "hostA", ep, "--need", "head", env=env)
    consumer.wait_for(lambda e: e.get("event") == "started")  # no agent yet: started anyway
    host = agent(processes, realm, "hostA", ep)
    consumer.wait_for(lambda e: first_from(e, "cam"))

    processes.kill(host.popen, signal.SIGKILL)
    host.popen.wait(timeout=10)
    mark = consumer.mark
    if topology == "peer":
        # peers link to each other: samples keep flowing without the agent
        consumer.wait_for(lambda e: e.get("event") == "counts" and e["counts"]["cam"] > 50,
                          after=mark)
    agent(processes, realm, "hostA", ep)
    # clients of the agent are routed by it: their samples flow again once it is back
    consumer.wait_for(lambda e: e.get("event") == "counts" and e["counts"]["cam"] > 50,
                      after=mark)
    def fusion_matches() -> list[str] | None:
        """The restarted agent's matches of the fusion's need, once both services are
        registered with it (matching follows registration: the listing may come between)."""
        listed = services_json(realm, ep)
        services = {s["service_id"]: s for a in listed["agents"] for s in a["services"]}
        if set(services) != {"cam", "fusion"}:
            return None
        return [m["service_id"] for m in services["fusion"]["needs"][0]["matches"]]

    matches = None
    for _ in range(50):
        matches = fusion_matches()
        if matches:
            break
        time.sleep(0.1)
    assert matches == ["cam"]
    # the restart never disconnected the need
    assert not any(matched_to(e, "head") for e in consumer.events[mark:])
    assert cam.popen.poll() is None

    # an ability that vanished while the agent was down is disconnected once it is back
    host = next(p for p in processes.procs[::-1] if "agent" in p.args)
    processes.kill(host, signal.SIGKILL)
    host.wait(timeout=10)
    processes.kill(cam.popen, signal.SIGKILL)
    mark = consumer.mark
    agent(processes, realm, "hostA", ep)
    consumer.wait_for(lambda e: matched_to(e, "head"), after=mark)


def test_agent_cli_errors_and_clean_shutdown(processes, realm, tmp_path) -> None:
    import subprocess
    import sys

    def uma(*args: str) -> subprocess.CompletedProcess:
        return subprocess.run([sys.executable, "-m", "agent.cli", *args], capture_output=True,
                              text=True, timeout=60)

    r = uma("agent", "--realm", realm, "--connect", "tcp/127.0.0.1:99999")
    assert r.returncode == 1 and "port 99999" in r.stderr and "Traceback" not in r.stderr
    r = uma("agent", "--realm", "bad/realm")
    assert r.returncode == 1 and "realm 'bad/realm'" in r.stderr
    bad = tmp_path / "bad.toml"
    bad.write_text('realm = "x"\ncolour = "blue"\n')
    r = uma("agent", "--config", str(bad))
    assert r.returncode == 1 and "colour" in r.stderr
    bad.write_text('[[static]]\nparent = "a/b"\nchild = "c/d"\nposition = [0, 0]\n'
                   'quaternion = [0, 0, 0, 1]\n')
    r = uma("agent", "--config", str(bad))
    assert r.returncode == 1 and "static edge #1 position" in r.stderr
    r = uma("agent", "--realm", realm, "--service", "no-such-service")
    assert r.returncode == 1 and "no-such-service" in r.stderr
    r = uma("services", "--realm", realm, "--connect", endpoint(free_port()))
    assert r.returncode == 1 and "cannot reach" in r.stderr

    ep = endpoint(free_port())
    good = tmp_path / "host.toml"
    good.write_text(f'realm = "{realm}"\nid = "hostC"\nlisten = ["{ep}"]\n'
                    '[matching]\ngrace_s = 0.3\n[zenoh]\nlease_ms = 500\n'
                    '[[static]]\nparent = "ivy/world"\nchild = "ivy/cam_nw"\n'
                    'position = [0, 0, 2.4]\nquaternion = [0, 0, 0, 1]\npos_std_m = 0.001\n')
    host = spawn(processes, ["-m", "agent.cli", "agent", "--config", str(good)])
    assert ep in host.wait_line("uma agent hostC")
    r = uma("agent", "--realm", realm, "--id", "hostC", "--connect", ep)
    assert r.returncode == 1 and "already running" in r.stderr
    host.popen.send_signal(signal.SIGTERM)
    assert host.popen.wait(timeout=20) == 0


def test_an_agent_whose_start_stalls_says_so_and_exits() -> None:
    """A start stuck inside Zenoh (a known deadlock when peers reconnect during start-up)
    ends the daemon with a message naming it, instead of a silent hang."""
    import subprocess
    import sys

    from agent.cli.agent import STALLED_START

    script = ("import time\n"
              "from agent.cli import agent as daemon\n"
              "daemon.START_LIMIT_S = 0.3\n"
              "class Stuck:\n"
              "    def start(self):\n"
              "        time.sleep(30)\n"
              "daemon._start_or_exit(Stuck())\n")
    t0 = time.monotonic()
    out = subprocess.run([sys.executable, "-c", script], capture_output=True, text=True,
                         timeout=60)
    assert out.returncode == 1 and STALLED_START in out.stderr
    assert time.monotonic() - t0 < 25  # the watchdog, not the 30 s sleep, ended it


def test_an_agent_whose_session_stalls_later_says_so_and_exits() -> None:
    """A running agent whose worker is blocked in Zenoh past the limit exits 1 naming the
    call (its supervisor starts it again); one within the limit goes on."""
    import subprocess
    import sys

    from agent.cli.agent import STALLED_RUNNING

    script = ("from agent.cli import agent as daemon\n"
              "class Blocked:\n"
              "    def stalled(self, limit_s):\n"
              "        return 'its worker is blocked in _resync_agent_tokens for 31 s' \\\n"
              "            if limit_s < 31 else None\n"
              "daemon.STALL_LIMIT_S = 60.0\n"
              "daemon._exit_if_stalled(Blocked())\n"
              "print('went on', flush=True)\n"
              "daemon.STALL_LIMIT_S = 30.0\n"
              "daemon._exit_if_stalled(Blocked())\n"
              "print('still running')\n")
    out = subprocess.run([sys.executable, "-c", script], capture_output=True, text=True,
                         timeout=60)
    assert out.returncode == 1, out
    assert out.stdout == "went on\n" and STALLED_RUNNING in out.stderr
    assert "_resync_agent_tokens for 31 s" in out.stderr
