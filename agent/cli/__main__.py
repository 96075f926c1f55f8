"""``python -m agent.cli``: the ``uma`` command without the console script."""

from agent.cli.main import run

run()
