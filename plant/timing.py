"""The drive's side of a cycle: when received setpoints become active (pure).

The one timing rule of docs/ARCHITECTURE.md ("Sampled timing"), used by the emulated
device on every SYNC and by `simulate`: with RPDO apply ON_RECEIPT the data received
since the last cycle become active first; then the drive advances one period and
samples; with AT_NEXT_SYNC (CiA 301 synchronous RPDOs) the received data become active
after the sample, so they act over the next interval.
"""

from __future__ import annotations

from collections.abc import Callable
from typing import TypeVar

from dbc.modes import RpdoApply

_M = TypeVar("_M")


def sync_cycle(advance: Callable[[], _M], latch: Callable[[], object],
               apply: RpdoApply) -> _M:
    """One cycle at the drive: (latch) → ``advance()`` (one period, returns the sample) →
    (latch), per ``apply``; returns what ``advance`` returned."""
    if apply is RpdoApply.ON_RECEIPT:
        latch()
    sample = advance()
    if apply is RpdoApply.AT_NEXT_SYNC:
        latch()
    return sample
