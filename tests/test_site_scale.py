"""Issue 23 at site scale: 20 hosts in network namespaces, one agent each with 10 services,
form one realm, and ``uma services`` run from a host of its own lists all 200.

The wall time of ``uma services`` is printed, not asserted (its goal, <= 1 s, is measured
by ``bench/bench_site_scale.py``).  Needs root: skips otherwise (see the ``site`` fixture).
"""

from __future__ import annotations

import time

import pytest
from agent_helpers import scale

AGENTS, SERVICES_PER_AGENT = 20, 10
#: low, so that 20 agents and 20 service processes fit on 2 shared cores
RATE_HZ = 2.0


@pytest.mark.slow
@pytest.mark.alone
def test_twenty_hosts_form_one_realm_that_lists_all_services(site, realm) -> None:
    s = site(AGENTS + 1)  # the last host runs only the client
    started = time.monotonic()
    realm_ = scale.start(s, realm)
    scale.add_services(realm_, SERVICES_PER_AGENT, RATE_HZ)
    realm_.wait_listed(SERVICES_PER_AGENT)
    formed_s = time.monotonic() - started

    listing, wall_s = realm_.services_json()
    assert listing["problems"] == []
    assert [a["agent_id"] for a in listing["agents"]] == sorted(h.name for h in s.hosts[:-1])
    for a in listing["agents"]:
        assert [svc["service_id"] for svc in a["services"]] == \
            sorted(f"s{i}" for i in range(SERVICES_PER_AGENT))
        assert a["endpoints"] == [s.hosts[int(a["agent_id"][1:])].endpoint()]
        assert all([(ab["name"], ab["type"]) for ab in svc["abilities"]] == [("pose", "pose6d")]
                   for svc in a["services"])
    print(f"\n{AGENTS} agents x {SERVICES_PER_AGENT} services: realm formed in "
          f"{formed_s:.1f} s; `uma services` listed all in {wall_s:.2f} s; agents started "
          f"again after a stalled Zenoh session: {realm_.restarts or 'none'}")
