"""The emulated drive in CiA 402's standard cyclic modes (CSP 8, CSV 9, CST 10), driven by a master
we did not write: python-canopen's BaseNode402 built from dbc/drive.eds. It sets the mode
(checked against 0x6502), remaps the PDOs through its own PDO API, walks the power state
machine, then streams the target every SYNC and reads the actual values back over PDO
(plant/servo.py is the drive's own field orientation and speed loop)."""

from __future__ import annotations

import math

import canopen
import numpy as np
import pytest
from node402_support import Master402

from dbc import EDS_PATH
from dbc.cia402 import POSITION_UNIT, VELOCITY_UNIT
from dbc.motor import MotorParams
from plant.device import DriveDevice
from plant.servo import T_RATED, Servo, ServoParams

NODE = 5
T = 1e-3


class Master(Master402):
    """The emulator at node 5; RPDO1: controlword + target; TPDO1: statusword + velocity
    actual + torque actual, TPDO2: position actual, on every SYNC."""

    def __init__(self) -> None:
        super().__init__(lambda bus: DriveDevice(bus, NODE), NODE, EDS_PATH)

    def configure(self, mode: str, target: int) -> None:
        super().configure(mode, target, rpdo1=(0x6040, target),
                          tpdos=((0x6041, 0x606C, 0x6077), (0x6064,)),
                          period_us=round(T * 1e6))

    def cycle(self, value: int) -> tuple[int, float, float]:  # type: ignore[override]
        """One lockstep cycle → (statusword, velocity in rad/s, torque in N·m)."""
        sw = super().cycle(value)
        return sw, self.value(0x606C) * VELOCITY_UNIT, self.value(0x6077) * T_RATED / 1000

    def position(self) -> float:
        """The position actual value of the last cycle's TPDO2, rad."""
        return self.value(0x6064) * POSITION_UNIT


@pytest.fixture
def master():
    m = Master()
    yield m
    m.close()


def test_csv_tracks_a_ramp_within_the_speed_loop_bandwidth(master):
    """Magnetise 0.5 s at standstill, ramp to 100 rad/s at 100 rad/s², hold 0.5 s: a type-2
    loop follows the ramp with a lag that dies out (w_bw 60 rad/s)."""
    master.configure("CYCLIC SYNCHRONOUS VELOCITY", 0x60FF)
    errors, w = [], 0.0
    for k in range(2000):
        t = k * T
        w_ref = min(max(t - 0.5, 0.0), 1.0) * 100.0
        sw, w, torque = master.cycle(round(w_ref / VELOCITY_UNIT))
        assert sw & 0x6F == 0x27, f"left Operation enabled at {t:.3f} s: 0x{sw:04X}"
        errors.append((t, w_ref - w))
    ramp = [abs(e) for t, e in errors if 0.7 <= t <= 1.5]
    hold = [abs(e) for t, e in errors if t >= 1.8]
    assert max(ramp) < 1.0, max(ramp)  # rad/s, during the ramp
    assert max(hold) < 0.05, max(hold)  # settled at 100 rad/s
    assert abs(w - 100.0) < 0.05
    assert abs(torque) < 0.2  # no load, no friction: no torque at constant speed


def test_cst_makes_the_torque_asked_for(master):
    """2 N·m after the flux has settled: the torque actual value reads it and the motor
    accelerates at T/J (model (1): no friction)."""
    master.configure("CYCLIC SYNCHRONOUS TORQUE", 0x6071)
    J = MotorParams().J
    for _ in range(500):  # magnetise
        master.cycle(0)
    _, w0, _ = master.cycle(round(2.0 / T_RATED * 1000))
    for _ in range(199):
        _, w1, torque = master.cycle(round(2.0 / T_RATED * 1000))
    assert torque == pytest.approx(2.0, abs=0.05)
    assert (w1 - w0) / (199 * T) == pytest.approx(2.0 / J, rel=0.03)


def test_csp_follows_a_position_ramp(master):
    """CSP: magnetise 0.5 s, then a position that ramps at 50 rad/s for 1 s, then holds:
    the drive's position loop (with the target's speed fed forward) follows it, and the
    position actual value (0x6064) counts what the motor turned."""
    master.configure("CYCLIC SYNCHRONOUS POSITION", 0x607A)
    lag, w = [], 0.0
    for k in range(2000):
        t = k * T
        theta_ref = 50.0 * min(max(t - 0.5, 0.0), 1.0)
        _, w, _ = master.cycle(round(theta_ref / POSITION_UNIT))
        lag.append((t, theta_ref - master.position()))
    assert max(abs(e) for t, e in lag if 0.8 <= t <= 1.5) < 0.2  # rad, while moving
    assert max(abs(e) for t, e in lag if t >= 1.8) < 0.02  # rad, settling at 50 rad
    assert abs(lag[-1][1]) < 0.002  # rad, 0.5 s after the ramp
    assert abs(w) < 0.05


def test_a_mode_the_drive_does_not_have_is_refused(master):
    """0x6502 says which modes exist; 0x6060 refuses any other with an SDO abort."""
    node = master.node
    assert not node.is_op_mode_supported("PROFILED POSITION")
    assert node.is_op_mode_supported("CYCLIC SYNCHRONOUS TORQUE")
    assert node.is_op_mode_supported("CYCLIC SYNCHRONOUS POSITION")
    node.nmt.state = "PRE-OPERATIONAL"
    with pytest.raises(canopen.SdoAbortedError) as exc:
        node.sdo[0x6060].raw = 1
    assert exc.value.code == 0x06090030
    assert node.sdo[0x6061].raw == -1  # unchanged


def test_the_servo_orients_the_field_and_limits_the_torque():
    """The drive's own control, alone: with exact parameters the torque of model (1) equals
    the target once the flux is up; the torque limit holds."""
    from plant.drive import Drive
    from plant.params import DriveParams

    motor = MotorParams()
    drive = Drive(motor, DriveParams(mode="ideal"))
    drive.enable(True)
    servo = Servo(motor, ServoParams(T_max=3.0), T)
    w = 0.0
    for _ in range(600):
        drive.set_setpoints(servo.torque(1.5, w))
        meas = drive.advance(T, 0.0)
        w = meas.w_m
    assert meas.T_e == pytest.approx(1.5, rel=0.01)
    assert abs(meas.psi_r_ab) == pytest.approx(ServoParams().psi_rated, rel=0.01)
    drive.set_setpoints(servo.torque(50.0, w))
    meas = drive.advance(T, 0.0)
    assert meas.T_e <= 3.0 * 1.01
    assert math.isfinite(servo.T_est)


# ------------------------------------------------------------------ the gateway's side


def _summary(out) -> dict:
    import json

    return json.loads((out / "summary.json").read_text())


def test_sim_runs_the_speed_pi_over_cst_and_equals_simulate(tmp_path):
    """`sim --controller speed-pi`: the standard emulator profile in CST, the gateway's speed
    PI over the drive's torque; lockstep equals the in-process simulation bit for bit in every
    column but the measured timing (both quantise through the same DBC)."""
    from gateway.cli import main
    from gateway.report import read_csv

    assert main(["sim", "--controller", "speed-pi", "--duration", "1.2s",
                 "--out", str(tmp_path / "sim")]) == 0
    assert main(["simulate", "--controller", "speed-pi", "--duration", "1.2s",
                 "--out", str(tmp_path / "simulate")]) == 0
    s = _summary(tmp_path / "sim")
    assert s["configuration"]["drive_mode"] == "torque"
    assert s["configuration"]["controller"]["name"] == "speed-pi"
    assert s["configuration"]["drive_profile"] == "<emulator-standard>"
    # a PI speed loop without load feed-forward: about 5 rad/s at the paper's load steps
    assert s["speed_error"]["rms"] < 1.5 and abs(s["speed_error"]["final"]) < 0.1
    bus, local = read_csv(tmp_path / "sim" / "signals.csv"), read_csv(tmp_path / "simulate"
                                                                       / "signals.csv")
    for name, column in local.items():
        assert np.array_equal(bus[name], column, equal_nan=True), name
    assert (tmp_path / "sim" / "fig4_controller.png").is_file()  # T_ref, w_int


@pytest.mark.parametrize("mode, target", [("velocity", 1.5), ("torque", 1.5),
                                          ("position", 3.0)])
def test_stream_sends_the_profile_as_the_target(drive_run, mode, target):
    """`stream`: CSV streams ω* (the drive's speed loop tracks it), CSP ∫ω* dt (its
    position loop), CST the torque that makes ω* against the profile's load (open loop);
    over CANopen (the pytest plugin's drive_run)."""
    from gateway.drivecheck import assert_no_fault

    run = drive_run("paper", where="sim", controller="stream", drive_mode=mode,
                    duration="1.2s")
    assert_no_fault(run)
    s = run.summary
    assert s["speed_error"]["rms"] < target, s["speed_error"]
    assert s["configuration"]["drive_mode"] == mode
    assert s["configuration"]["drive_profile"] == "<emulator-standard>"


def test_csp_streams_the_integral_of_the_speed_profile_and_equals_simulate(tmp_path):
    """CSP: the target position is ∫ω* dt (trapezoids, one period ahead), 0x6060 = 8, and
    the lockstep run equals the in-process simulation bit for bit but for the timing."""
    from gateway.cli import main
    from gateway.reference import load_profile
    from gateway.report import read_csv

    argv = ["--controller", "stream", "--drive-mode", "position", "--reference",
            "profiles/quick.toml"]
    assert main(["sim", *argv, "--out", str(tmp_path / "sim")]) == 0
    assert main(["simulate", *argv, "--out", str(tmp_path / "simulate")]) == 0
    bus, local = read_csv(tmp_path / "sim" / "signals.csv"), read_csv(tmp_path / "simulate"
                                                                       / "signals.csv")
    for name, column in local.items():
        assert np.array_equal(bus[name], column, equal_nan=True), name
    t, theta = bus["t"], bus["theta_target"]
    w_ref = np.array([load_profile("profiles/quick.toml").at(x).w_ref for x in t])
    T = t[1] - t[0]
    want = np.concatenate([[0.0], np.cumsum(0.5 * T * (w_ref[1:] + w_ref[:-1]))]) + T * w_ref
    assert np.allclose(theta, want, atol=1e-9)
    # the drive's position loop turns it into speed: the motor ends on the profile's speed
    s = _summary(tmp_path / "sim")
    assert abs(s["speed_error"]["final"]) < 0.1 and s["speed_error"]["rms"] < 3.0


@pytest.mark.parametrize("argv, words", [
    (["sim", "--drive-mode", "torque"], "--controller speed-pi"),
    (["simulate", "--drive-mode", "velocity"], "--controller speed-pi"),
    (["sim", "--controller", "ifoc", "--drive-mode", "velocity"], "for a standard drive"),
    (["sim", "--controller", "speed-pi", "--drive-mode", "velocity"], "--drive-mode torque"),
    (["sim", "--controller", "stream", "--drive-mode", "ideal"], "--drive-mode velocity"),
])
def test_a_controller_and_drive_that_do_not_fit_are_refused(tmp_path, capsys, argv, words):
    from gateway.cli import main

    assert main([*argv, "--out", str(tmp_path / "o")]) == 2
    err = capsys.readouterr().err
    assert words in err and "Traceback" not in err
    assert not (tmp_path / "o").exists()


def test_run_drives_a_device_in_cst_over_the_bus(emulator, tmp_path):
    """`run` against the emulated device on a virtual bus, as a standard drive: the gateway
    sets 0x6060 = 10 by SDO, maps the standard objects by index, streams the target torque
    and reads the velocity actual value; the drive ends disabled."""
    from gw_support import _patient_drive_profile, assert_disabled, gateway_run

    emu = emulator("current-loop")
    out = tmp_path / "run"
    assert gateway_run(emu, out, "--drive", str(_patient_drive_profile("emulator-standard")),
                       "--controller", "speed-pi", "--duration", "0.6s") == 0
    s = _summary(out)
    assert s["run"]["cycles"] == 600 and s["run"]["stop"] == "END_OF_PROFILE"
    assert s["speed_error"]["rms"] < 2.0  # 1.13 rad/s: the load step at 0.5 s, no feed-forward
    assert emu.device._values[(0x6060, 0)] == 10
    # the speed is the drive's velocity actual value, at its own resolution, not TPDO3's
    assert s["truth"].startswith("TPDO1.velocity_actual, ω to 0.000105 rad/s")
    assert s["quantisation"]["source"] == "standard.dbc"
    assert "w_m" not in s["quantisation"]["signals"]
    assert_disabled(emu)


@pytest.mark.parametrize("key, value, controller", [("velocity", 3, "stream"),
                                                     ("torque", 4, "speed-pi")])
def test_profile_modes_from_the_drive_profile(emulator, tmp_path, key, value, controller):
    """A drive without cyclic modes: the profile's [modes] names profile velocity (3) or
    profile torque (4); the gateway checks it against 0x6502, writes 0x6060 and streams
    the same targets over PDO; the drive ramps them itself (0x6083/0x6084, 0x6087), at
    rates its [[sdo]] start-up writes raise for the paper's speed step (at the defaults,
    104.7 rad/s² and 100 N·m/s, the step outruns the ramp and the guard stops the run)."""
    from gw_support import _patient_drive_profile, assert_disabled, gateway_run

    emu = emulator("current-loop")
    text = _patient_drive_profile("emulator-standard").read_text()
    text = text.replace(f"{key} = {9 if key == 'velocity' else 10} ", f"{key} = {value} ")
    text += "".join(f"\n[[sdo]]\nindex = 0x{i:04X}\nsub = 0\nvalue = {v}\n" for i, v in (
        (0x6083, 20_000_000), (0x6084, 20_000_000), (0x6087, 1_000_000)))  # 2094 rad/s²
    profile = tmp_path / "pv.toml"
    profile.write_text(text)
    mode = "velocity" if key == "velocity" else "torque"
    out = tmp_path / "run"
    assert gateway_run(emu, out, "--drive", str(profile), "--controller", controller,
                       "--drive-mode", mode, "--duration", "0.6s") == 0
    assert emu.device._values[(0x6060, 0)] == value
    s = _summary(out)
    assert s["run"]["stop"] == "END_OF_PROFILE" and s["run"]["cycles"] == 600
    # the drive's own ramp (104.7 rad/s² by default in PV) lags the paper's speed step
    assert s["speed_error"]["rms"] < 15.0 and s["shutdown"]["safe"]
    assert_disabled(emu)
