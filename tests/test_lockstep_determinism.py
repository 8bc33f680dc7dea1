"""Lockstep is deterministic: every supervision of a lockstep run counts the loop's own time
(SYNCs), so a `sim` run gives the same signals, bit for bit, on an idle host, on a loaded one
and with its threads held up; the wall clock is only the backstop for a peer that stopped
altogether (:data:`dbc.timing.LOCKSTEP_BACKSTOP_S`).

Each case holds up what a loaded host holds up, on purpose and for longer than the wall-clock
supervision of a real-time run allows (the drive's 0.5 s heartbeat watch, the emulator's 1 s
consumer), so that a supervision still on the wall clock fails the case on any host.
"""

from __future__ import annotations

import csv
import json
import multiprocessing
import os
import time
from pathlib import Path

import can
import pytest

from dbc.timing import LOCKSTEP_BACKSTOP_S, TimeBase
from gateway.cli import main
from plant import od as odm
from plant.device import DriveDevice
from plant.nmt import NmtSlave

pytestmark = pytest.mark.timing

#: The columns of signals.csv measured by the wall clock (the cycle's timing on the bus).
WALL_CLOCK_COLUMNS = ("sync_period", "sync_to_tpdo", "reaction")
SIM = ["sim", "--duration", "1.5s"]
#: How long a held-up thread is held: past every wall-clock watch of a real-time run, inside
#: the lockstep backstop.
HOLD = 1.0
assert HOLD < LOCKSTEP_BACKSTOP_S - 0.5


def _sim(out: Path, *args: str) -> tuple[int, dict, dict[str, list[str]]]:
    rc = main([*SIM, "--out", str(out), *args])
    summary = json.loads((out / "summary.json").read_text())
    with (out / "signals.csv").open(newline="") as f:
        rows = list(csv.reader(f))
    columns = {name: [row[j] for row in rows[1:]] for j, name in enumerate(rows[0])}
    for name in WALL_CLOCK_COLUMNS:
        columns.pop(name)
    return rc, summary, columns


@pytest.fixture(scope="module")
def idle(tmp_path_factory):
    """The reference: the same command with nothing held up."""
    rc, s, columns = _sim(tmp_path_factory.mktemp("idle"))
    assert rc == 0 and s["run"]["stop_reason"] == "end of the profile", s["run"]
    assert s["run"]["cycles"] == 1500 and s["run"]["missed_cycles"] == 0
    return columns


def _assert_same(columns: dict[str, list[str]], idle: dict[str, list[str]]) -> None:
    assert columns.keys() == idle.keys()
    for name in idle:
        assert columns[name] == idle[name], f"column {name} differs from the idle run"


def _hold_once_after(cycles: int, seconds: float, real):
    """A method wrapper that sleeps ``seconds`` once, the first time the device has simulated
    ``cycles`` cycles (as a loaded host holds a thread: here with the device's lock held)."""
    held = []

    def wrapper(self, *args, **kwargs):
        if not held and self._cycles_total >= cycles:
            held.append(time.monotonic())
            time.sleep(seconds)
        return real(self, *args, **kwargs)

    wrapper.held = held
    return wrapper


def test_a_drive_held_up_past_every_wall_clock_watch_changes_nothing(idle, tmp_path,
                                                                     monkeypatch):
    """The emulator's timer thread (its heartbeat producer) held for 1 s with the device's
    lock, so it answers nothing meanwhile: the gateway's drive watch (0.5 s of silence in real
    time) and the loop's wait for TPDOs must not count it."""
    hold = _hold_once_after(300, HOLD, DriveDevice._timers)
    monkeypatch.setattr(DriveDevice, "_timers", hold)
    rc, s, columns = _sim(tmp_path)
    assert hold.held, "the drive was never held up"
    assert rc == 0, s["run"]
    assert s["run"]["missed_cycles"] == 0 and s["faults"] == []
    _assert_same(columns, idle)


def test_a_starved_gateway_heartbeat_changes_nothing(idle, tmp_path, monkeypatch):
    """The gateway's wall-clock heartbeat producer sends its first heartbeat and then none
    for 60 s (a thread the host never schedules): the emulator, supervising it in simulated
    time, sees the heartbeat the loop sends every few SYNCs instead, and never trips."""
    real = can.BusABC.send_periodic

    def starved(self, msgs, period, *args, **kwargs):
        return real(self, msgs, 60.0, *args, **kwargs)

    monkeypatch.setattr(can.BusABC, "send_periodic", starved)
    hold = _hold_once_after(300, HOLD, DriveDevice._advance_and_transmit)
    monkeypatch.setattr(DriveDevice, "_advance_and_transmit", hold)  # and the run takes > 1 s
    rc, s, columns = _sim(tmp_path)
    assert hold.held
    assert rc == 0, s["run"]
    assert s["faults"] == []
    _assert_same(columns, idle)


def test_a_lost_gateway_heartbeat_trips_at_the_same_cycle_every_time(tmp_path, monkeypatch):
    """Without any heartbeat after the first (the loop's off too), the emulator trips in
    simulated time: EMCY 0x8130 at the SYNC where 1 s of simulated time has passed since the
    last heartbeat, the same cycle in two runs, whatever the wall clock did meanwhile."""
    real = can.BusABC.send_periodic
    monkeypatch.setattr(can.BusABC, "send_periodic",
                        lambda self, msgs, period, *a, **k: real(self, msgs, 60.0, *a, **k))
    from gateway import loop

    original_init = loop.LoopConfig.__post_init__

    def no_loop_heartbeat(self):
        original_init(self)
        object.__setattr__(self, "heartbeat_every", 0)

    monkeypatch.setattr(loop.LoopConfig, "__post_init__", no_loop_heartbeat)
    stops = []
    for i in range(2):
        rc, s, _ = _sim(tmp_path / f"run{i}")
        assert rc == 1
        assert s["run"]["stop"] == "DRIVE_FAULT" and "0x8130" in s["run"]["stop_reason"]
        stops.append(s["run"]["cycles"])
    assert stops[0] == stops[1]
    # the first heartbeat goes out before the loop; 1 s of simulated time is 1000 cycles
    assert 1000 <= stops[0] <= 1002, stops


def _burn(stop_at: float) -> None:
    while time.monotonic() < stop_at:
        pass


def test_a_loaded_host_gives_the_same_signals(idle, tmp_path):
    """Every core kept busy by two processes each while the run lasts."""
    n = 2 * (os.cpu_count() or 1)
    ctx = multiprocessing.get_context("spawn")
    hogs = [ctx.Process(target=_burn, args=(time.monotonic() + 120,), daemon=True)
            for _ in range(n)]
    for h in hogs:
        h.start()
    try:
        rc, s, columns = _sim(tmp_path)
    finally:
        for h in hogs:
            h.kill()
            h.join(5)
    assert rc == 0, s["run"]
    _assert_same(columns, idle)


# ---------------------------------------------------------------- the emulator's consumer


def _nmt(time_base: TimeBase, timeout_ms: int = 300):
    values = {(0x1017, 0): 0, (0x1016, 1): (0x7F << 16) | timeout_ms,
              (odm.TIME_BASE, 0): int(time_base)}
    lost: list[float] = []
    nmt = NmtSlave(1, values, lambda *_: None, _Wake(), start=lambda: None,
                   pdos_off=lambda: None, reset_node=lambda: None,
                   reset_communication=lambda: None, heartbeat_lost=lambda: lost.append(1))
    nmt.configure_heartbeats()
    return nmt, lost


class _Wake:
    def set(self) -> None:
        pass


def test_sync_time_base_counts_simulated_time_only():
    """SYNC time base: the consumer trips at the first SYNC past 300 ms of simulated time since
    the last heartbeat, however little wall-clock time passed; a wall-clock gap (a stalled
    master process) trips only past the backstop, and SYNCs keep even that off."""
    nmt, lost = _nmt(TimeBase.SYNC)
    nmt.on_heartbeat()
    for _ in range(300):
        nmt.on_sync(1e-3)
    assert not lost
    nmt.on_sync(1e-3)
    assert lost == [1]
    # the wall clock: SYNCs and heartbeats keep the backstop off; silence trips it
    nmt, lost = _nmt(TimeBase.SYNC)
    nmt.on_heartbeat()
    t0 = time.monotonic()
    nmt.timers(t0 + 1.0)  # 1 s without anything: more than 300 ms, less than the backstop
    assert not lost
    nmt.timers(t0 + LOCKSTEP_BACKSTOP_S + 0.1)
    assert lost == [1]


def test_wall_time_base_is_a_real_devices_consumer():
    nmt, lost = _nmt(TimeBase.WALL)
    nmt.on_heartbeat()
    for _ in range(1000):
        nmt.on_sync(1e-3)  # SYNCs are no heartbeat
    t0 = time.monotonic()
    nmt.timers(t0 + 0.25)
    assert not lost
    nmt.timers(t0 + 0.35)
    assert lost == [1]
