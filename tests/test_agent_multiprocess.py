"""The issue's "Done when": agents and services in separate processes, real Zenoh on
loopback, a unique realm and fresh ports per test."""

from __future__ import annotations

import signal
import time

from agent_helpers.harness import (
    agent,
    first_from,
    matched_to,
    service,
    services_json,
    spawn,
)
from conftest import endpoint, free_port

PRODUCER = ("--ability", "pose", "--edge", "ivy/world", "alice/head")


def test_need_on_one_host_receives_an_ability_of_the_other(processes, realm) -> None:
    ep_a, ep_b = endpoint(free_port()), endpoint(free_port())
    agent(processes, realm, "hostA", ep_a)
    agent(processes, realm, "hostB", ep_b, connect=(ep_a,))
    service(processes, realm, "cam", "hostB", ep_b, *PRODUCER, "--rate", "100",
            "--attr", "frequency_hz=100", "--attr", "latency_s=0.005")
    consumer = service(processes, realm, "fusion", "hostA", ep_a, "--need", "head",
                       "--where", "frequency_hz >= 30", "--prefer", "latency_s")
    consumer.wait_for(lambda e: matched_to(e, "head", "cam"))
    first = consumer.wait_for(lambda e: first_from(e, "cam"))
    assert first["edge"] == ["ivy/world", "alice/head"]
    assert first["attributes"]["frequency_hz"] == 100
    consumer.wait_for(lambda e: e.get("event") == "counts" and e["counts"].get("cam", 0) >= 20)

    realm_view = services_json(realm, ep_a)
    agents = {a["agent_id"]: a for a in realm_view["agents"]}
    assert set(agents) == {"hostA", "hostB"}
    need = agents["hostA"]["services"][0]["needs"][0]
    assert need["satisfied"] is True
    assert [(m["agent_id"], m["service_id"], m["ability"]) for m in need["matches"]] == [
        ("hostB", "cam", "pose")]
    cam = agents["hostB"]["services"][0]
    assert cam["service_id"] == "cam" and cam["abilities"][0]["edge"] == ["ivy/world",
                                                                          "alice/head"]
    assert realm_view["problems"] == []


def test_preferred_ability_failover_on_sigkill_and_move_to_a_better_one(processes,
                                                                        realm) -> None:
    ep_a, ep_b = endpoint(free_port()), endpoint(free_port())
    agent(processes, realm, "hostA", ep_a)
    agent(processes, realm, "hostB", ep_b, connect=(ep_a,))
    fast = service(processes, realm, "fast", "hostB", ep_b, *PRODUCER,
                   "--attr", "latency_s=0.002")
    service(processes, realm, "slow", "hostA", ep_a, *PRODUCER, "--attr", "latency_s=0.02")
    consumer = service(processes, realm, "fusion", "hostA", ep_a, "--need", "head",
                       "--prefer", "latency_s")
    consumer.wait_for(lambda e: matched_to(e, "head", "fast"))
    consumer.wait_for(lambda e: first_from(e, "fast"))

    mark = consumer.mark
    t_kill = time.time_ns()
    processes.kill(fast.popen, signal.SIGKILL)
    consumer.wait_for(lambda e: matched_to(e, "head", "slow"), after=mark)
    ev = consumer.wait_for(lambda e: first_from(e, "slow"), after=mark)
    print(f"SIGKILL -> first sample from the backup: {(ev['recv_ns'] - t_kill) / 1e6:.1f} ms")

    mark = consumer.mark
    service(processes, realm, "best", "hostB", ep_b, *PRODUCER, "--attr", "latency_s=0.001")
    consumer.wait_for(lambda e: matched_to(e, "head", "best"), after=mark)
    consumer.wait_for(lambda e: first_from(e, "best"), after=mark)


def test_rate_below_predicate_is_abandoned_and_regained(processes, realm) -> None:
    ep_a = endpoint(free_port())
    agent(processes, realm, "hostA", ep_a)
    good = service(processes, realm, "good", "hostA", ep_a, *PRODUCER, "--rate", "100",
                   "--attr", "frequency_hz=100", "--attr", "latency_s=0.001")
    service(processes, realm, "backup", "hostA", ep_a, *PRODUCER, "--rate", "100",
            "--attr", "frequency_hz=100", "--attr", "latency_s=0.01")
    consumer = service(processes, realm, "fusion", "hostA", ep_a, "--need", "head",
                       "--where", "frequency_hz >= 50", "--prefer", "latency_s")
    consumer.wait_for(lambda e: first_from(e, "good"))

    mark = consumer.mark
    good.send("rate 10")  # still alive, still advertising 100 Hz, but delivering 10 Hz
    consumer.wait_for(lambda e: matched_to(e, "head", "backup"), after=mark)
    consumer.wait_for(lambda e: first_from(e, "backup"), after=mark)

    mark = consumer.mark
    good.send("rate 100")  # conforms again: the better one is taken back
    consumer.wait_for(lambda e: matched_to(e, "head", "good"), after=mark)


def test_attribute_update_is_re_advertised_and_re_matched(processes, realm) -> None:
    ep_a = endpoint(free_port())
    agent(processes, realm, "hostA", ep_a)
    one = service(processes, realm, "one", "hostA", ep_a, *PRODUCER, "--attr", "cost=1")
    service(processes, realm, "two", "hostA", ep_a, *PRODUCER, "--attr", "cost=2")
    consumer = service(processes, realm, "fusion", "hostA", ep_a, "--need", "head",
                       "--prefer", "cost")
    consumer.wait_for(lambda e: first_from(e, "one"))
    mark = consumer.mark
    one.send("update cost=5")
    consumer.wait_for(lambda e: matched_to(e, "head", "two"), after=mark)
    ev = consumer.wait_for(lambda e: first_from(e, "two"), after=mark)
    assert ev["attributes"]["cost"] == 2


def test_two_realms_on_the_same_endpoints_never_meet(processes, realm) -> None:
    other = realm + "x"
    ep_a, ep_b = endpoint(free_port()), endpoint(free_port())
    agent(processes, realm, "hostA", ep_a)
    agent(processes, other, "hostA", ep_b, connect=(ep_a,))
    cam = service(processes, other, "cam", "hostA", ep_b, *PRODUCER)
    consumer = service(processes, realm, "fusion", "hostA", ep_a, "--need", "head")
    for proc in (cam, consumer):
        proc.wait_for(lambda e: e.get("event") == "started" and e["registered"])
    seen_other = services_json(other, ep_a)  # same endpoint, other realm
    assert [a["agent_id"] for a in seen_other["agents"]] == ["hostA"]
    assert [s["service_id"] for s in seen_other["agents"][0]["services"]] == ["cam"]
    mine = services_json(realm, ep_a)
    assert [s["service_id"] for s in mine["agents"][0]["services"]] == ["fusion"]
    assert mine["agents"][0]["services"][0]["needs"][0]["matches"] == []
    assert not any(e.get("event") == "first" for e in consumer.events)


def test_client_agents_behind_a_router(processes, realm, tmp_path) -> None:
    ep_r = endpoint(free_port())
    router = spawn(processes, ["-m", "agent.cli", "router", "--listen", ep_r])
    router.wait_line("listening on")
    for host in ("hostA", "hostB"):
        cfg = tmp_path / f"{host}.toml"
        cfg.write_text(f'realm = "{realm}"\nid = "{host}"\nmode = "client"\n'
                       f'connect = ["{ep_r}"]\n')
        spawn(processes, ["-m", "agent.cli", "agent", "--config", str(cfg)]).wait_line(
            "listening on")
    service(processes, realm, "cam", "hostB", ep_r, *PRODUCER)
    consumer = service(processes, realm, "fusion", "hostA", ep_r, "--need", "head")
    consumer.wait_for(lambda e: first_from(e, "cam"))
    listed = services_json(realm, ep_r)
    assert [a["agent_id"] for a in listed["agents"]] == ["hostA", "hostB"]


def test_a_router_listens_where_its_config_file_says(processes, tmp_path) -> None:
    ep = endpoint(free_port())
    cfg = tmp_path / "router.json5"
    cfg.write_text(f'{{ listen: {{ endpoints: ["{ep}"] }} }}')
    router = spawn(processes, ["-m", "agent.cli", "router", "--config", str(cfg)])
    assert router.wait_line("listening on").split("listening on ")[1].split() == [ep]


def test_frozen_producer_is_dropped_after_its_lease_and_regained(processes, realm) -> None:
    ep_a, ep_b = endpoint(free_port()), endpoint(free_port())
    agent(processes, realm, "hostA", ep_a)
    agent(processes, realm, "hostB", ep_b, connect=(ep_a,))
    frozen = service(processes, realm, "fast", "hostB", ep_b, *PRODUCER,
                     "--attr", "latency_s=0.002")
    service(processes, realm, "slow", "hostA", ep_a, *PRODUCER, "--attr", "latency_s=0.02")
    consumer = service(processes, realm, "fusion", "hostA", ep_a, "--need", "head",
                       "--prefer", "latency_s")
    consumer.wait_for(lambda e: first_from(e, "fast"))
    mark = consumer.mark
    frozen.popen.send_signal(signal.SIGSTOP)  # silent death: no socket closes
    try:
        t_stop = time.time_ns()
        ev = consumer.wait_for(lambda e: first_from(e, "slow"), after=mark)
        print(f"frozen producer -> backup sample after {(ev['recv_ns'] - t_stop) / 1e9:.3f} s "
              "(lease 1 s)")
        mark = consumer.mark
    finally:
        frozen.popen.send_signal(signal.SIGCONT)
    # it wakes up, re-links, registers again and, being better, is taken back
    consumer.wait_for(lambda e: first_from(e, "fast"), after=mark)


def test_abilities_of_a_vanished_agent_are_dropped_and_regained(processes, realm) -> None:
    ep_a, ep_b = endpoint(free_port()), endpoint(free_port())
    agent(processes, realm, "hostA", ep_a)
    host_b = agent(processes, realm, "hostB", ep_b, connect=(ep_a,))
    service(processes, realm, "remote", "hostB", ep_b, *PRODUCER, "--attr", "latency_s=0.001")
    service(processes, realm, "local", "hostA", ep_a, *PRODUCER, "--attr", "latency_s=0.01")
    consumer = service(processes, realm, "fusion", "hostA", ep_a, "--need", "head",
                       "--prefer", "latency_s")
    consumer.wait_for(lambda e: first_from(e, "remote"))
    mark = consumer.mark
    processes.kill(host_b.popen, signal.SIGKILL)  # the service lives on, its agent does not
    consumer.wait_for(lambda e: first_from(e, "local"), after=mark)
    mark = consumer.mark
    agent(processes, realm, "hostB", ep_b, connect=(ep_a,))  # the service registers again
    consumer.wait_for(lambda e: first_from(e, "remote"), after=mark)
