"""The loop ends after n_cycles even when the last one is missed (real time: a cycle whose
TPDOs are incomplete when the next SYNC comes). Before, it ran one cycle more, so a real-time
run's cycles + missed could be n + 1 (seen in tests/test_two_process.py on a loaded host)."""

from __future__ import annotations

from types import SimpleNamespace

from dbc.timing import Sampling
from gateway.loop import CycleLoop, LoopConfig
from gateway.process_data import ProcessData


def _bare_loop(n_cycles: int, max_missed: int) -> CycleLoop:
    """A CycleLoop on no bus: only the cycle bookkeeping runs (no controller work)."""
    cfg = LoopConfig(n_cycles=n_cycles, sampling=Sampling(1e-3), timing="realtime",
                     max_missed=max_missed, max_miss_rate=1.0)
    return CycleLoop(None, lambda *args: None, ProcessData([]),  # type: ignore[arg-type]
                     SimpleNamespace(coast=lambda: None, signals=()), None, cfg,  # type: ignore[arg-type]
                     own_echo=False)


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
