"""A campaign's progress bar on stderr: points done, the rate and the time left.

On a terminal it redraws one line; elsewhere (a log, a CI job) it prints a line at every
tenth of the work, so a long campaign still shows that it moves.
"""

from __future__ import annotations

import sys
import time
from typing import TextIO


def clock(seconds: float) -> str:
    """``1:02:03``, ``2:05`` or ``7 s``."""
    if seconds != seconds or seconds == float("inf"):
        return "?"
    s = round(seconds)
    h, rem = divmod(s, 3600)
    m, s = divmod(rem, 60)
    if h:
        return f"{h}:{m:02d}:{s:02d}"
    return f"{m}:{s:02d}" if m else f"{s} s"


class CampaignProgress:
    """``total`` points to run now (``before``: already in the table)."""

    WIDTH = 28

    def __init__(self, label: str, total: int, before: int = 0, enabled: bool | None = None,
                 stream: TextIO | None = None) -> None:
        self.label, self.total, self.before = label, total, before
        self.stream = stream or sys.stderr
        self.tty = self.stream.isatty() if enabled is None else enabled
        self.done = 0
        self.failed = 0
        self._t0 = time.perf_counter()
        self._tenth = 0
        self._last_draw = 0.0

    def line(self) -> str:
        """The progress line as it stands."""
        elapsed = time.perf_counter() - self._t0
        frac = self.done / self.total if self.total else 1.0
        filled = round(self.WIDTH * frac)
        rate = self.done / elapsed if elapsed > 0 else 0.0
        left = (self.total - self.done) / rate if rate > 0 else float("nan")
        text = (f"{self.label} [{'#' * filled}{'.' * (self.WIDTH - filled)}] "
                f"{self.done}/{self.total}")
        if self.before:
            text += f" (+{self.before} before)"
        text += f"  {rate:.3g} points/s  "
        text += f"{clock(elapsed)} elapsed" if self.done >= self.total else f"{clock(left)} left"
        if self.failed:
            text += f"  {self.failed} not ok"
        return text

    def advance(self, n: int, failed: int = 0) -> None:
        self.done += n
        self.failed += failed
        if self.tty:
            now = time.perf_counter()
            if now - self._last_draw > 0.1 or self.done >= self.total:
                self._last_draw = now
                self.stream.write("\r" + self.line() + "\033[K")
                self.stream.flush()
        else:
            tenth = (10 * self.done) // max(self.total, 1)
            if tenth > self._tenth:
                self._tenth = tenth
                self.stream.write(self.line() + "\n")
                self.stream.flush()

    def close(self) -> None:
        if self.tty:
            self.stream.write("\r" + self.line() + "\033[K\n")
            self.stream.flush()
