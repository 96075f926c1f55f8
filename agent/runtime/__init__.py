"""What every uma process uses, whatever its role: its Zenoh session, plug-in lookup,
rate-limited logs and the stopping of processes.

The names below are the runtime's public part, what a plug-in (a service, an evaluation,
a command) and a long-running command may use; the modules behind them are internal:

- plug-in declarations: :class:`ServicePlugin`, :class:`EvalPlugin`, :class:`CommandPlugin`
  and :func:`add_network_arguments` (``--realm``, ``--connect``, ``--listen``);
  :func:`load_all`: every plug-in of an entry-point group (a command's own subcommands);
- :func:`stop_on_signals`: an event set on SIGINT/SIGTERM; :func:`stop_processes`: end
  children by PID;
- sessions: :func:`open_session`, :func:`close_session`, :func:`sdk_mode` (client or peer
  for these endpoints), :func:`query` (a bounded ``get``), :func:`lease_ms_default`;
- :class:`RateLimitedLog` and :func:`guarded`: log a peer's bad input and a callback's
  failures without flooding;
- :class:`WakeLoop`: a thread that runs a step when woken (or every period) until closed;
- :func:`compiled_twin`: a hot loop's optional compiled module, or None (pure Python).
"""

from __future__ import annotations

from agent._lazy import lazy_attributes

__all__ = ["CommandPlugin", "EvalPlugin", "RateLimitedLog", "ServicePlugin", "WakeLoop",
           "add_network_arguments", "close_session", "compiled_twin", "guarded", "lease_ms_default",
           "load_all", "open_session", "query", "sdk_mode", "stop_on_signals", "stop_processes"]

__getattr__ = lazy_attributes(__name__, {
    "CommandPlugin": "agent.runtime.plugins",
    "EvalPlugin": "agent.runtime.plugins",
    "ServicePlugin": "agent.runtime.plugins",
    "add_network_arguments": "agent.runtime.plugins",
    "load_all": "agent.runtime.plugins",
    "RateLimitedLog": "agent.runtime.logs",
    "guarded": "agent.runtime.callbacks",
    "close_session": "agent.runtime.session",
    "lease_ms_default": "agent.runtime.session",
    "open_session": "agent.runtime.session",
    "query": "agent.runtime.session",
    "sdk_mode": "agent.runtime.session",
    "stop_on_signals": "agent.runtime.processes",
    "stop_processes": "agent.runtime.processes",
    "WakeLoop": "agent.runtime.worker",
    "compiled_twin": "schemas.native",
})
