"""Reading a recording back, also one whose writer was killed or whose disk filled.

A complete file is read through its summary and indexes (``mcap``'s seeking reader). A file
without a usable summary (the writer was killed, the disk was full, the tail is damaged) is
read record by record from the start up to the first damaged or missing byte;
:attr:`Recording.damage` then says where it broke and what was lost.  Every error from the
``mcap`` library becomes an ``UmaError`` naming the file.
"""

from __future__ import annotations

import os
import struct
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from agent.errors import UmaError


@dataclass(frozen=True)
class Channel:
    id: int
    topic: str
    message_encoding: str
    metadata: dict[str, str]


@dataclass(frozen=True)
class Message:
    channel: Channel
    log_ns: int
    publish_ns: int
    data: bytes


@dataclass
class Recording:
    """A recording's channels, metadata and messages (in log-time order)."""

    path: str
    size: int
    channels: dict[int, Channel] = field(default_factory=dict)
    metadata: dict[str, dict[str, str]] = field(default_factory=dict)
    messages: list[Message] = field(default_factory=list)
    #: None for a complete file, else what broke and what was lost
    damage: str | None = None


def read(path: str | Path) -> Recording:
    """The whole recording at ``path`` (see the module docstring)."""
    path = str(path)
    try:
        size = os.path.getsize(path)
    except OSError as exc:
        raise UmaError(f"cannot read {path}: {exc.strerror or exc}") from None
    rec = Recording(path, size)
    try:
        _read_indexed(rec)
    except Exception:  # no summary, or one that does not hold: read it as a stream
        rec = Recording(path, size)
        _read_stream(rec)
    rec.messages.sort(key=lambda m: m.log_ns)
    return rec


def _read_indexed(rec: Recording) -> None:
    from mcap.reader import SeekingReader

    with open(rec.path, "rb") as f:
        reader = SeekingReader(f, validate_crcs=True)
        summary = reader.get_summary()
        if summary is None:
            raise ValueError("no summary")
        for meta in reader.iter_metadata():
            rec.metadata[meta.name] = dict(meta.metadata)
        for _schema, ch, msg in reader.iter_messages(log_time_order=True):
            channel = rec.channels.get(ch.id)
            if channel is None:
                channel = rec.channels[ch.id] = _channel(ch)
            rec.messages.append(Message(channel, msg.log_time, msg.publish_time, msg.data))
        for ch in summary.channels.values():
            rec.channels.setdefault(ch.id, _channel(ch))


def _channel(ch: Any) -> Channel:
    return Channel(ch.id, ch.topic, ch.message_encoding, dict(ch.metadata))


def _read_stream(rec: Recording) -> None:
    """Record by record until the footer or the first damaged byte."""
    from mcap import records
    from mcap.stream_reader import StreamReader

    with open(rec.path, "rb") as f:
        good = 0
        footer = False
        try:
            for r in StreamReader(f, validate_crcs=True,
                                      record_size_limit=rec.size).records:
                if isinstance(r, records.Channel):
                    rec.channels.setdefault(r.id, _channel(r))
                elif isinstance(r, records.Message) and r.channel_id in rec.channels:
                    rec.messages.append(Message(rec.channels[r.channel_id], r.log_time,
                                                r.publish_time, r.data))
                elif isinstance(r, records.Metadata):
                    rec.metadata[r.name] = dict(r.metadata)
                elif isinstance(r, records.Footer):
                    footer = True
                good = f.tell()
        except Exception as exc:  # the mcap library raises many kinds on damaged bytes
            rec.damage = _damage(rec, good, exc)
            return
    if not footer:
        rec.damage = _damage(rec, good, None)


def _damage(rec: Recording, good: int, exc: Exception | None) -> str:
    if not rec.channels and good == 0:
        reason = f": {exc}" if exc is not None and str(exc) else ""
        raise UmaError(f"{rec.path} is not a readable MCAP file (damaged before its first "
                       f"record{reason})")
    why = _why(exc, at_end=good == rec.size)
    last = max((m.log_ns for m in rec.messages), default=None)
    until = f", up to log time {last} ns" if last is not None else ""
    lost = (f"the {rec.size - good} bytes after it (at most the last chunk, about a second) "
            "and the index are lost" if good < rec.size else
            "only the index is lost (the writer stopped before writing it)")
    return (f"{rec.path} is truncated or damaged after byte {good} of {rec.size} ({why}); "
            f"read {len(rec.messages)} messages before the damage{until}; {lost}")


def _why(exc: Exception | None, at_end: bool) -> str:
    """The damage in words (the mcap library's exceptions say little about truncation)."""
    from mcap.exceptions import EndOfFile, RecordLengthLimitExceeded

    if exc is None or at_end:
        return "it ends without a footer"
    if isinstance(exc, EndOfFile | struct.error):
        return "it ends inside a record"
    if isinstance(exc, RecordLengthLimitExceeded):
        return "a record claims more bytes than the file holds"
    return f"{type(exc).__name__}: {exc}"
