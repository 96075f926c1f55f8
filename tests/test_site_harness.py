"""The site harness itself (:mod:`agent_helpers.site`): hosts reach each other only over
the bridge, a cut link carries nothing until healed, nothing lands in the machine's own
namespace, and closing a site leaves no process and no namespace behind."""

from __future__ import annotations

import subprocess

import pytest
from agent_helpers import site as site_mod
from agent_helpers.site import NETNS_DIR, Site

#: a TCP server that says "ready" once it listens, then accepts until killed
SERVER = ("import socket, sys\n"
          "s = socket.create_server((sys.argv[1], 9000)); print('ready', flush=True)\n"
          "while True: s.accept()[0].close()\n")
#: exits 0 if it connects to ARGV[1]:9000 within 1 s, else 1
CLIENT = ("import socket, sys\n"
          "try: socket.create_connection((sys.argv[1], 9000), timeout=1).close()\n"
          "except OSError: sys.exit(1)\n")


def reaches(s: Site, src: int, dst: int) -> bool:
    return s.run(s.hosts[src], ["-c", CLIENT, s.hosts[dst].addr], 30).returncode == 0


def root_links() -> str:
    return subprocess.run(["ip", "-o", "link"], capture_output=True, text=True,
                          check=True).stdout


def test_hosts_reach_each_other_over_the_bridge_and_a_cut_link_carries_nothing(site) -> None:
    before = root_links()
    s = site(3)
    assert root_links() == before
    assert len({h.addr for h in s.hosts}) == 3
    assert all(h.addr.startswith(f"10.77.{s.subnet}.") for h in s.hosts)
    s.spawn(s.hosts[1], ["-c", SERVER, s.hosts[1].addr]).wait_line("ready")
    assert reaches(s, 0, 1) and reaches(s, 2, 1)

    s.cut(s.hosts[1])
    assert not reaches(s, 0, 1)
    s.heal(s.hosts[1])
    assert reaches(s, 0, 1)


def test_close_stops_processes_and_deletes_namespaces(site) -> None:
    s = site(2)
    server = s.spawn(s.hosts[0], ["-c", SERVER, s.hosts[0].addr])
    server.wait_line("ready")
    names = {h.netns for h in s.hosts} | {s.bridge_ns}
    assert names <= {p.name for p in NETNS_DIR.iterdir()}

    s.close()
    assert server.popen.poll() is not None
    assert not names & {p.name for p in NETNS_DIR.iterdir()}


def test_a_site_left_by_a_killed_run_is_removed_by_the_next(site) -> None:
    proc = subprocess.Popen(["true"])  # its PID no longer exists once it has exited
    proc.wait()
    stale = f"{site_mod.PREFIX}{proc.pid}x0-h0"
    site_mod.ip("netns", "add", stale)
    try:
        site(1)
        assert stale not in {p.name for p in NETNS_DIR.iterdir()}
    finally:
        if (NETNS_DIR / stale).exists():
            site_mod.ip("netns", "del", stale)


def test_unavailable_names_what_is_missing(monkeypatch) -> None:
    monkeypatch.setattr(site_mod.os, "geteuid", lambda: 1000)
    assert "root" in site_mod.unavailable()
    monkeypatch.setattr(site_mod.os, "geteuid", lambda: 0)
    monkeypatch.setattr(site_mod.shutil, "which", lambda name: None)
    assert "`ip`" in site_mod.unavailable()


def test_a_site_has_a_sane_number_of_hosts() -> None:
    with pytest.raises(ValueError, match=r"1\.\.250 hosts"):
        Site(0)
