"""What was parsed from files, kept while those files do not change.

A campaign runs thousands of points in one process; each would read the same EDS, DBC and
drive profile again (about 30 ms a point, as long as the 150 ms point's simulation). A
:class:`FileMemo` keeps a value built from files with the identity of each file it read
(device, inode, size, modification time in ns): a later :meth:`FileMemo.get` for the same
key returns the kept value while every one of those files is unchanged, and builds it
again when one changed, vanished or appeared. A directory's identity changes when an entry
is added or removed in it (an installed package's metadata directory, for entry points).

Values are shared by every caller: they must be treated as read-only. Bounded (least
recently used dropped first) and safe to use from several threads; a build runs outside
the lock (two threads may both build a value; the last one is kept).
"""

from __future__ import annotations

import os
import threading
from collections import OrderedDict
from collections.abc import Callable, Hashable, Iterable
from pathlib import Path
from typing import Generic, TypeVar

V = TypeVar("V")

#: A file's identity: (device, inode, size, mtime in ns), or None when it does not exist.
FileId = tuple[int, int, int, int] | None


def file_id(path: str | os.PathLike[str]) -> FileId:
    """The identity of ``path`` now (None: it does not exist or cannot be read)."""
    try:
        st = os.stat(path)
    except OSError:
        return None
    return st.st_dev, st.st_ino, st.st_size, st.st_mtime_ns


class FileMemo(Generic[V]):
    """Values built from files, by key, valid while their files are unchanged."""

    def __init__(self, size: int = 32) -> None:
        if size < 1:
            raise ValueError(f"a FileMemo holds at least one value, not {size}")
        self._size = size
        self._lock = threading.Lock()
        self._kept: OrderedDict[Hashable, tuple[V, tuple[tuple[str, FileId], ...]]] = (
            OrderedDict())

    def get(self, key: Hashable,
            build: Callable[[], tuple[V, Iterable[str | os.PathLike[str]]]]) -> V:
        """The value kept for ``key`` if every file it was built from is unchanged; else
        ``build()`` → (value, the files it read), kept and returned. What ``build``
        raises is raised (and nothing kept)."""
        with self._lock:
            kept = self._kept.get(key)
            if kept is not None:
                self._kept.move_to_end(key)
        if kept is not None and all(file_id(p) == fid for p, fid in kept[1]):
            return kept[0]
        value, files = build()
        ids = tuple((str(p), file_id(p)) for p in files)
        with self._lock:
            self._kept[key] = (value, ids)
            self._kept.move_to_end(key)
            while len(self._kept) > self._size:
                self._kept.popitem(last=False)
        return value

    def clear(self) -> None:
        """Forget every value (the next :meth:`get` of each builds it)."""
        with self._lock:
            self._kept.clear()

    def __len__(self) -> int:
        with self._lock:
            return len(self._kept)


def resolved(path: str | os.PathLike[str]) -> str:
    """``path`` as an absolute path (a key that does not depend on the working directory)."""
    return str(Path(path).resolve())
