"""The loop ends after n_cycles even when the last one is missed (real time: a cycle whose
TPDOs are incomplete when the next SYNC comes). Before, it ran one cycle more, so a real-time
run's cycles + missed could be n + 1 (seen in tests/test_two_process.py on a loaded host)."""

from __future__ import annotations

import math
import threading
from types import SimpleNamespace

from gateway.loop import CycleLoop, LoopConfig, LoopStats


def _bare_loop(n_cycles: int, max_missed: int) -> CycleLoop:
    """Just the cycle bookkeeping of a CycleLoop: no bus, no controller work."""
    loop = object.__new__(CycleLoop)
    loop.cfg = LoopConfig(period=1e-3, n_cycles=n_cycles, timing="realtime",
                          max_missed=max_missed)
    loop.ctl = SimpleNamespace(coast=lambda: None)
    loop.stats = LoopStats()
    loop._lock = threading.Lock()
    loop._done = threading.Event()
    loop._frames = {}
    loop._stale = False
    loop._k = loop._k_done = loop._consecutive_missed = 0
    loop._sync_time = loop._sync_prev = math.nan
    return loop


def test_a_missed_last_cycle_ends_the_run():
    loop = _bare_loop(n_cycles=3, max_missed=100)
    for k in range(1, 5):  # SYNC 1..3 without TPDOs, then SYNC 4 closes cycle 3 as missed
        assert not loop._done.is_set(), f"ended before SYNC {k}"
        loop._open_cycle(float(k))
    assert loop._done.is_set()
    assert loop.stats.missed == 3 and loop.stats.cycles == 0
    assert loop.stats.stop_reason == "end of the profile"


def test_missed_cycles_before_the_last_do_not_end_it():
    loop = _bare_loop(n_cycles=5, max_missed=100)
    for k in range(1, 5):  # closes cycles 1..3 as missed
        loop._open_cycle(float(k))
    assert not loop._done.is_set() and loop.stats.missed == 3


def test_the_missed_limit_still_wins():
    loop = _bare_loop(n_cycles=3, max_missed=3)
    for k in range(1, 5):
        loop._open_cycle(float(k))
    assert loop._done.is_set()
    assert loop.stats.stop_reason.startswith("3 consecutive cycles without")
