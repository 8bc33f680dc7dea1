"""Faults: every fault injected, the drive ends safe, the cause is named, the exit
status is right and the run directory is complete and readable.

The gateway and the emulated drive run in threads of one process on a virtual bus; an
"intruder" bus on the same channel injects what a faulty bus or node would send.
"""

from __future__ import annotations

import json
import math
import os
import random
import re
import threading
import time
import warnings
from pathlib import Path

import can
import numpy as np
import pytest
from gw_support import Emulator, assert_disabled, gateway_run, run_in_thread, wait_cycles

from dbc.cia301 import Emcy
from dbc.cia402 import Controlword, State
from dbc.modes import DriveMode
from gateway.cycle import CycleRow
from gateway.drive_profile import load_drive_profile
from gateway.guard import Envelope, Plausibility
from gateway.master import DriveMaster
from gateway.process_data import ProcessData
from gateway.report import read_csv
from gateway.spec import RunSpec
from gateway.stop import StopReason, StopSignals
from plant.device import DriveDevice
from plant.params import DriveParams


def _intrude(emu: Emulator, *frames: tuple[int, bytes]) -> None:
    with can.Bus(interface="virtual", channel=emu.channel) as bus:
        for cob_id, data in frames:
            bus.send(can.Message(arbitration_id=cob_id, data=data, is_extended_id=False))


def _summary(out: Path) -> dict:
    return json.loads((out / "summary.json").read_text())


def _run_until(emu: Emulator, out: Path, cycles: int, cfg: RunSpec | None = None):
    """A gateway run in a thread, started and past ``cycles`` cycles of the drive."""
    th, result = run_in_thread(emu, out, cfg or RunSpec(duration=30.0), StopSignals())
    wait_cycles(emu.device, cycles)
    return th, result


def _finished(th, result) -> dict:
    th.join(15)
    assert not th.is_alive(), "the run did not stop"
    assert "error" not in result, result.get("error")
    return result["summary"]


def _assert_complete(out: Path, s: dict) -> None:
    """The run directory is complete and readable."""
    assert _summary(out)["run"]["status"] == "finished"
    assert s["run"]["exit_status"] == 1
    sig = read_csv(out / "signals.csv")
    assert len(sig["t"]) == s["run"]["cycles"]
    frames = list(can.LogReader(str(out / "bus.blf")))
    assert len(frames) == s["run"]["bus_frames_logged"] > 0


# ------------------------------------------------------------------------ shutdown

NMT_STATES = ("OPERATIONAL", "PRE-OPERATIONAL", "STOPPED")
DRIVE_STATES = ("OPERATION_ENABLED", "SWITCHED_ON", "QUICK_STOP_ACTIVE", "FAULT",
                "SWITCH_ON_DISABLED")


@pytest.mark.parametrize("nmt", NMT_STATES)
@pytest.mark.parametrize("drive_state", DRIVE_STATES)
def test_shutdown_reaches_a_safe_drive_from_every_state(emulator, nmt, drive_state):
    emu = emulator()
    bus = can.Bus(interface="virtual", channel=emu.channel, receive_own_messages=True)
    master = DriveMaster(bus, load_drive_profile(None), 1)
    try:
        master.connect()
        master.configure(1e-3, ProcessData([]), False, DriveMode.IDEAL.mode_of_operation, {})
        master.start()
        master.enable()
        dev = emu.device
        assert dev.cia402_state is State.OPERATION_ENABLED and dev.drive.enabled
        if drive_state == "SWITCHED_ON":
            master.sdo_write(0x6040, 0, Controlword.SWITCH_ON)
        elif drive_state == "QUICK_STOP_ACTIVE":
            master.sdo_write(0x6040, 0, Controlword.QUICK_STOP)
        elif drive_state == "SWITCH_ON_DISABLED":
            master.sdo_write(0x6040, 0, Controlword.DISABLE_VOLTAGE)
        elif drive_state == "FAULT":
            _intrude(emu, (0x201, b"\x00"))  # an RPDO of wrong length: EMCY 0x8210, Fault
        deadline = time.monotonic() + 2
        while dev.cia402_state.name != drive_state and time.monotonic() < deadline:
            time.sleep(0.01)
        assert dev.cia402_state.name == drive_state
        command = {"OPERATIONAL": 0x01, "PRE-OPERATIONAL": 0x80, "STOPPED": 0x02}[nmt]
        _intrude(emu, (0x000, bytes([command, 1])))
        deadline = time.monotonic() + 2
        while dev.nmt_state != nmt and time.monotonic() < deadline:
            time.sleep(0.01)
        assert dev.nmt_state == nmt
        report = master.shutdown()
    finally:
        master.shutdown()
        bus.shutdown()
    assert report is not None and report.safe, report
    assert_disabled(emu)
    # supervision is switched off only with the power stage confirmed off
    assert report.supervision_off == ("0x1016:1 = 0" in report.steps)
    if nmt == "STOPPED":  # no SDO in STOPPED: pre-operational first, then confirmed
        assert "NMT pre-operational" in report.steps


def test_silent_drive_is_not_called_safe_and_keeps_its_supervision(emulator):
    emu = emulator()
    bus = can.Bus(interface="virtual", channel=emu.channel, receive_own_messages=True)
    master = DriveMaster(bus, load_drive_profile(None), 1)
    try:
        master.connect()
        master.configure(1e-3, ProcessData([]), False, -1, {})
        master.start()
        master.enable()
        emu.device.stop()  # gone: no SDO, no boot-up after a reset
        report = master.shutdown()
    finally:
        bus.shutdown()
    assert report is not None and not report.safe and not report.supervision_off
    assert "NMT reset node" in report.steps and "no boot-up after the reset" in report.steps


# ------------------------------------------------------------------ faults in a run


@pytest.mark.parametrize("name, cob_id, data", [
    ("TPDO1", 0x181, b"\x37\x02\x00"),
    ("TPDO2", 0x281, b"\x00\x00\x00\x00"),
    ("TPDO3", 0x381, b"\x01"),
])
def test_wrong_length_tpdo_stops_the_run_within_a_cycle(emulator, tmp_path, name, cob_id,
                                                        data):
    emu = emulator()
    th, result = _run_until(emu, tmp_path, 200)
    at = emu.device.account()["cycles"]
    _intrude(emu, (cob_id, data))
    sent = emu.device.account()["cycles"]
    s = _finished(th, result)
    assert s["run"]["stop"] == "BAD_FRAME" and name in s["run"]["stop_reason"]
    assert at - 1 <= s["run"]["cycles"] <= sent + 1  # stopped as the frame came in
    assert any(f["cob_id"] == f"0x{cob_id:03X}" and f["data"] == data.hex()
               for f in s["run"]["frames_before_stop"])
    assert s["run"]["last_good_cycle"] >= at - 1
    _assert_complete(tmp_path, s)
    assert s["shutdown"]["safe"], s["shutdown"]
    assert_disabled(emu)


@pytest.mark.parametrize("frames, stop, words", [
    ([(0x701, b"\x00")], "DRIVE_STATE", "rebooted"),  # a boot-up of the drive
    ([(0x000, b"\x81\x01")], "DRIVE_STATE", "rebooted"),  # NMT reset node of the drive
    ([(0x000, b"\x80\x01")], "DRIVE_STATE", "PRE-OPERATIONAL"),  # another master's NMT
    ([(0x080, b"")], "FOREIGN_SYNC", "another SYNC producer"),
    ([(0x080, b"\x07")], "FOREIGN_SYNC", "another SYNC producer"),
    ([(0x081, bytes([0x10, 0x23, 0x03, 0, 0, 0, 0, 0]))], "DRIVE_FAULT", "0x2310"),
])
def test_bus_fault_stops_the_run_with_its_name(emulator, tmp_path, frames, stop, words):
    emu = emulator()
    th, result = _run_until(emu, tmp_path, 200)
    at = emu.device.account()["cycles"]
    _intrude(emu, *frames)
    s = _finished(th, result)
    assert s["run"]["cycles"] >= at - 1
    assert s["run"]["stop"] == stop and words in s["run"]["stop_reason"], s["run"]
    assert s["run"]["cycles"] <= at + 60  # heartbeat-borne causes: within a heartbeat (50 ms)
    _assert_complete(tmp_path, s)
    assert s["shutdown"]["safe"]
    assert_disabled(emu)


def test_emcy_stops_a_lockstep_run_within_one_cycle(emulator, tmp_path):
    emu = emulator()
    th, result = _run_until(emu, tmp_path, 300, RunSpec(duration=30.0))
    _intrude(emu, (0x081, bytes([0x10, 0x23, 0x03, 0, 0, 0, 0, 0])))
    at = emu.device.account()["cycles"]
    s = _finished(th, result)
    assert s["run"]["stop"] == "DRIVE_FAULT"
    assert s["run"]["cycles"] <= at + 2


def test_emcy_near_the_end_is_not_exit_0(emulator, tmp_path):
    """An EMCY in the last cycle (or after it, before the shutdown) fails the run."""
    from gateway.loop import CycleLoop

    emu = emulator()
    real = CycleLoop._cycle

    def last_cycle_with_emcy(self, t_arrival):
        if self._k == self.cfg.n_cycles:
            _intrude(emu, (0x081, bytes([0x10, 0x23, 0x03, 0, 0, 0, 0, 0])))
        real(self, t_arrival)

    CycleLoop._cycle = last_cycle_with_emcy
    try:
        rc = gateway_run(emu, tmp_path, "--duration", "0.3s")
    finally:
        CycleLoop._cycle = real
    s = _summary(tmp_path)
    assert rc == 1 and s["run"]["stop"] == "DRIVE_FAULT" and s["run"]["exit_status"] == 1
    assert "0x2310" in s["run"]["stop_reason"]


def test_implausible_measurement_stops_the_run_before_any_setpoint(tmp_path):
    """A DC link of 1000 V reported by a drive whose range is 400..700 V."""
    emu = Emulator()
    emu.device.stop()
    emu.device = DriveDevice(emu.bus, 1, drive_params=DriveParams(mode="ideal", u_dc=1000.0))
    emu.device.start()
    try:
        assert gateway_run(emu, tmp_path, "--duration", "0.2s") == 1
        s = _summary(tmp_path)
        assert s["run"]["stop"] == "IMPLAUSIBLE" and "DC link u_dc = 1000.0 V outside the " \
            "drive's range 400..700 V" in s["run"]["stop_reason"]
        assert s["run"]["cycles"] == 0
        assert_disabled(emu)
    finally:
        emu.close()


def test_plausibility_and_envelope_checks():
    p = Plausibility(i_peak=25.0, u_dc_min=400.0, u_dc_max=700.0)
    ok = {"i_sa": 3.0, "i_sb": -4.0, "u_sa": 1.0, "u_sb": 2.0, "u_dc": 560.0}
    assert p.check(ok) is None
    assert "not a number" in p.check({**ok, "i_sa": math.nan})
    assert "peak current" in p.check({**ok, "i_sa": 32.767, "i_sb": 0.0})
    assert "DC link" in p.check({**ok, "u_dc": 1310.7})
    assert "DC link" in p.check({**ok, "u_dc": 0.0})
    env = Envelope.from_demand(w_peak=200.0, i_peak=8.2, psi_peak=1.16, u_peak=209.0,
                               i_limit=20.0)
    row = CycleRow(*([0.0] * len(CycleRow._fields)))
    good = row._replace(w_ref=200.0, w_hat=199.0, w_m=199.5, i_sa=8.0, u_sa=240.0,
                        psi_r_mod_hat=1.16)
    assert env.check(good) is None
    assert env.check(good._replace(w_hat=-250.0)).startswith("speed")  # the case
    assert "flux" in env.check(good._replace(psi_r_mod_hat=3.5))
    assert "voltage" in env.check(good._replace(u_sa=927.0))
    assert "estimation error" in env.check(good._replace(w_m=150.0))
    assert "current" in env.check(good._replace(i_sa=30.0))
    assert env.check(good._replace(w_m=math.nan)) is None  # no truth from a real drive
    assert env.check(good._replace(w_hat=math.nan)) is not None


def test_divergence_stops_the_run(emulator, tmp_path):
    """A controller that believes R_s three times too large integrates a wrong flux: the
    open-loop estimate leaves the envelope (since session 8 the orientation check sees it
    first: the estimate turns away from the frame during the magnetisation) and the run
    stops, exit 1."""
    emu = emulator()
    motor = tmp_path / "wrong-motor.toml"
    motor.write_text("R_s = 15.9\n")
    out = tmp_path / "run"  # a run directory must be new (or --force)
    rc = gateway_run(emu, out, "--motor", str(motor))
    s = _summary(out)
    assert rc == 1 and s["run"]["stop"] == "DIVERGED", s["run"]
    reason = s["run"]["stop_reason"]
    assert "field orientation lost" in reason or "beyond" in reason, reason
    assert "no new setpoints" not in reason, reason  # no cycle was lost
    assert_disabled(emu)


def test_a_divergence_after_lost_cycles_names_them():
    """Half the drive's TPDO1 lost (the loop's own miss guards off, as a user may set them):
    the controller's model follows the held setpoints, but the run leaves its envelope
    (0.44 s), and the divergence stop says that half the cycles before it gave the drive no
    new setpoints — which a divergence without losses does not (test above)."""
    from sim_support import sim_config

    from dbc.motor import MotorParams
    from gateway.guard import DivergenceWatch, profile_envelope
    from gateway.reference import paper_profile
    from gateway.simulate import run
    from plant.scenario import parse_scenario

    prof = paper_profile()
    lossy = parse_scenario('[[bus.fault]]\nkind = "drop"\nmessage = "TPDO1"\ncycle = 1\n'
                           'probability = 0.5\nseed = 1\n', "lossy")
    rec = run(prof, MotorParams(), sim_config(plant=lossy, max_missed=1000, max_miss_rate=1.0),
              watch=DivergenceWatch(profile_envelope(prof, MotorParams(), 20.0)))
    stats = rec.link.stats
    assert stats.stop is StopReason.DIVERGED, stats.stop_reason
    m = re.search(r"; (\d+) of the 100 cycles before it \(100 ms\) gave the drive no new "
                  r"setpoints \(missed: (\d+) in the run", stats.stop_reason)
    assert m, stats.stop_reason
    assert 35 <= int(m[1]) <= 65 and int(m[2]) == stats.missed, stats.stop_reason
    assert "signals.csv's columns missed and withheld" in stats.stop_reason

def test_missed_cycle_rate_stops_the_run(emulator, tmp_path):
    """Isolated misses (never two in a row; the limit in a row is out of reach) but more
    than 20 % of the cycles of 100 ms."""
    from gateway.loop import CycleLoop

    emu = emulator()
    dropped = iter(range(10**9))
    real = CycleLoop._on_tpdo

    def flaky(self, can_id, data, timestamp):
        if can_id == 0x181 and next(dropped) % 3 == 0:
            return  # every third TPDO1 lost
        real(self, can_id, data, timestamp)

    CycleLoop._on_tpdo = flaky
    try:
        th, result = run_in_thread(emu, tmp_path, RunSpec(timing="realtime",
                                                            max_missed=1000), StopSignals())
        s = _finished(th, result)
    finally:
        CycleLoop._on_tpdo = real
    assert s["run"]["stop"] == "DRIVE_LOST" and "of the last 100 cycles" in \
        s["run"]["stop_reason"]


# ------------------------------------------------------------------- nothing lost


def test_full_disk_for_the_bus_log_and_the_signals_is_reported(emulator, tmp_path):
    if not os.path.exists("/dev/full"):
        pytest.fail("/dev/full is needed to emulate a full disk")
    emu = emulator()
    (tmp_path / "bus.asc").symlink_to("/dev/full")
    (tmp_path / "signals.csv").symlink_to("/dev/full")
    rc = gateway_run(emu, tmp_path, "--duration", "0.3s", "--log", "bus.asc", "--force")
    s = _summary(tmp_path)
    assert rc == 1 and s["run"]["exit_status"] == 1
    errors = " ".join(s["write_errors"])
    assert "bus.asc" in errors and "signals.csv" in errors and "No space" in errors
    assert s["run"]["stop"] == "END_OF_PROFILE"  # the run itself went well, and says so
    assert_disabled(emu)


# ------------------------------------------------------------------------ fuzzing


def test_gateway_survives_10000_random_frames_during_a_run(emulator, tmp_path):
    """Random frames on every COB-ID during a run: it ends with a named reason, safe."""
    emu = emulator()
    th, result = _run_until(emu, tmp_path, 100)
    rng = random.Random(11)
    with can.Bus(interface="virtual", channel=emu.channel) as bus:
        for _ in range(10_000):
            cob = rng.choice([rng.randrange(0x800), 0x080, 0x181, 0x281, 0x381, 0x701, 0x081])
            if cob == 0x000 or 0x600 <= cob < 0x680:
                cob = 0x7FF  # no NMT commands or SDO requests at the drive itself
            data = bytes(rng.randrange(256) for _ in range(rng.randrange(9)))
            bus.send(can.Message(arbitration_id=cob, data=data, is_extended_id=False))
    s = _finished(th, result)
    assert StopReason[s["run"]["stop"]] not in (StopReason.END_OF_PROFILE,
                                                StopReason.CONTROL_ERROR)
    assert s["run"]["exit_status"] == 1 and s["shutdown"]["safe"], s["shutdown"]
    _assert_complete(tmp_path, s)
    assert_disabled(emu)


def test_emcy_texts_cover_the_codes():
    assert Emcy.describe(0x2310) == "over-current"
    assert Emcy.describe(0xFF01) == "drive-specific error"


# --------------------------------------------------------------- damaged logs


@pytest.mark.parametrize("suffix", [".asc", ".csv", ".log", ".trc"])
def test_damaged_text_logs_are_read_around_the_damage(tmp_path, suffix):
    from gateway.buslog import read_log

    path = tmp_path / f"run{suffix}"
    writer = can.Logger(str(path))
    for i in range(20):
        writer.on_message_received(can.Message(arbitration_id=0x181, data=bytes([i, 2, 3]),
                                               timestamp=1000.0 + i * 1e-3,
                                               is_extended_id=False))
    writer.stop()
    lines = path.read_text().splitlines(keepends=True)
    data_lines = [i for i, line in enumerate(lines) if "181" in line.upper()
                  and not line.startswith(";")]
    lines[data_lines[5]] = "this line is garbage #!\n"
    path.write_text("".join(lines))
    frames = read_log(path)
    assert frames.damaged == 1
    assert [m.data[0] for m in frames] == [i for i in range(20) if i != 5]


def test_trc_cut_in_its_header_gives_no_traceback(tmp_path):
    from gateway.buslog import read_log

    path = tmp_path / "cut.trc"
    writer = can.Logger(str(path))
    writer.on_message_received(can.Message(arbitration_id=0x181, data=b"\x01"))
    writer.stop()
    path.write_text(path.read_text()[:40])
    frames = read_log(path)
    assert list(frames) == [] and frames.damaged >= 0


def test_blf_cut_short_is_read_up_to_the_cut(tmp_path):
    from gateway.buslog import read_log

    path = tmp_path / "cut.blf"
    writer = can.Logger(str(path))
    for i in range(3000):
        writer.on_message_received(can.Message(arbitration_id=0x181, data=bytes([i % 256]),
                                               timestamp=1000.0 + i * 1e-3))
        if i == 1999:
            writer._flush()  # what the run's recorder does every second
    writer.stop()
    data = path.read_bytes()
    path.write_bytes(data[: len(data) - 200])  # the last container cut (a crash)
    frames = read_log(path)  # python-can stops at the cut container without an error
    assert 2000 <= len(frames) < 3000
    assert [m.data[0] for m in frames] == [i % 256 for i in range(len(frames))]


def test_a_second_run_after_a_fault_starts_from_a_motor_at_rest(emulator, tmp_path):
    """The emulated model advances only on SYNC; between runs the real motor's flux decays.
    After a fault mid-run, a new run on the same drive must not inherit a magnetised model."""
    emu = emulator()
    (tmp_path / "r1").mkdir()
    th, result = _run_until(emu, tmp_path / "r1", 300)
    _intrude(emu, (0x201, b"\x00"))  # an RPDO of wrong length: the drive faults (0x8210)
    # the gateway sees a frame on its RPDO1 COB-ID it did not send, and stops by that
    assert _finished(th, result)["run"]["stop"] == "FOREIGN_WRITER"
    time.sleep(0.3)  # about three rotor time constants
    assert gateway_run(emu, tmp_path / "r2", "--duration", "0.5s") == 0
    s = _summary(tmp_path / "r2")
    assert s["run"]["stop"] == "END_OF_PROFILE" and s["speed_error"]["max"] < 0.5


def test_between_runs_the_idle_motor_comes_to_rest_in_real_time(emulator, tmp_path):
    """The quick profile ends at 100 rad/s. Between runs the emulated motor lives in real
    time: its flux decays and the test bench brakes it to rest (500 rad/s²), so a second
    run a moment later starts from rest, as on a real bench."""
    emu = emulator()
    assert gateway_run(emu, tmp_path / "r1", "--reference", "profiles/quick.toml") == 0
    deadline = time.monotonic() + 30.0  # about 0.2 s on an idle host
    while emu.device._drive.state.w_m != 0.0 and time.monotonic() < deadline:
        time.sleep(0.02)
    assert emu.device._drive.state.w_m == 0.0
    assert gateway_run(emu, tmp_path / "r2", "--reference", "profiles/quick.toml") == 0
    assert _summary(tmp_path / "r2")["run"]["stop"] == "END_OF_PROFILE"


def test_a_run_on_a_motor_still_turning_says_so(emulator, tmp_path, capsys):
    """On a bench that does not brake an idle motor (``idle_brake`` 0) the model keeps the
    quick profile's final 100 rad/s (no friction): a new run from rest diverges at once,
    and its reason says the motor was turning."""
    emu = emulator()
    emu.device.idle_brake = 0.0
    assert gateway_run(emu, tmp_path / "r1", "--reference", "profiles/quick.toml") == 0
    capsys.readouterr()
    assert gateway_run(emu, tmp_path / "r2", "--reference", "profiles/quick.toml") == 1
    reason = _summary(tmp_path / "r2")["run"]["stop_reason"]
    m = re.search(r"the motor was already turning at ([\d.]+) rad/s", reason)
    assert m and abs(float(m[1]) - 100.0) < 1.0, reason
    assert "already turning" in capsys.readouterr().err
    assert_disabled(emu)


def test_a_drive_slow_to_act_on_nmt_start_is_not_a_fault(emulator, tmp_path, monkeypatch):
    """The NMT watch is armed only once the drive's heartbeat reports OPERATIONAL. Here the
    drive acts on the start command 150 ms late (its first one is dropped and the command
    repeated on the bus), so its heartbeat reports PRE-OPERATIONAL two or three times after
    the command went out, as a drive in a slower process did in CI over vcan. That is not a
    drive leaving OPERATIONAL: the run goes to its end."""
    from plant.nmt import NmtSlave

    real = NmtSlave.on_command
    dropped: list[float] = []

    def late_start(self, data: bytes) -> None:
        if len(data) == 2 and data[0] == 0x01 and not dropped:
            dropped.append(time.time())  # the clock of python-can's timestamps
            threading.Timer(0.15, _intrude, (emu, (0x000, bytes(data)))).start()
            return
        real(self, data)

    monkeypatch.setattr(NmtSlave, "on_command", late_start)
    emu = emulator()
    with can.Bus(interface="virtual", channel=emu.channel) as bus:
        rc = gateway_run(emu, tmp_path / "run", "--duration", "0.1s")
        heartbeats = []
        while (msg := bus.recv(0)) is not None:
            if msg.arbitration_id == 0x701 and msg.timestamp > dropped[0]:
                heartbeats.append(msg.data[0])
    s = _summary(tmp_path / "run")
    assert rc == 0, s["run"]["stop_reason"]
    assert s["run"]["stop"] == "END_OF_PROFILE" and s["run"]["cycles"] == 100
    assert heartbeats[:2] == [0x7F, 0x7F] and 0x05 in heartbeats, heartbeats
    assert_disabled(emu)


def test_a_drive_that_does_not_enter_operational_is_named(emulator, tmp_path, capsys,
                                                          monkeypatch):
    """A drive that ignores NMT start: the gateway says so within the heartbeat watch time,
    exits non-zero and leaves the drive disabled."""
    from plant.nmt import NmtSlave

    real = NmtSlave.on_command

    def deaf_to_start(self, data: bytes) -> None:
        if len(data) == 2 and data[0] == 0x01:
            return
        real(self, data)

    monkeypatch.setattr(NmtSlave, "on_command", deaf_to_start)
    emu = emulator()
    t0 = time.monotonic()
    rc = gateway_run(emu, tmp_path / "run", "--duration", "0.1s")
    err = capsys.readouterr().err
    assert rc != 0
    assert "did not report OPERATIONAL" in err and "PRE-OPERATIONAL" in err, err
    assert "Traceback" not in err
    assert time.monotonic() - t0 < 10
    assert emu.device.account()["cycles"] == 0
    assert_disabled(emu)


def test_tpdos_of_a_missed_cycle_arriving_late_are_not_mixed_into_the_next(emulator,
                                                                           tmp_path):
    """The drive stalls after TPDO1 of cycle 127 (10 ms, paper scenario) and sends TPDO2 and
    TPDO3 of that cycle only after SYNC 128, just before cycle 128's: the gateway misses 127
    and does not take those two late frames (a voltage of the interval before) for cycle
    128's, whose TPDO1 echo comes after them. As on vcan in CI, where the mix threw the
    flux estimate to 2.3 Wb and the divergence guard stopped the run."""
    emu = emulator()
    samples: dict[int, complex] = {}
    emu.device.on_sample = lambda m, meas: samples.__setitem__(m, meas.u_s_ab)
    real_send = emu.bus.send
    held: list[can.Message] = []
    n_tpdo1 = [0]

    def stalling_send(msg: can.Message, timeout: float | None = None) -> None:
        if msg.arbitration_id == 0x181:
            n_tpdo1[0] += 1
            while held:  # the stall is over: the rest of cycle 127 goes out first
                real_send(held.pop(0))
        elif msg.arbitration_id in (0x281, 0x381) and n_tpdo1[0] == 127:
            held.append(msg)
            return
        real_send(msg, timeout)

    emu.bus.send = stalling_send
    rc = gateway_run(emu, tmp_path / "run", "--period", "10ms", "--duration", "1.5s")
    s = _summary(tmp_path / "run")
    assert rc == 0, s["run"]["stop_reason"]
    assert s["run"]["missed_cycles"] == 1 and s["run"]["cycles"] == 149
    sig = read_csv(tmp_path / "run" / "signals.csv")
    k = np.rint(sig["t"] / 0.01).astype(int)
    assert 127 not in k and 128 in k
    # every recorded voltage is the one the drive sampled at that SYNC (to 1 LSB, 20 mV)
    u = sig["u_sa"] + 1j * sig["u_sb"]
    u_drive = np.array([samples[int(j)] for j in k])
    assert np.max(np.abs(u - u_drive)) < 0.05, k[np.argmax(np.abs(u - u_drive))]
    psi_hat = sig["psi_r_mod_hat"][k > 120]
    assert np.max(np.abs(psi_hat - 1.16)) < 0.05


def test_rpdos_that_reach_the_bus_after_the_next_sync_are_counted_and_modelled(emulator,
                                                                               tmp_path):
    """Real time, 2 ms: the host holds the gateway between its two RPDOs of one cycle, so
    RPDO2 reaches the bus after the next SYNC (RPDO1 before it). The bus's own echo shows
    it: counted (``run.rpdo_after_sync``) and the controller told the drive held its
    setpoints (a withhold after the step; a wrong call would stop the run with
    CONTROL_ERROR).

    The loop's miss guards are off (so that a loaded host's own misses do not end the run
    before the held frame); a host that then lost more than a default run accepts (20 % of
    some 100 ms in the 200 ms before the stop: once here, a shared host with half its CPU
    stolen) may take the loop at 2 ms out of its envelope and the divergence guard stop it,
    safely; where that was before the held frame (the run's start lost), a fresh run, three
    in all. Anything else is a failure."""
    from gw_support import closed_run, host_losses

    from dbc.timing import Sampling

    for attempt in range(1, 4):
        emu = emulator()
        bus = can.Bus(interface="virtual", channel=emu.channel, receive_own_messages=True)
        real_send = bus.send
        held: list[can.Message] = []
        n_rpdo2 = [0]

        def send(msg: can.Message, timeout: float | None = None, real_send=real_send,
                 held=held, n_rpdo2=n_rpdo2) -> None:
            if msg.arbitration_id == 0x301:
                n_rpdo2[0] += 1
                if n_rpdo2[0] == 150:
                    held.append(msg)  # until the next SYNC has gone out
                    return
            real_send(msg, timeout)
            if msg.arbitration_id == 0x080 and held:
                real_send(held.pop())

        bus.send = send
        cfg = RunSpec(timing="realtime", sampling=Sampling(2e-3, 1), duration=1.2,
                      max_missed=1000, max_miss_rate=1.0)
        s = closed_run(bus, tmp_path, cfg)
        run = s["run"]
        sig = read_csv(tmp_path / "signals.csv")
        withheld = sig["withheld"]
        if run["stop"] != "END_OF_PROFILE":
            window = 50  # cycles in the loop's miss-rate window (100 ms) at 2 ms
            k = np.rint(sig["t"] / 2e-3).astype(int)
            assert run["stop"] == "DIVERGED" and s["shutdown"]["safe"], run["stop_reason"]
            lost = host_losses(k, withheld, window, since=run["stop_cycle"] - 100)
            assert lost > 0.2 * window, (lost, run["stop_reason"])
            assert_disabled(emu)
        if n_rpdo2[0] > 150:
            break
        # stopped so before the held frame (the host lost the start of the run: a stall of
        # a hundred milliseconds, seen in CI and here): a fresh run on a fresh drive
        warnings.warn(f"attempt {attempt}: the host lost the real-time run before the "
                      f"held frame: {run['stop_reason']}", stacklevel=1)
    # the 150th RPDO2 (a cycle of 600: a loaded host that misses half of them still sends
    # it; the 300th was once not reached, 174 sent)
    assert not held and n_rpdo2[0] > 150, (n_rpdo2[0], run["missed_cycles"])
    assert run["rpdo_after_sync"] >= 1
    # the rows say which cycles' setpoints were withheld (late by the clock), as many as counted
    assert set(np.unique(withheld)) <= {0.0, 1.0}
    assert int(withheld.sum()) == run["late_rpdo"]
    assert_disabled(emu)


def _row(**kw):
    base = {f: 0.0 for f in CycleRow._fields}
    base.update(w_m=math.nan, psi_r_mod=math.nan, T_e=math.nan, psi_ref=1.16,
                psi_rd_hat=1.16, psi_r_mod_hat=1.16)
    base.update(kw)
    return CycleRow(**base)


def test_orientation_guard_names_a_turned_or_collapsed_flux_estimate():
    env = Envelope.from_demand(w_peak=200.0, i_peak=8.2, psi_peak=1.16, u_peak=209.0)
    assert env.check(_row()) is None
    # 60° off, a large but recoverable error of the drift-free estimator: inside
    c, s = math.cos(math.radians(60.0)), math.sin(math.radians(60.0))
    assert env.check(_row(psi_rd_hat=1.16 * c, psi_rq_hat=1.16 * s)) is None
    why = env.check(_row(psi_rd_hat=-0.2, psi_rq_hat=1.0, psi_r_mod_hat=math.hypot(0.2, 1.0),
                         T_L=0.5))
    assert why.startswith("field orientation lost: the flux estimate is 1.02 Wb at +101° "), why
    assert "load torque the laws are not told (the profile's T_L is 0.5 N·m)" in why
    why = env.check(_row(psi_rd_hat=0.2, psi_r_mod_hat=0.2))  # collapsed, on the d axis
    assert why.startswith("field orientation lost: the flux estimate is 0.2 Wb at +0° "), why
    # early in the magnetisation (ψ* below a quarter of the peak) the angle means nothing
    assert env.check(_row(psi_ref=0.2, psi_rd_hat=-0.001, psi_rq_hat=0.001,
                          psi_r_mod_hat=0.0014)) is None


def test_a_flux_estimate_that_stays_low_stops_the_run_after_half_a_second():
    """The slow loss (an untold load in field weakening): the estimate stays on the d axis
    but fades. 0.4·ψ* is inside the per-cycle bounds; held for 0.5 s it is a stop, and a
    deficit that recovers in between starts the clock again."""
    from gateway.guard import DivergenceWatch

    env = Envelope.from_demand(w_peak=200.0, i_peak=8.2, psi_peak=1.16, u_peak=209.0)
    low = _row(psi_ref=0.5, psi_rd_hat=0.2, psi_r_mod_hat=0.2, T_L=0.5)
    assert env.check(low) is None and env.flux_deficit(low)
    watch = DivergenceWatch(env)
    rows = [low._replace(t=0.01 * k) for k in range(40)]  # 0 … 0.39 s low
    rows.append(_row(psi_ref=0.5, psi_rd_hat=0.5, psi_r_mod_hat=0.5, t=0.40))  # recovered
    rows += [low._replace(t=0.41 + 0.01 * k) for k in range(60)]  # low again from 0.41 s
    stop = next(k for k, r in enumerate(rows) if watch.check(r, k + 1))
    assert rows[stop].t == pytest.approx(0.91), stop
    assert watch.reason.startswith("cycle 92 (t = 0.9100 s): flux estimate below 0.5·ψ* "
                                   "since t = 0.4100 s (|ψ̂_r| = 0.2 Wb, ψ* = 0.5 Wb)"), \
        watch.reason
    assert "the profile's T_L is 0.5 N·m" in watch.reason


def test_a_motor_lost_to_an_untold_load_is_stopped_without_a_speed_sensor():
    """The shipped untold-load scenario: the rated torque on the shaft from 1.2 s that the
    controller is not told. The speed estimate keeps reading about ω* while the motor stalls
    and turns backwards; without the emulator's truth (a real drive) only the orientation
    check can see it, and it does — after the true speed error passes 20 rad/s, while
    |ω̂ − ω*| is still inside its bound. 1 N·m untold is lost more slowly, in field
    weakening, and is stopped by the sustained flux deficit."""
    from sim_support import sim_config

    from dbc.motor import MotorParams
    from gateway.guard import DivergenceWatch, profile_envelope
    from gateway.reference import paper_profile
    from gateway.simulate import run
    from plant.scenario import parse_scenario, resolve_scenario

    prof = paper_profile()
    env = profile_envelope(prof, MotorParams(), 20.0)
    shipped = resolve_scenario("untold-load")
    text = (Path(__file__).parents[1] / "plant" / "scenarios" / "untold-load.toml").read_text()
    assert "value = 5.8" in text
    one = parse_scenario(text.replace("value = 5.8", "value = 1.0"), "untold 1 N·m")
    for scenario, first, window in ((shipped, "field orientation lost", (1.2, 1.6)),
                                    (one, "flux estimate below 0.5·ψ*", (1.8, 2.5))):
        rec = run(prof, MotorParams(), sim_config(plant=scenario, estimator="rs-adaptive"))
        sig = rec.arrays()
        watch = DivergenceWatch(env)
        stop = None
        for k in range(len(sig["t"])):
            row = CycleRow(**{f: float(sig[f][k]) for f in CycleRow._fields})
            blind = row._replace(w_m=math.nan, psi_r_mod=math.nan, T_e=math.nan)
            if watch.check(blind, k + 1):
                stop = k
                break
        assert stop is not None, "the guard never fired"
        assert first in watch.reason, watch.reason
        e = sig["w_m"] - sig["w_ref"]
        assert window[0] < sig["t"][stop] < window[1]
        assert abs(e[stop]) > 20.0  # the motor is lost by then
        # the speed estimate cannot tell
        assert abs(sig["w_hat"][stop] - sig["w_ref"][stop]) < env.e_max
        # what the guard protects against: left alone, the motor ends far from ω*
        assert abs(e[-1]) > 80.0
