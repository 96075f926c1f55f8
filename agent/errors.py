"""The errors a user of uma sees: a message that says what was asked and why it failed.

Every error uma raises at its user derives from :class:`UmaError`, so one ``except
UmaError`` catches them all (as tf2's ``TransformException`` and zenoh's ``ZError``).  Each
kind keeps the builtin base it has always had as a second parent, so code that catches
``ValueError``, ``LookupError`` or ``TimeoutError`` still does.  ``UmaError`` itself is
defined in ``schemas.errors`` (the lowest layer), so the contracts' errors
(``schemas.codec.DecodeError``, ``schemas.expr.ExprError``) are ``UmaError`` too.
"""

from schemas.errors import UmaError

__all__ = ["InvalidInputError", "NotFoundError", "UmaError", "UmaTimeoutError"]


class InvalidInputError(UmaError, ValueError):
    """Something given to uma is malformed: an argument, a pose, an attribute."""


class NotFoundError(UmaError, LookupError):
    """Something asked for is not there (yet): a frame, an edge, a route, an agent's data."""


class UmaTimeoutError(UmaError, TimeoutError):
    """Something did not happen in the time allowed."""
