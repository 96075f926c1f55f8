"""``uma view`` in a real headless Chromium (Selenium): the page of a live realm.

Two agents, the simulator and a tracker (the accelerometer rig, whose reset need is matched
to the simulator's head) run as separate processes on loopback; the view is one more.
"""

from __future__ import annotations

import re
import time
from collections.abc import Iterator
from typing import Any

import pytest
from agent_helpers.browser import chromium, scene_png, wait_text
from agent_helpers.harness import WAIT_S, agent, poll, spawn
from conftest import endpoint, free_port

#: the page must show a departure within this (the issue's bound)
DEPARTURE_S = 2.0
#: the match row: ability -> need, its measured rate and latency, its state
MATCH = re.compile(r"lab/sim/head → lab/accel-rig\.reset [\d.]+ Hz [\d.]+ ms streaming")


@pytest.fixture(scope="module")
def browser() -> Iterator[Any]:
    """One Chromium for the module's pages: starting it costs a few CPU-seconds."""
    with chromium() as driver:
        yield driver


def _view(processes, realm: str, ep: str):
    view = spawn(processes, ["-m", "agent.cli", "view", "--realm", realm, "--connect", ep,
                             "--port", "0", "--root", "ivy/world"])
    line = view.wait_line("uma view: http://", 60)
    return view, re.search(r"http://\S+/", line).group(0)


def test_the_page_shows_a_live_realm(processes, realm, tmp_path, browser):
    ep_lab, ep_app = endpoint(free_port()), endpoint(free_port())
    config = tmp_path / "lab.toml"  # a static edge the page learns from the agent's answers
    config.write_text('[[static]]\nparent = "ivy/world"\nchild = "ivy/cam_nw"\n'
                      'position = [1.2, 1.2, 2.4]\nquaternion = [0, 0, 0, 1]\n')
    agent(processes, realm, "lab", ep_lab, extra=("--config", str(config)))
    agent(processes, realm, "app", ep_app, connect=(ep_lab,))
    common = ["--realm", realm, "--agent", "lab", "--connect", ep_lab]
    spawn(processes, ["-m", "agent.cli", "service", "run", "sim", *common])
    rig = spawn(processes, ["-m", "agent.cli", "service", "run", "accel-rig", *common])
    _, url = _view(processes, realm, ep_app)
    browser.get(url)
    text = wait_text(browser, lambda t: bool(MATCH.search(t)) and "lab/accel-rig" in t, 90,
                     "both agents, the services and the streaming match")
    assert "app tcp/127.0.0.1" in text and "lab tcp/127.0.0.1" in text, text
    assert "lab/sim\n" in text and "service sim came on agent lab" in text, text
    # the SRG: world, head, both rigs (the simulator's static mountings, the rig's pose)
    # and the agent's configured camera
    wait_text(browser, lambda t: "5 frame(s) placed from ivy/world" in t, WAIT_S,
              "the five frames of the SRG")
    # the query box: the head in the world, its path and covariance
    _query(browser, "alice/head")
    wait_text(browser, lambda t: "path: ivy/world -> alice/head" in t, WAIT_S,
              "the query's answer")
    # the head frame moves: two screenshots of the scene differ
    first = scene_png(browser)
    second = poll(lambda: (lambda s: s if s != first else False)(scene_png(browser)),
                  10, "a changed scene")
    assert second != first
    # killing the tracker removes it from the page within 2 s, and the log says so
    assert "lab/accel-rig" in text
    processes.kill(rig.popen)
    killed = time.monotonic()
    after = wait_text(browser, lambda t: "lab/accel-rig" not in _outside_events(t) and
                      "service accel-rig left agent lab" in t, WAIT_S, "the departure")
    took = time.monotonic() - killed
    print(f"the departure showed on the page {took:.2f} s after the kill")
    assert took <= DEPARTURE_S, f"the departure took {took:.2f} s to show"
    assert "lab/sim\n" in after and "no needs in the realm" in after, after


def _outside_events(text: str) -> str:
    """The page's text without its event log, which keeps naming a departed service (its
    arrival, or a need of it re-matched at start-up on a loaded host)."""
    head, sep, rest = text.partition("\nEvents\n")
    services = rest.find("\nServices\n")
    return text if not sep else head + (rest[services:] if services >= 0 else "")


def _query(browser, target: str) -> None:
    """Type ``target`` into the query box and press its button."""
    from selenium.webdriver.common.by import By

    box = browser.find_element(By.XPATH, "//label[normalize-space()='target']/following::input[1]")
    box.clear()
    box.send_keys(target)
    browser.find_element(By.XPATH, "//button[normalize-space()='query']").click()


def test_an_empty_realm_says_so_and_a_later_realm_shows_up(processes, realm, browser):
    ep = endpoint(free_port())
    _, url = _view(processes, realm, ep)
    browser.get(url)
    wait_text(browser, lambda t: f"No agents in realm {realm} yet" in t, 60,
              "that the realm is empty")
    agent(processes, realm, "late", ep)
    text = wait_text(browser, lambda t: "agent late joined the realm" in t, 30,
                     "the agent that came later")
    assert f"No agents in realm {realm}" not in text and "late tcp/127.0.0.1" in text
