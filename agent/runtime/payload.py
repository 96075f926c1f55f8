"""A Zenoh payload's bytes, its size checked before they are copied.

``ZBytes.to_bytes()`` copies the whole payload into Python; the codec then refuses a
message over 1 MiB (``schemas.codec``).  Checking ``len()`` first (which copies nothing)
spares the copy of what would be refused anyway.
"""

from __future__ import annotations

import zenoh

from schemas.codec import MAX_MESSAGE_BYTES, DecodeError


def payload_bytes(payload: zenoh.ZBytes | None, limit: int = MAX_MESSAGE_BYTES) -> bytes:
    """The payload's bytes (none: empty); ``DecodeError`` naming both sizes, before any
    copy, when it is longer than ``limit``."""
    if payload is None:
        return b""
    size = len(payload)
    if size > limit:
        raise DecodeError(f"message of {size} bytes exceeds the limit of {limit}")
    return payload.to_bytes()
