"""The raw bus log's formats: python-can's writers and readers, by file suffix."""

from __future__ import annotations

#: Raw log formats (python-can writers/readers), by file suffix.
LOG_SUFFIXES: dict[str, str] = {
    ".blf": "Vector BLF, compact binary",
    ".asc": "Vector ASCII",
    ".csv": "python-can CSV",
    ".log": "candump -l, for canplayer",
    ".trc": "PEAK trace",
}
