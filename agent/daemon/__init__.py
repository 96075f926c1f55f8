"""Code that runs in the agent daemon, one process per host (``uma agent``).

:mod:`agent.daemon.agent` is the daemon itself; the other modules are the parts it owns:
matching needs to abilities, its view of the realm, and its SRG node.
"""
