"""Identifiers: the one rule for realms, agent ids, service ids and ability or need names.

Each of them is one chunk of a Zenoh key (``uma/<realm>/data/<agent>/<service>/<ability>``)
and a field of the wire models, so the same rule must hold in both places; it lives here,
in the lowest layer, and :mod:`agent.protocol.keys`, :mod:`schemas.models` and the agent's
settings all call :func:`check_id` / :func:`check_name`.  The rule is the narrowest that
every use accepts: no ``/``, no Zenoh wildcard or reserved character (``*``, ``$``, ``#``,
``?``, ``@``), no ``:`` (Zenoh endpoints and host names use it), no spaces.

- ids (realms, agents, services): letters, digits, ``_``, ``.``, ``-``; at most 64;
- names (abilities, needs): letters, digits, ``_``, ``-``; at most 64.
"""

from __future__ import annotations

import re

ID_PATTERN = r"^[A-Za-z0-9_.\-]+$"
NAME_PATTERN = r"^[A-Za-z0-9_\-]+$"
MAX_LENGTH = 64

_ID_RE = re.compile(ID_PATTERN)
_NAME_RE = re.compile(NAME_PATTERN)
_ID_RULE = "letters, digits, '_', '.' and '-' only"
_NAME_RULE = "letters, digits, '_' and '-' only"


def _check(regex: re.Pattern[str], rule: str, kind: str, value: object) -> str:
    if not isinstance(value, str):
        raise ValueError(f"{kind} must be a string, got {value!r}")
    if len(value) > MAX_LENGTH:
        raise ValueError(f"{kind} {value[:40]!r}... is longer than {MAX_LENGTH} characters")
    if not regex.match(value):
        raise ValueError(f"{kind} {value!r} is not valid: {rule}, at most {MAX_LENGTH} "
                         "characters (e.g. 'hostA', 'cam-nw', 'lab_2')")
    return value


def is_id(value: str) -> bool:
    """Whether ``value`` passes :func:`check_id` (for parsing received keys, where a wrong
    chunk means "not one of ours", not an error to explain)."""
    return len(value) <= MAX_LENGTH and _ID_RE.match(value) is not None


def check_id(kind: str, value: object) -> str:
    """``value`` if it is a valid realm, agent id or service id; else ``ValueError`` naming
    ``kind``, the value and the rule."""
    return _check(_ID_RE, _ID_RULE, kind, value)


def check_name(kind: str, value: object) -> str:
    """``value`` if it is a valid ability or need name; else ``ValueError`` as above."""
    return _check(_NAME_RE, _NAME_RULE, kind, value)
