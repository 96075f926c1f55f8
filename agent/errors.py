"""The error a user of uma sees: a message that says what was asked and why it failed."""


class UmaError(Exception):
    """A failure explained to the user (the CLI prints it without a traceback, exit 1)."""
