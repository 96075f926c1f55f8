"""The ``uma`` command line: one module per command, the grammar in :mod:`agent.cli.main`.

Every module here runs in the process of the command the user typed; each imports the
part of uma it drives (the daemon, the SDK) only when its command runs.
"""

from agent.cli.main import main

__all__ = ["main"]
