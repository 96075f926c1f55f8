"""An agent's stream digest: the newest sample of each of its services' pose streams, put a
few tens of times a second while someone listens (``uma view``).

``uma/R/agent/A/digest`` carries ``{"agent": A, "samples": {"<service>/<ability>": sample
bytes}}``: each sample exactly as its service published it on ``uma/R/data/A/<service>/
<ability>`` (``schemas.codec``).  A viewer that draws at 30 Hz needs the newest sample of
each stream, not every one: subscribed to every data key, it receives every sample in its
transport (20,000 a second for 200 frames at 100 Hz) and falls seconds behind on a loaded
host; subscribed to the digests it receives one message per agent per digest.
"""

from __future__ import annotations

from collections.abc import Mapping

from agent.protocol import keys
from schemas.codec import DecodeError, decode_message, encode_message

#: streams one digest carries at most (a message must stay well under the codec's 1 MiB)
MAX_DIGEST_STREAMS = 4096


def digest_message(agent: str, samples: Mapping[tuple[str, str], bytes]) -> bytes:
    """The digest of ``samples``: the newest payload by (service id, ability name)."""
    return encode_message({"agent": agent, "samples": {
        f"{service}/{ability}": data for (service, ability), data in samples.items()}})


def read_digest(data: bytes, realm: str, agent: str) -> dict[str, bytes]:
    """The samples of agent ``agent``'s digest by their data key; ``DecodeError`` names
    what is wrong (another agent's name, a malformed stream name or sample)."""
    msg = decode_message(data, required=("agent", "samples"))
    if msg["agent"] != agent:
        raise DecodeError(f"digest names agent {str(msg['agent'])[:64]!r}, not the agent of "
                          "its key")
    samples = msg["samples"]
    if not isinstance(samples, dict) or len(samples) > MAX_DIGEST_STREAMS:
        raise DecodeError(f"digest: samples must be a map of at most {MAX_DIGEST_STREAMS} "
                          "streams")
    out = {}
    for name, payload in samples.items():
        service, _, ability = str(name).partition("/")
        if not isinstance(payload, bytes):
            raise DecodeError(f"digest: the sample of {str(name)[:64]!r} is not bytes")
        try:
            out[keys.data(realm, agent, service, ability)] = payload
        except ValueError as exc:
            raise DecodeError(f"digest: stream {str(name)[:64]!r}: {exc}") from None
    return out
