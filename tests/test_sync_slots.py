"""Real time with a SYNC producer held up past its slots: the SYNCs it could not send on
time are skipped, not sent late in a burst; the SYNC counter skips with them, so the drive
lives through the whole time (the emulator advances by the periods the counter says) and
the controller coasts through each skipped slot. It costs accuracy, never stability."""

from __future__ import annotations

import time

import can
import numpy as np
import pytest

from dbc.cia301 import SYNC_ID, sync_counter, sync_periods
from gateway.loop import catch_up
from gateway.report import read_csv


def test_sync_periods_counts_the_slots_between_two_counters():
    assert sync_periods(1, 2) == 1
    assert sync_periods(1, 4) == 3
    assert sync_periods(240, 1) == 1  # the overflow
    assert sync_periods(239, 2) == 3
    assert sync_periods(3, 5, overflow=5) == 2 and sync_periods(4, 1, overflow=5) == 2
    assert sync_periods(7, 7) == 1  # a repeated counter is not a whole overflow of time


def test_catch_up_skips_the_slots_whose_time_has_passed():
    T = 1e-3
    assert catch_up(5, 0.0, T, 0.0041) == 5  # on time, or less than a period late: this slot
    assert catch_up(5, 0.0, T, 0.0049) == 5
    assert catch_up(5, 0.0, T, 0.0051) == 6  # slot 6 (5 ms) has come: slot 5 skipped
    assert catch_up(5, 0.0, T, 0.0095) == 10  # slots 5–9 skipped


#: when (SYNC counter time, s) the test holds the SYNC thread: at steady speed and load,
#: between the paper profile's events (load steps at 0.5 and 1 s, speed steps at 0.32 and
#: 1.5 s), so what a hold costs is the hold's alone
HOLDS_S = (0.75, 1.3)


#: cycles in the loop's miss-rate window (100 ms) at the held-up test's 5 ms
_WINDOW = 20


@pytest.mark.timing
def test_a_sync_thread_held_up_skips_slots_and_the_run_stays_accurate(emulator, tmp_path,
                                                                     monkeypatch):
    """Real time at 5 ms: the SYNC thread is held 3.4 periods twice (the host stalled it),
    at steady speed and load: before a SYNC (that SYNC leaves late, and the cycle it opens
    has no time to complete: missed) and after one (that cycle's setpoints go out on time,
    and the drive latches them only at the SYNC after the skipped slots, with their frame
    angle two periods old: the loop tells the controller, ``delayed``). Each time the
    thread skips the slots that passed; the drive advances through them (the counter tells
    it), the controller coasts through them, and the run ends at the end of the profile.
    The holds cost accuracy, never stability: the speed error after each is that of the
    setpoints the drive held (and, after the second, of the old frame angle: a braking
    period, about 2 rad/s, and the loop's ringing after it), and the run ends on its
    reference. The model that took the late setpoints as on time ran away there.

    A host this loaded also misses and delays cycles of its own, anywhere in the profile; a
    few of them in a speed step cost rad/s (the drive holds its setpoints while the
    reference accelerates). That is accuracy too, and the profile's end shows it recovered."""
    from gw_support import closed_run, host_losses

    from dbc.timing import Sampling
    from gateway.spec import RunSpec

    T = 5e-3
    emu = emulator()
    bus = can.Bus(interface="virtual", channel=emu.channel, receive_own_messages=True)
    holds = list(HOLDS_S)
    held_at: list[int] = []

    def held_catch_up(k: int, t0: float, period: float, now: float) -> int:
        """The SYNC thread asks for the slot of its next SYNC right after sending one, and
        outside the lock its sends take: here the host holds it."""
        if len(holds) == 2 and k * T >= holds[0]:  # the first: before SYNC k (late)
            held_at.append(k)
        elif len(holds) == 1 and (k - 1) * T >= holds[0]:  # the second: after SYNC k − 1
            held_at.append(k - 1)
        else:
            return catch_up(k, t0, period, now)
        holds.pop(0)
        if holds:  # before SYNC k: held from its time on, it leaves 3.4 periods late
            time.sleep(max(0.0, t0 + (k - 1) * period - time.perf_counter()) + 3.4 * T)
        else:  # after a SYNC: the slots that passed meanwhile are skipped
            time.sleep(3.4 * T)
            now = time.perf_counter()
        return catch_up(k, t0, period, now)

    monkeypatch.setattr("gateway.loop.catch_up", held_catch_up)
    cfg = RunSpec(timing="realtime", sampling=Sampling(T, 1), max_missed=1000,
                  max_miss_rate=1.0)
    s = closed_run(bus, tmp_path, cfg)
    run = s["run"]
    sig = read_csv(tmp_path / "signals.csv")
    k = np.rint(sig["t"] / T).astype(int)
    if run["stop"] != "END_OF_PROFILE":
        # The loop's guards are off here (max_missed 1000, max_miss_rate 1), so that the
        # holds show. A host loaded beyond what a default run accepts — its own missed and
        # withheld cycles beyond 20 % of some 100 ms in the 200 ms before the stop, where
        # the default guards would have stopped the run ("drive lost", "the loop cannot
        # keep its rate") — may then take the loop out of its envelope (a shared host
        # here, half its CPU stolen: 9 cycles in a row lost in the first speed ramp, or
        # the SYNC thread itself held 70 ms): the divergence guard stops it, safely.
        # Anything else, or a divergence where the host kept its rate, is a failure.
        assert run["stop"] == "DIVERGED" and s["shutdown"]["safe"], run["stop_reason"]
        lost = host_losses(k, sig["withheld"], _WINDOW, held_at, since=run["stop_cycle"] - 40)
        assert lost > 0.2 * _WINDOW, (lost, run["stop_reason"])
        return
    assert run["exit_status"] == 0 and s["shutdown"]["safe"]
    assert len(held_at) == 2
    assert run["skipped_syncs"] >= 4, run  # at least two slots at each hold
    assert emu.device.account()["sync_gaps"] >= 2
    # every sample is the one the drive took at that slot's SYNC: its counter echo
    assert all(int(c) == sync_counter(int(j)) for c, j in zip(sig["sync_counter"], k,
                                                               strict=True))
    # a row per cycle with a sample; the slots between rows are the missed ones, skipped
    # slots included, and no row in the slots each hold skipped
    assert np.array_equal(np.diff(k) - 1, np.diff(sig["missed"]).astype(int))
    # (slots the thread skipped after the last row are in skipped_syncs, not in a row)
    assert int(sig["missed"][-1]) + (round(2.5 / T) - int(k[-1])) >= run["skipped_syncs"]
    for h in held_at:
        assert not np.any((k > h) & (k <= h + 2)), (h, k[(k > h - 3) & (k < h + 6)])
    # accuracy, not stability: in the 100 ms after each hold the error of the periods the
    # drive held its setpoints (measured under two busy loops on 2 cores, 28 runs: up to
    # 1.8 rad/s), and, where the cycle of the hold's slot sent its setpoints (always
    # after the second hold, rarely after the first), of the late frame angle with the
    # ringing after it (12 runs: 2.1 to 6.1 rad/s; the model that took the setpoints as
    # on time: 13 rad/s and runaways). Where the loaded host also lost more than two
    # cycles of its own there or in the 0.3 s before (missed, or withheld: late), the
    # drive held its setpoints longer than the hold (under stress-ng on both cores: 7
    # periods in a row, 11 rad/s), or the loop still rang from those losses (a run of
    # them at the load step: ±10 rad/s): what it costs is no longer the hold's alone, and
    # the bound is stability's.
    e = sig["w_m"] - sig["w_ref"]
    for h in held_at:
        sent = bool(np.any((k == h) & (sig["withheld"] == 0)))
        near = (k >= h) & (k <= h + 20)
        # the host's own losses from 0.3 s before the hold (the hold's own: 3): at 5 ms
        # the loop rings after a run of lost cycles for that long (docs/robustness.md §10)
        around = (k >= h - 60) & (k <= h + 20)
        own = (int(sig["missed"][near][-1] - sig["missed"][k < h - 60][-1]) - 3
               + int(np.sum(sig["withheld"][around])))
        bound = (9.0 if sent else 3.0) if own <= 2 else 25.0
        assert np.max(np.abs(e[near])) < bound, (h, sent, own, e[near])
    # and at the profile's end the run is back on its reference (nominal: 1 mrad/s; under
    # load up to 0.05, 0.78 where the host stalled the loop in the profile's last ramp),
    # unless the host lost cycles in its last 0.4 s (at 200 rad/s and 0.5 Wb the torque
    # to recover is limited: 12 rad/s decaying to 8 in the last 0.1 s), or lost more than a
    # default run accepts anywhere (20 % of some 100 ms: the default guards stop such a
    # run): the loop at 5 ms can be left ringing by such losses for the rest of the run
    # (in CI once, 3.4 to 8 rad/s at the end with no loss in its last 0.4 s):
    # stability's bound then
    end = sig["t"] >= sig["t"][-1] - 0.1
    last = sig["t"] >= sig["t"][-1] - 0.4
    late = (int(sig["missed"][-1] - sig["missed"][~last][-1])
            + int(np.sum(sig["withheld"][last])))
    heavy = host_losses(k, sig["withheld"], _WINDOW, held_at) > 0.2 * _WINDOW
    bound = 1.5 if late <= 2 and not heavy else 25.0
    assert float(np.sqrt(np.mean(e[end] ** 2))) < bound, (late, heavy, e[end])


def test_lockstep_takes_the_answers_that_overtake_the_syncs_echo(emulator, tmp_path):
    """python-can's virtual bus queues a frame for each receiver in turn: the drive (created
    first) can answer a SYNC before the gateway's own copy of it is queued. Made to happen
    every cycle here (the gateway's echo of each SYNC is queued only once the drive's three
    TPDOs are in): each answer is held and taken when the echo opens its cycle. Dropped as
    late, every cycle waited for the 2 s backstop and the run stopped, drive lost."""
    from gw_support import closed_run

    from gateway.spec import RunSpec

    emu = emulator()
    bus = can.Bus(interface="virtual", channel=emu.channel, receive_own_messages=True)
    own, overtaken = bus.queue, [0]

    def copy(msg: can.Message, stamp: float, is_rx: bool) -> can.Message:
        return can.Message(arbitration_id=msg.arbitration_id, data=msg.data,
                           is_extended_id=False, timestamp=stamp, is_rx=is_rx,
                           channel=emu.channel)

    def send(msg: can.Message, timeout: float | None = None) -> None:
        stamp = time.time()
        for q in bus.channel:  # what VirtualBus.send does, the sender's copy last
            if q is not own:
                q.put(copy(msg, stamp, is_rx=True))
        if msg.arbitration_id == SYNC_ID:
            # the drive's TPDO1..3 first (the gateway's notifier sends the SYNC, and reads
            # nothing meanwhile, in every cycle but the first: its echoes of the RPDOs wait)
            want, deadline = own.qsize() + 3, time.monotonic() + 1.0
            while own.qsize() < want and time.monotonic() < deadline:
                time.sleep(1e-4)
            overtaken[0] += own.qsize() >= want
        own.put(copy(msg, stamp, is_rx=False))

    bus.send = send
    s = closed_run(bus, tmp_path, RunSpec(duration=0.05))
    run = s["run"]
    assert run["stop"] == "END_OF_PROFILE", run["stop_reason"]
    assert run["cycles"] == 50 and run["missed_cycles"] == 0, run
    held = run["tpdo_before_echo"]
    assert overtaken[0] >= 50 and held >= 150, (overtaken, held)
    assert run["tpdo_events"] == {}
    sig = read_csv(tmp_path / "signals.csv")
    k = np.rint(sig["t"] / 1e-3).astype(int)
    assert all(int(c) == sync_counter(int(j)) for c, j in zip(sig["sync_counter"], k,
                                                               strict=True))


@pytest.mark.timing
def test_setpoints_ready_after_the_threads_next_sync_are_withheld(emulator, tmp_path,
                                                                  monkeypatch):
    """Real time at 10 ms: the SYNC thread is held 6 ms past the time of SYNC 60, which
    leaves late; SYNC 61 then goes out on its schedule, 4 ms after it. Cycle 60's step takes
    6 ms (the controller held up too): its setpoints are ready after SYNC 61 was sent, yet
    before SYNC 60's time + T, by which the loop once judged them in time and sent them —
    the drive then latched them a period late with a frame angle a period old, unknown to
    the model. Now the loop sees the SYNC sent (the thread and the RPDOs share a send lock)
    and withholds them. (A loaded host may miss cycle 60 of its own, or delay SYNC 61: then
    the case did not arise, and the run is made again, up to three times.)"""
    from gw_support import closed_run

    from dbc.timing import Sampling
    from gateway.cycle import ControlCycle
    from gateway.spec import RunSpec

    T, h = 1e-2, 60
    real_step = ControlCycle.step

    def slow_step(self, k, measured, truth=None):  # type: ignore[no-untyped-def]
        if k == h:
            time.sleep(0.6 * T)
        return real_step(self, k, measured, truth)

    monkeypatch.setattr(ControlCycle, "step", slow_step)
    cfg = RunSpec(timing="realtime", sampling=Sampling(T, 1), max_missed=1000,
                  max_miss_rate=1.0, duration=0.8)
    seen = []
    for attempt in range(3):
        held: list[int] = []

        def held_catch_up(k: int, t0: float, period: float, now: float,
                          held: list[int] = held) -> int:
            if k == h and not held:
                held.append(k)
                time.sleep(max(0.0, t0 + (k - 1) * period - time.perf_counter()) + 0.6 * T)
            return catch_up(k, t0, period, now)

        monkeypatch.setattr("gateway.loop.catch_up", held_catch_up)
        out = tmp_path / str(attempt)
        emu = emulator()
        bus = can.Bus(interface="virtual", channel=emu.channel, receive_own_messages=True)
        s = closed_run(bus, out, cfg)
        run = s["run"]
        assert run["stop"] == "END_OF_PROFILE" and s["shutdown"]["safe"], run["stop_reason"]
        assert held == [h]
        sig = read_csv(out / "signals.csv")
        k = np.rint(sig["t"] / T).astype(int)
        rows = np.flatnonzero(k == h)
        # the case: cycle 60 completed, and SYNC 61 came less than a period after SYNC 60
        if len(rows) and rows[0] + 1 < len(k) and k[rows[0] + 1] == h + 1 \
                and sig["sync_period"][rows[0] + 1] < 0.7 * T:
            row = int(rows[0])
            assert sig["withheld"][row] == 1 and run["late_rpdo"] >= 1, \
                sig["withheld"][row - 2:row + 3]
            return
        seen.append(k[(k > h - 3) & (k < h + 3)].tolist())
    pytest.fail(f"the host missed the case three times (slots around {h}: {seen})")
