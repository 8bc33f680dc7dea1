"""The user-facing error of the gateway's commands (defined in :mod:`dbc.errors`)."""

from dbc.errors import UserError

__all__ = ["UserError"]
