"""The topology of a host: services and clients are Zenoh clients of their host's agent and
share one session per process, so a realm's links grow with processes, not services²."""

from __future__ import annotations

import os
import threading
import time

import pytest
import zenoh
from agent_helpers.harness import agent, first_from, poll, service
from conftest import endpoint, free_port

from agent import Client, Service
from agent.errors import UmaError
from agent.runtime.processes import established_tcp
from agent.runtime.session import SDK_MODE_ENV, close_session, sdk_mode

WORLD, HEAD = "ivy/world", "alice/head"


def test_the_sdk_mode_follows_what_a_process_names() -> None:
    assert sdk_mode(None, ["tcp/127.0.0.1:7447"]) == "client"
    assert sdk_mode(None, []) == "peer"
    assert sdk_mode("peer", ["tcp/127.0.0.1:7447"]) == "peer"
    with pytest.raises(UmaError, match=r"'router'.*'client'.*'peer'"):
        sdk_mode("router", [])


def test_the_sdk_mode_can_be_set_for_a_whole_host(monkeypatch) -> None:
    monkeypatch.setenv(SDK_MODE_ENV, "peer")
    assert sdk_mode(None, ["tcp/127.0.0.1:7447"]) == "peer"
    monkeypatch.setenv(SDK_MODE_ENV, "routerish")
    with pytest.raises(UmaError, match="UMA_SDK_MODE"):
        sdk_mode(None, [])


def test_services_of_a_process_share_one_session_and_one_link(processes, realm) -> None:
    ep = endpoint(free_port())
    agent(processes, realm, "hostA", ep)
    services = [Service(f"s{i}", realm=realm, agent="hostA", connect=[ep]) for i in range(10)]
    try:
        for i, svc in enumerate(services):
            svc.ability("pose", type="pose6d", edge=(WORLD, f"obj/{i}"), frequency_hz=10)
            svc.start()
        assert all(s.wait_registered(10.0) for s in services)
        assert len({id(s.session) for s in services}) == 1
        with Client(realm=realm, connect=[ep]) as client:
            assert client.session is services[0].session
            assert established_tcp(os.getpid()) <= 2, "one link to the agent, not one a service"
        own = Service("own", realm=realm, agent="hostA", connect=[ep], shared=False).start()
        assert own.session is not services[0].session
        own.close()
        assert not services[0].session.is_closed()
    finally:
        shared = services[0].session
        for svc in services:
            svc.close()
    assert shared.is_closed()  # the last service out closed it


@pytest.mark.parametrize("topology", ["client", "peer"])
def test_samples_cross_processes_in_both_topologies(processes, realm, topology) -> None:
    ep = endpoint(free_port())
    agent(processes, realm, "hostA", ep)
    env = {SDK_MODE_ENV: topology}
    cam = service(processes, realm, "cam", "hostA", ep, "--ability", "pose", "--edge", WORLD,
                  HEAD, env=env)
    consumer = service(processes, realm, "fusion", "hostA", ep, "--need", "head", env=env)
    consumer.wait_for(lambda e: first_from(e, "cam"))
    links = [established_tcp(p.popen.pid) for p in (cam, consumer)]
    if topology == "client":
        assert links == [1, 1], "a client holds one link: to its agent"
    else:
        assert min(links) >= 2, "peers link to each other as well as to the agent"


def test_a_service_started_before_its_agent_connects_when_it_comes(processes, realm) -> None:
    ep = endpoint(free_port())
    svc = Service("early", realm=realm, agent="hostA", connect=[ep], register_timeout=0.2)
    out = svc.ability("pose", type="pose6d", edge=(WORLD, HEAD), frequency_hz=10)
    try:
        svc.start()  # nothing at ep yet: returns, keeps trying
        assert svc.session is None and svc.connecting
        out.publish(time.time_ns(), [0.0, 0.0, 1.6], [0.0, 0.0, 0.0, 1.0])
        assert out.unsent == 1  # counted, not raised: nobody could have received it
        agent(processes, realm, "hostA", ep)
        assert svc.wait_registered(10.0)
        assert svc.session is not None and not svc.connecting
    finally:
        svc.close()


class _AttachingSession:
    """A real session, but for a sample published on the service's other thread just as
    its publishers are declared (the moment a service started before its agent attaches)."""

    def __init__(self, session: zenoh.Session, publish) -> None:
        self._session, self._publish = session, publish

    def __getattr__(self, name: str):
        return getattr(self._session, name)

    def declare_publisher(self, key: str):
        self._publish()
        return self._session.declare_publisher(key)


def test_a_sample_published_while_the_service_attaches_is_unsent_not_an_error(
        monkeypatch, realm) -> None:
    from agent.runtime.session import open_session
    from agent.sdk import service as service_module
    svc = Service("early", realm=realm, agent="hostA", connect=[endpoint(free_port())],
                  register_timeout=0.1)
    out = svc.ability("pose", type="pose6d", edge=(WORLD, HEAD), frequency_hz=10)
    published: list[BaseException | None] = []

    def publish() -> None:   # on a thread of its own, as the service's own code publishes
        def run() -> None:
            try:
                out.publish(time.time_ns(), [0.0, 0.0, 1.6], [0.0, 0.0, 0.0, 1.0])
                published.append(None)
            except UmaError as exc:
                published.append(exc)
        thread = threading.Thread(target=run)
        thread.start()
        thread.join(5.0)

    monkeypatch.setattr(service_module, "acquire_session", lambda *args, **kw: (
        _AttachingSession(open_session("peer", listen=[]), publish)))
    try:
        svc.start()
        assert published == [None] and out.unsent == 1 and svc.session is not None
        out.publish(time.time_ns(), [0.0, 0.0, 1.6], [0.0, 0.0, 0.0, 1.0])   # sent
        assert out.unsent == 1
    finally:
        svc.close()


class _StuckSession:
    """A session whose close times out, as Zenoh's does on a CPU-starved host."""

    def close(self) -> None:
        raise zenoh.ZError("close operation timed out!")


def test_closing_a_session_never_raises(caplog) -> None:
    close_session(_StuckSession())  # type: ignore[arg-type]
    assert "did not close cleanly" in caplog.text and "timed out" in caplog.text


def test_a_client_block_never_raises_on_exit(processes, realm) -> None:
    ep = endpoint(free_port())
    agent(processes, realm, "hostA", ep)
    with Client(realm=realm, connect=[ep], shared=False) as client:
        poll(lambda: len(client.agents()) > 0, 10.0, "the agent in the client's view")
        client.session.close()  # closed under the client's feet
    client.close()  # and twice: still nothing raised


def test_an_agent_whose_token_lapses_but_still_answers_keeps_its_services(realm) -> None:
    """A token is not the only sign of life: agent B's token goes (as a lease lapses on a
    starved host) while B still answers; agent A keeps B's services matched.  Once B is
    really gone (closed), A drops them."""
    from agent.daemon.agent import Agent
    from agent.daemon.settings import AgentSettings

    ep_a, ep_b = endpoint(free_port()), endpoint(free_port())
    a = Agent(AgentSettings(realm=realm, agent_id="hostA", listen=[ep_a]))
    b = Agent(AgentSettings(realm=realm, agent_id="hostB", listen=[ep_b], connect=[ep_a]))
    a.start()
    b.start()
    try:
        with Service("cam", realm=realm, agent="hostB", connect=[ep_b]) as cam, \
                Service("fusion", realm=realm, agent="hostA", connect=[ep_a]) as fusion:
            cam.ability("pose", type="pose6d", edge=(WORLD, HEAD), frequency_hz=100)
            fusion.need("head", type="pose6d", edge=(WORLD, "*/head"))
            cam.start()
            fusion.start()
            fusion.wait_matched("head", timeout=15.0)
            checks = a._checks
            b._token.undeclare()  # the token lapses; B itself runs on
            deadline = time.monotonic() + 15.0  # until A has asked B and heard its answer
            while ((a._checks == checks or "hostB" in a._agent_checks)
                   and time.monotonic() < deadline):
                time.sleep(0.05)
            assert a._checks > checks and "hostB" not in a._agent_checks
            handled = threading.Event()  # A's worker is past the answer's handling
            a._worker.put(handled.set)
            assert handled.wait(10.0)
            assert [m.service_id for m in fusion.matches("head")] == ["cam"]
            assert "hostB" in a.view.live_agents
            b.close()  # now B is gone for real: its services go with it, and so does B
            fusion.wait_matched("head", timeout=15.0, until=lambda ms: not ms)
            deadline = time.monotonic() + 15.0  # A's next resync (every 5 s) checks again
            while "hostB" in a.view.live_agents and time.monotonic() < deadline:
                time.sleep(0.1)
            assert "hostB" not in a.view.live_agents
    finally:
        b.close()
        a.close()
