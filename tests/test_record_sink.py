"""The recording writer's limits, on a real file system: a disk that fills up, a disk slower
than the samples (its queue overflows), and the file they leave behind."""

from __future__ import annotations

import contextlib
import json
import subprocess
import time

import numpy as np
import pytest

from agent.protocol import keys
from agent.protocol.registration import snapshot_message
from agent.record import layout
from agent.record.reader import read
from schemas.codec import encode_descriptor, encode_pose
from schemas.models import Ability, ServiceDescriptor

pytest.importorskip("mcap")
pytest.importorskip("rosbags")

REALM = "lab"
KEY = keys.data(REALM, "a1", "cam", "pose")


def _snapshot() -> tuple[str, bytes]:
    """Agent a1's snapshot describing service cam's pose ability."""
    ability = Ability(name="pose", type="pose6d", edge=("ivy/world", "cam/rig"),
                      attributes={"frequency_hz": 100.0})
    desc = ServiceDescriptor(service_id="cam", agent_id="a1", abilities=[ability])
    info = {"agent_id": "a1", "realm": REALM}
    data = snapshot_message(info, 1, 1, [{"descriptor": encode_descriptor(desc),
                                          "instance": "i1"}])
    return keys.agent_services(REALM, "a1"), data


def _pose(i: int, rng: np.random.Generator) -> bytes:
    q = rng.normal(size=4)
    return encode_pose(1_700_000_000_000_000_000 + i * 10_000_000, rng.normal(size=3),
                       q / np.linalg.norm(q), seq=i + 1)


@contextlib.contextmanager
def small_disk(path, size: str = "192k"):
    """A real tmpfs of ``size`` at ``path`` (skips where mounting is not allowed)."""
    path.mkdir()
    out = subprocess.run(["mount", "-t", "tmpfs", "-o", f"size={size}", "tmpfs", str(path)],
                         capture_output=True, text=True)
    if out.returncode != 0:
        pytest.skip(f"cannot mount a small tmpfs here: {out.stderr.strip()}")
    try:
        yield path
    finally:
        subprocess.run(["umount", "-l", str(path)], capture_output=True)


def test_a_full_disk_stops_the_recording_and_leaves_a_readable_file(tmp_path) -> None:
    from agent.record.sink import RecordingSink

    rng = np.random.default_rng(1)
    with small_disk(tmp_path / "disk") as disk:
        path = disk / "full.mcap"
        sink = RecordingSink(str(path), REALM, [], flush_s=0.05)
        sink.offer(*_snapshot(), time.time_ns())
        offered = 0
        for i in range(200_000):               # far more than 192 kB holds
            if sink.stopped.is_set():
                break
            sink.offer(KEY, _pose(i, rng), time.time_ns())
            offered += 1
            if i % 200 == 0:
                time.sleep(0.002)              # let the writer reach the disk
        stats = sink.close()
        assert sink.stopped.is_set() and "the disk is full" in stats.error, stats.error
        rec = read(path)
        written = [m for m in rec.messages if m.channel.topic == KEY]
        assert len(written) > 100 and rec.damage and "without a footer" in rec.damage
        assert path.stat().st_size <= 192 * 1024
        # the counts are the file's: what is in it is counted written, everything else
        # (the chunk being written when the disk filled included) dropped
        assert stats.messages[KEY] == len(written)
        assert len(written) + stats.dropped[KEY] == offered


def test_a_disk_full_from_the_start_records_nothing_and_says_so(tmp_path) -> None:
    from agent.record.sink import RecordingSink

    rng = np.random.default_rng(2)
    with small_disk(tmp_path / "disk", "64k") as disk:
        with contextlib.suppress(OSError), open(disk / "filler", "wb") as f:
            f.write(b"\0" * 128 * 1024)
        path = disk / "full.mcap"
        sink = RecordingSink(str(path), REALM, [], flush_s=0.05)
        sink.offer(*_snapshot(), time.time_ns())
        for i in range(200):
            sink.offer(KEY, _pose(i, rng), time.time_ns())
        stats = sink.close()
        assert "the disk is full" in (stats.error or ""), stats.error
        assert path.stat().st_size == 0
        assert sum(stats.messages.values()) == 0 and stats.dropped[KEY] == 200


def test_a_slow_disk_drops_are_counted_and_reported(tmp_path) -> None:
    from agent.record.sink import RecordingSink

    rng = np.random.default_rng(2)
    path = tmp_path / "slow.mcap"
    sink = RecordingSink(str(path), REALM, [], queue_size=64)
    sink.offer(*_snapshot(), time.time_ns())
    payloads = [_pose(i, rng) for i in range(20_000)]
    for p in payloads:                         # faster than the writer: the queue overflows
        sink.offer(KEY, p, time.time_ns())
    stats = sink.close()
    assert stats.error is None and stats.dropped[KEY] > 0
    rec = read(path)
    written = [m.data for m in rec.messages if m.channel.topic == KEY]
    assert len(written) + stats.dropped[KEY] == len(payloads)
    assert set(written) <= set(payloads) and rec.damage is None
    assert json.loads(rec.metadata[layout.META_END]["dropped"]) == {KEY: stats.dropped[KEY]}
    ability = layout.ability_of(next(c for c in rec.channels.values()
                                     if c.topic == KEY).metadata)
    assert ability.edge == ("ivy/world", "cam/rig")


def test_no_ros_leaves_out_the_tf_channels(tmp_path) -> None:
    from mcap.reader import make_reader

    from agent.record.sink import RecordingSink

    rng = np.random.default_rng(3)
    files = {}
    for ros in (True, False):
        path = tmp_path / f"ros_{ros}.mcap"
        sink = RecordingSink(str(path), REALM, [], ros=ros)
        sink.offer(*_snapshot(), time.time_ns())
        for i in range(20):
            sink.offer(KEY, _pose(i, rng), time.time_ns())
        assert sink.close().error is None
        files[ros] = read(path)
        with open(path, "rb") as f:
            assert make_reader(f).get_header().profile == ("ros2" if ros else "")
    topics = {ros: {c.topic for c in rec.channels.values()} for ros, rec in files.items()}
    assert layout.TF_TOPIC in topics[True] and layout.TF_TOPIC not in topics[False]
    assert topics[True] - topics[False] == {layout.TF_TOPIC}
    assert len([m for m in files[True].messages if m.channel.topic == layout.TF_TOPIC]) == 20


def test_undecodable_bytes_are_recorded_as_received_and_counted(tmp_path) -> None:
    from agent.record.sink import RecordingSink

    path = tmp_path / "bad.mcap"
    good = _pose(0, np.random.default_rng(4))
    sink = RecordingSink(str(path), REALM, [])
    sink.offer(*_snapshot(), time.time_ns())
    for data in (good, b"\xc1 not msgpack", good):
        sink.offer(KEY, data, time.time_ns())
    stats = sink.close()
    assert stats.undecodable == 1 and stats.error is None
    rec = read(path)
    assert [m.data for m in rec.messages if m.channel.topic == KEY] == [good, b"\xc1 not msgpack",
                                                                         good]
    assert len([m for m in rec.messages if m.channel.topic == layout.TF_TOPIC]) == 2
    assert rec.metadata[layout.META_END]["undecodable"] == "1"
