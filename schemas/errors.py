"""The base of every error uma explains to its user, here in the lowest layer so that the
contracts' own errors (a message that does not decode, an expression that does not parse)
are ``UmaError`` too.  Code imports it as ``agent.errors.UmaError`` (``from agent import
UmaError``), where its kinds are."""


class UmaError(Exception):
    """A failure explained to the user (the CLI prints it without a traceback, exit 1)."""
