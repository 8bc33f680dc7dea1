"""A file written completely or not at all: the text goes to a temporary name beside the
file and is renamed over it, so a reader sees the old file or the new one, never half."""

from __future__ import annotations

import os
from pathlib import Path


def write_text_atomic(path: Path, text: str, encoding: str = "utf-8") -> Path:
    """Write ``text`` to ``path`` through ``<name>.tmp`` and a rename; on an error the
    temporary file is removed and the :class:`OSError` raised (``path`` is then as it was).
    Returns ``path``."""
    tmp = path.with_name(path.name + ".tmp")
    try:
        tmp.write_text(text, encoding=encoding)
        os.replace(tmp, path)
    except OSError:
        tmp.unlink(missing_ok=True)
        raise
    return path
