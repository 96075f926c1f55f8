"""What ``uma agent`` can be told (command line and/or TOML config), checked before use.

``AgentSettings.check`` names the setting that is wrong; ``check_static_edge`` checks and
normalises one ``[[static]]`` table of the config (a fixed transform the agent's SRG holds
from the start, see ``agent.daemon.srg_node``).
"""

from __future__ import annotations

import math
import re
from collections.abc import Mapping
from dataclasses import dataclass, field
from typing import Any

from agent.errors import UmaError
from agent.geometry import check_quaternion, check_vector
from agent.protocol import keys


@dataclass
class AgentSettings:
    """Everything ``uma agent`` can be told (command line and/or TOML config)."""

    realm: str = "default"
    agent_id: str = field(default_factory=keys.default_agent_id)
    mode: str = "peer"
    listen: list[str] | None = None
    connect: list[str] = field(default_factory=list)
    services: list[str] = field(default_factory=list)
    static_edges: list[dict[str, Any]] = field(default_factory=list)
    grace_s: float = 0.5
    rate_window_s: float = 0.5
    lease_ms: int | None = None
    tick_s: float = 0.05
    #: listen without TLS where other hosts reach it (refused otherwise: safe by default)
    insecure: bool = False

    def check(self) -> AgentSettings:
        """Validate; ``UmaError`` names the setting that is wrong."""
        keys.check_name("realm", self.realm)
        keys.check_name("agent id", self.agent_id)
        if self.mode not in ("peer", "client"):
            raise UmaError(f"mode {self.mode!r}: an agent runs as 'peer' or 'client'")
        for name in ("grace_s", "rate_window_s", "tick_s"):
            value = getattr(self, name)
            if not isinstance(value, int | float) or not 0 < value <= 60:
                raise UmaError(f"{name} must be a number of seconds in (0, 60], got {value!r}")
        self.static_edges = [check_static_edge(e, i) for i, e in enumerate(self.static_edges)]
        return self


def check_static_edge(edge: Any, i: int) -> dict[str, Any]:
    """A ``[[static]]`` table, checked and normalised (lists of floats, unit quaternion)."""
    where = f"static edge #{i + 1}"
    if not isinstance(edge, Mapping):
        raise UmaError(f"{where}: expected a table, got {type(edge).__name__}")
    allowed = {"parent", "child", "position", "quaternion", "pos_std_m", "rot_std_rad"}
    unknown = set(edge) - allowed
    if unknown:
        raise UmaError(f"{where}: unknown key(s) {', '.join(sorted(unknown))} "
                       f"(allowed: {', '.join(sorted(allowed))})")
    out: dict[str, Any] = {}
    for k in ("parent", "child"):
        v = edge.get(k)
        if not isinstance(v, str) or not re.fullmatch(r"[A-Za-z0-9_.\-]+(/[A-Za-z0-9_.\-]+)*", v):
            raise UmaError(f"{where}: {k} must be a frame id like 'ivy/world', got {v!r}")
        out[k] = v
    if out["parent"] == out["child"]:
        raise UmaError(f"{where}: parent and child are both {out['parent']!r}")
    try:
        out["position"] = check_vector(edge.get("position"), f"{where} position").tolist()
        out["quaternion"] = check_quaternion(edge.get("quaternion"),
                                             f"{where} quaternion").tolist()
    except ValueError as exc:
        raise UmaError(str(exc)) from None
    if len(out["position"]) != 3 or len(out["quaternion"]) != 4:
        raise UmaError(f"{where}: position needs 3 numbers and quaternion 4 (x, y, z, w)")
    for k in ("pos_std_m", "rot_std_rad"):
        if k in edge:
            v = edge[k]
            if isinstance(v, bool) or not isinstance(v, int | float) or not (
                    math.isfinite(v) and v >= 0):
                raise UmaError(f"{where}: {k} must be a finite number >= 0, got {v!r}")
            out[k] = float(v)
    return out
