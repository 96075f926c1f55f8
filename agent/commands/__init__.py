"""One module per ``uma`` command that runs the agent side (the grammar is in ``agent.cli``)."""
