"""An output file an option names, checked before any work: its directory exists and it
can be written there (so a long command does not fail at its very end)."""

from __future__ import annotations

import os
from pathlib import Path

from gateway.errors import UserError


def check_writable(p: Path, option: str) -> None:
    """:class:`UserError` (exit 2) naming ``option`` unless ``p`` can be written: not a
    directory, its directory exists and is writable, and the file, if there, too."""
    parent = p.parent if str(p.parent) else Path(".")
    if p.is_dir():
        raise UserError(f"{option} {str(p)!r} is a directory; give a file name")
    if not parent.is_dir():
        raise UserError(f"{option} {str(p)!r}: the directory {str(parent)!r} does not exist; "
                        "create it or choose another place")
    if not os.access(parent, os.W_OK) or (p.exists() and not os.access(p, os.W_OK)):
        raise UserError(f"{option} {str(p)!r} is not writable (permission denied); choose "
                        "another place")
