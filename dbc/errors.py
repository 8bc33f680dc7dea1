"""The one exception that carries a user-facing message (what failed, where, how to fix).

Both command lines (`hil-gateway`, `hil-plant`) report it as one paragraph and exit with
its status, without a traceback."""

from __future__ import annotations


class UserError(Exception):
    """A failure caused by the user's input or environment, reported without a traceback.

    The message is one paragraph: what failed, where (file, key, interface, node), and
    what to do about it. ``exit_code`` is the process exit status (2 for bad input).
    """

    def __init__(self, message: str, exit_code: int = 2) -> None:
        super().__init__(message)
        self.exit_code = exit_code
