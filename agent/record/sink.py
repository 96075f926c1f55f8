"""The writing side of ``uma record``: an MCAP file fed from a bounded queue by its own thread.

Zenoh callbacks only :meth:`RecordingSink.offer` (a non-blocking put), so recording never
slows the realm: when the disk cannot keep up and the queue is full, the sample is dropped
and counted per key, and the counts are reported and written into the file
(``uma.recording.end``).  The writer closes a chunk every ``flush_s`` (compressed, indexed),
so a recorder killed outright loses at most that much.  A full disk (or any write error)
stops the recording with a message naming it; the file is cut back to its last complete
chunk, which ``uma info`` and ``uma play`` read.
"""

from __future__ import annotations

import contextlib
import errno
import json
import logging
import os
import queue
import threading
import time
from collections import Counter
from collections.abc import Callable
from dataclasses import dataclass, field
from importlib.metadata import PackageNotFoundError, version
from typing import Any, BinaryIO

from agent.errors import UmaError
from agent.protocol import keys, parse_snapshot
from agent.record import layout
from agent.record.statics import decode_statics
from agent.runtime import RateLimitedLog
from schemas.codec import DecodeError, decode_measurement, peek_time
from schemas.models import Ability

log = logging.getLogger("uma.record")

#: samples waiting for the disk; beyond this they are dropped and counted
QUEUE_SIZE = 100_000
#: a data key whose ability no snapshot has described yet waits this long for one
DESCRIBE_WAIT_S = 2.0
FLUSH_S = 1.0
CHUNK_BYTES = 1 << 20


def _uma_version() -> str:
    try:
        return version("uma-tracking")
    except PackageNotFoundError:
        return "unknown"


@dataclass
class SinkStats:
    """What was written, dropped and why the recording stopped."""

    messages: Counter = field(default_factory=Counter)   # topic -> messages in the file
    dropped: Counter = field(default_factory=Counter)    # key -> samples not written
    undecodable: int = 0
    bytes_in: int = 0
    error: str | None = None


class RecordingSink:
    """One MCAP recording being written (see the module docstring).

    ``offer(key, data, recv_ns)`` takes data samples and agent publications (snapshots,
    summaries) alike; the key says which.  ``close()`` writes what is queued, the summary
    and the end record, and returns the stats.
    """

    def __init__(self, path: str, realm: str, patterns: list[str], ros: bool = True,
                 queue_size: int = QUEUE_SIZE, flush_s: float = FLUSH_S,
                 compression: str = "zstd") -> None:
        from mcap.writer import CompressionType, Writer

        self.path = path
        self.realm = realm
        self.stats = SinkStats()
        self.stopped = threading.Event()   # set on a write error: the recorder stops
        self._queue: queue.Queue[tuple[str, bytes, int] | None] = queue.Queue(queue_size)
        self._flush_s = flush_s
        self._file: BinaryIO = open(path, "wb")  # noqa: SIM115 (closed by close())
        self._good = 0                            # file size after the last complete flush
        #: messages handed to the writer since the last flush (counted as written only
        #: once flushed: a failed write cuts the file back and they count as dropped)
        self._unflushed: Counter = Counter()
        self._sequence: Counter = Counter()       # topic -> the next message's sequence
        self._writer = Writer(self._file, chunk_size=CHUNK_BYTES,
                              compression=CompressionType[compression.upper()])
        self._channels: dict[str, int] = {}
        self._abilities: dict[str, tuple[Ability, dict[str, Any]]] = {}
        self._waiting: dict[str, tuple[float, list[tuple[bytes, int]]]] = {}
        self._tf = None
        self._log = RateLimitedLog(log)
        self._writer.start(profile="ros2" if ros else "", library=f"uma {_uma_version()}")
        self._writer.add_metadata(layout.META_START, {
            "realm": realm, "patterns": json.dumps(patterns), "started_ns": str(time.time_ns()),
            "uma_version": _uma_version(), "ros": str(bool(ros)).lower()})
        if ros:
            from agent.record.ros import TfEncoder
            self._tf = TfEncoder()
        self._thread = threading.Thread(target=self._run, name="uma-record-writer",
                                        daemon=True)
        self._thread.start()

    # -- the realm's side (Zenoh callbacks): never blocks
    def offer(self, key: str, data: bytes, recv_ns: int) -> None:
        try:
            self._queue.put_nowait((key, data, recv_ns))
        except queue.Full:
            self.stats.dropped[key] += 1

    # -- the writer thread
    def _run(self) -> None:
        next_flush = time.monotonic() + self._flush_s
        while True:
            try:
                item = self._queue.get(timeout=0.1)
            except queue.Empty:
                item = ()
            if item is None:
                return
            try:
                if item:
                    self._write(*item)
                self._retry_waiting(force=False)
                if time.monotonic() >= next_flush:
                    self._flush()
                    next_flush = time.monotonic() + self._flush_s
            except OSError as exc:
                self._fail(exc)
                return
            except Exception as exc:  # a bug must not end the recording silently
                self._log.warning("recording writer", f"{type(exc).__name__}: {exc}")
                if item:
                    self.stats.dropped[item[0]] += 1

    def _write(self, key: str, data: bytes, recv_ns: int) -> None:
        self.stats.bytes_in += len(data)
        kind = layout.kind_of_topic(key)
        if kind is not None:
            self._put(key, lambda: layout.realm_metadata(kind), data, recv_ns, recv_ns)
            if kind == layout.SNAPSHOT:
                self._learn(key, data)
            elif kind == layout.STATIC:
                self._write_static_tf(data, recv_ns)
            return
        if key not in self._channels and key not in self._abilities:
            self._waiting.setdefault(key, (time.monotonic(), []))[1].append((data, recv_ns))
            return
        self._write_data(key, data, recv_ns)

    def _write_data(self, key: str, data: bytes, recv_ns: int) -> None:
        ability, attrs = self._abilities.get(key, (None, {}))
        try:
            t_ns = peek_time(data)
        except DecodeError as exc:
            self.stats.undecodable += 1
            self._log.warning(key, f"undecodable, recorded as received ({exc})")
            t_ns = recv_ns
        self._put(key, lambda: layout.data_metadata(ability, attrs), data, recv_ns, t_ns)
        self._write_tf(ability, data, recv_ns)

    def _write_tf(self, ability: Ability | None, data: bytes, recv_ns: int) -> None:
        if self._tf is None or ability is None or ability.type != "pose6d" or not ability.edge:
            return
        try:
            m = decode_measurement(data, "pose6d")
        except DecodeError:
            return  # counted as undecodable above; its bytes are in the uma channel
        topic = layout.TF_STATIC_TOPIC if ability.attributes.static else layout.TF_TOPIC
        payload = self._tf.encode(ability.edge[0], ability.edge[1], m.t_ns, m.position,
                                  m.quaternion)
        self._put(topic, dict, payload, recv_ns, m.t_ns)

    def _write_static_tf(self, data: bytes, recv_ns: int) -> None:
        """An agent's static edges on /tf_static, stamped with the time they were seen."""
        if self._tf is None:
            return
        try:
            edges = decode_statics(data)["edges"]
        except ValueError as exc:
            self._log.warning("static edges", f"not written to /tf_static ({exc})")
            return
        for e in edges:
            payload = self._tf.encode(e["parent"], e["child"], recv_ns, e["p"], e["q"])
            self._put(layout.TF_STATIC_TOPIC, dict, payload, recv_ns, recv_ns)

    def _put(self, topic: str, metadata: Callable[[], dict[str, str]], data: bytes,
             log_ns: int, publish_ns: int) -> None:
        """Write one message; ``metadata()`` is called once, when ``topic`` gets its channel."""
        channel = self._channels.get(topic)
        if channel is None:
            channel = self._register(topic, metadata())
        self._writer.add_message(channel, log_time=log_ns, data=data, publish_time=publish_ns,
                                 sequence=self._sequence[topic])
        self._sequence[topic] += 1
        self._unflushed[topic] += 1

    def _register(self, topic: str, metadata: dict[str, str]) -> int:
        if topic in (layout.TF_TOPIC, layout.TF_STATIC_TOPIC):
            from agent.record import ros
            schema = self._writer.register_schema(ros.TF_TYPE, ros.SCHEMA_ENCODING,
                                                   self._tf.schema())
            channel = self._writer.register_channel(topic, ros.MESSAGE_ENCODING, schema)
        else:
            channel = self._writer.register_channel(topic, layout.MSGPACK, 0, metadata)
        self._channels[topic] = channel
        return channel

    def _learn(self, key: str, data: bytes) -> None:
        """Abilities of an agent's snapshot, by data key (for the channels' metadata)."""
        try:
            snap = parse_snapshot(data, keys.parse_agent_services(key, self.realm))
        except DecodeError as exc:
            self._log.warning(key, f"unreadable snapshot ({exc})")
            return
        for desc in snap.services.values():
            for ab in desc.abilities:
                data_key = keys.data(self.realm, snap.agent_id, desc.service_id, ab.name)
                self._abilities.setdefault(data_key, (ab, dict(desc.attributes)))
        self._retry_waiting(force=False)

    def _retry_waiting(self, force: bool) -> None:
        """Write the held samples of keys now described (or waited for long enough)."""
        now = time.monotonic()
        for key, (started, held) in list(self._waiting.items()):
            if key in self._abilities or force or now - started > DESCRIBE_WAIT_S:
                del self._waiting[key]
                for data, recv_ns in held:
                    self._write_data(key, data, recv_ns)

    def _flush(self) -> None:
        self._writer.flush()
        self._file.flush()
        self._good = self._file.tell()
        self._committed()

    def _committed(self) -> None:
        """What the writer was given so far is in the file."""
        self.stats.messages.update(self._unflushed)
        self._unflushed.clear()

    def _fail(self, exc: OSError) -> None:
        """Stop on a write error; cut the file back to its last complete chunk."""
        what = "the disk is full" if exc.errno in (errno.ENOSPC, errno.EDQUOT) else str(exc)
        self.stats.dropped.update(self._unflushed)  # cut away with the unfinished chunk
        self._unflushed.clear()
        written = sum(self.stats.messages.values())
        self.stats.error = (f"recording stopped: {what} (writing {self.path}); the file keeps "
                            f"what was flushed before, {self._good} bytes")
        log.error("%s; %d messages written before", self.stats.error, written)
        with contextlib.suppress(OSError):
            self._file.close()
        with contextlib.suppress(OSError):
            os.truncate(self.path, self._good)
        self.stopped.set()
        self._drain()

    def _drain(self) -> None:
        """After a failure nothing more is written: what is still queued counts as dropped."""
        while True:
            try:
                item = self._queue.get_nowait()
            except queue.Empty:
                return
            if item:
                self.stats.dropped[item[0]] += 1

    # -- the end
    def close(self, timeout: float = 30.0) -> SinkStats:
        """Write what is queued, then the summary; the stats (``error`` set on failure)."""
        self._queue.put(None)
        self._thread.join(timeout)
        if self._thread.is_alive():
            raise UmaError(f"the recording writer did not finish within {timeout:g} s")
        if self.stats.error is not None:
            self._drain()  # what was offered while the failed writer drained its queue
            return self.stats
        try:
            self._retry_waiting(force=True)
            self._writer.add_metadata(layout.META_END, {
                "dropped": json.dumps(dict(self.stats.dropped)),
                "undecodable": str(self.stats.undecodable),
                "stopped_ns": str(time.time_ns())})
            self._writer.finish()
            self._file.close()
            self._committed()
        except OSError as exc:
            self._fail(exc)
        return self.stats
