"""Bounds against buggy and hostile peers (issue 22, findings 5, 6, 10, 11): what a peer
sends cannot grow a log, a cache or a queue without bound, and every refusal is counted."""

from __future__ import annotations

import logging

from agent.runtime.logs import RateLimitedLog, kind_of


def test_log_keys_on_the_kind_of_error_not_its_values(caplog) -> None:
    """11,600 bad messages gave 497 warnings: the limiter keyed on byte values and
    positions.  One sender's malformed messages of one kind now give one line."""
    rl = RateLimitedLog(logging.getLogger("uma.test.kind"), interval=60)
    with caplog.at_level(logging.WARNING, logger="uma.test.kind"):
        for i in range(2000):
            rl.warning("data uma/r/data/a/s/p",
                       f"not valid msgpack: unpack(b) received extra data at {i} "
                       f"(byte 0x{i % 256:02x}) in 'x{i}'")
            rl.warning("data uma/r/data/a/s/p", f"expected a pose6d measurement, got {i}")
    assert len(caplog.records) == 2
    assert rl.seen == 4000 and rl.logged == 2
    assert kind_of("byte 0xc1 at 17 in 'abc'") == kind_of("byte 0x92 at 3 in 'zz'")
    assert kind_of("field 'k' missing") != kind_of("field 'k': not a string")


def test_log_bounds_a_flood_of_distinct_senders_and_reports_the_count(caplog) -> None:
    rl = RateLimitedLog(logging.getLogger("uma.test.flood"), interval=60, burst=5,
                        max_keys=100)
    with caplog.at_level(logging.WARNING, logger="uma.test.flood"):
        for i in range(3000):
            rl.warning(f"supernode uma/r/agent/forged{i}/supernode", "malformed summary")
    assert len(caplog.records) == 5 and len(rl._last) <= 100
    rl.interval = 0  # the next window: the swallowed ones are reported by count
    with caplog.at_level(logging.WARNING, logger="uma.test.flood"):
        rl.warning("supernode uma/r/agent/late/supernode", "malformed summary")
    assert "2995 more warnings" in caplog.records[-2].getMessage()
    assert caplog.records[-1].getMessage().startswith("supernode uma/r/agent/late")
