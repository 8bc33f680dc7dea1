"""What was parsed from files, kept on disk between processes.

Reading ``drive.dbc`` with cantools took about 0.3 s of every command that encodes frames
(the import 0.1 s, the parse 0.2 s), a third of a `hil-gateway simulate`. The parsed value
is small (2 KB pickled, 0.2 ms to load). :func:`cached` keeps it in the user's cache
directory (``$XDG_CACHE_HOME/can-drive-hil``, else ``~/.cache/can-drive-hil``) under a key
made of the files' contents and of the source of the code that parses them, so a changed
file or a changed parser is parsed again; a different Python or cantools too (their
versions are in the key). Written atomically (a temporary file renamed over), read only
when whole. Anything that goes wrong with the cache (no home, a read-only or full disk, a
damaged entry) is not an error: the value is parsed as without a cache. A parse that
fails caches nothing. ``CAN_DRIVE_HIL_NO_CACHE=1`` turns it off.

Pure of everything of ours but the standard library; the only I/O is the cache's own.
"""

from __future__ import annotations

import contextlib
import hashlib
import os
import pickle
import sys
import tempfile
from collections.abc import Callable, Iterable
from importlib import util
from pathlib import Path
from typing import TypeVar

V = TypeVar("V")

#: the cache entries' format; part of every key
FORMAT = 1


def cache_dir() -> Path | None:
    """Where entries go; None when switched off or there is no home."""
    if os.environ.get("CAN_DRIVE_HIL_NO_CACHE"):
        return None
    base = os.environ.get("XDG_CACHE_HOME")
    if not base:
        try:
            base = str(Path.home() / ".cache")
        except RuntimeError:
            return None
    return Path(base) / "can-drive-hil"


def _package_version(name: str) -> str:
    """A package's identity without importing it: its module file's size and mtime."""
    try:
        spec = util.find_spec(name)
    except (ImportError, ValueError):
        return "-"
    origin = spec.origin if spec is not None else None
    if not origin:
        return "-"
    try:
        st = os.stat(origin)
    except OSError:
        return "-"
    return f"{origin}:{st.st_size}:{st.st_mtime_ns}"


def key(kind: str, files: Iterable[Path | None], code: Iterable[str | Path],
        packages: Iterable[str] = (), extra: str = "") -> str | None:
    """The key of a value parsed from ``files`` (None: a file absent) by the modules whose
    source files are ``code``, with the versions of ``packages`` and any ``extra`` input;
    None when a file cannot be read."""
    h = hashlib.sha256()
    h.update(f"{kind}\0{FORMAT}\0{sys.version}\0{extra}\0".encode())
    for name in packages:
        h.update(_package_version(name).encode() + b"\0")
    try:
        for path in (*code, *files):
            if path is None:
                h.update(b"\0absent\0")
                continue
            h.update(Path(path).read_bytes())
            h.update(b"\0")
    except OSError:
        return None
    return f"{kind}-{h.hexdigest()[:32]}"


def cached(entry: str | None, build: Callable[[], V]) -> V:
    """The value of cache ``entry`` if it is there, else ``build()``, kept under it."""
    where = cache_dir()
    if entry is None or where is None:
        return build()
    path = where / f"{entry}.pickle"
    with contextlib.suppress(Exception):  # absent, damaged, unreadable: parse again
        return pickle.loads(path.read_bytes())
    value = build()
    tmp = None
    try:
        where.mkdir(parents=True, exist_ok=True)
        fd, tmp = tempfile.mkstemp(dir=where, prefix=f".{entry}.", suffix=".tmp")
        with os.fdopen(fd, "wb") as f:
            f.write(pickle.dumps(value, protocol=pickle.HIGHEST_PROTOCOL))
            f.flush()
            os.fsync(f.fileno())
        os.replace(tmp, path)
        tmp = None
    except OSError:
        pass  # a cache that cannot be written is no cache
    finally:
        if tmp is not None:
            with contextlib.suppress(OSError):
                os.unlink(tmp)
    return value
