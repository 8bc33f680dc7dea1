"""The emulated drive in CiA 402's profile modes, profile velocity (3) and profile torque (4),
driven by python-canopen's BaseNode402: the mode set by SDO 0x6060 (checked against
0x6502), targets by RPDO or by SDO; the drive ramps to them itself (plant/profile.py) and
its own control follows the ramp (plant/servo.py).

The tolerances come from the drive's speed loop: a PI on the motor's inertia with a double
closed-loop pole at w_bw = 60 rad/s (ServoParams.w_bw). Its error after a ramp of
acceleration a starts or ends is a·t·e^(−w_bw·t), at most a/(e·w_bw); the loop acts on the
encoder's sample of the period before, one period T later, which adds at most a·T."""

from __future__ import annotations

import itertools
import math

import canopen
import pytest
from node402_support import Master402

from dbc import EDS_PATH
from dbc.cia402 import SW_SPEED_ZERO, SW_TARGET_REACHED, VELOCITY_UNIT, OperationMode
from dbc.motor import MotorParams
from plant.device import DriveDevice
from plant.profile import ProfileRamp, ProfileSettings, ramp_velocity
from plant.servo import T_RATED, ServoParams

NODE = 6
T = 1e-3
W_BW = ServoParams().w_bw
TORQUE_UNIT = T_RATED / 1000
TPDOS = ((0x6041, 0x606C, 0x6077), (0x606B, 0x6074))  # actual values; the ramps' outputs
OPERATION_ENABLED = 0x27


def ramp_lag(a: float) -> float:
    """The largest speed error of the drive's loop where a ramp of ``a`` rad/s² starts or
    stops (see the module docstring), rad/s."""
    return a / (math.e * W_BW) + a * T


@pytest.fixture
def master():
    m = Master402(lambda bus: DriveDevice(bus, NODE), NODE, EDS_PATH)
    yield m
    m.close()


def run(master: Master402, cycles: int, target: float | None = None,
        unit: float = VELOCITY_UNIT) -> list[tuple[int, float, float, float, float]]:
    """``cycles`` lockstep cycles (``target`` in SI streamed in RPDO1, if given) → per cycle
    (statusword, velocity actual rad/s, velocity demand rad/s, torque actual N·m, torque
    demand N·m)."""
    rows = []
    for _ in range(cycles):
        sw = master.cycle(None if target is None else round(target / unit))
        assert sw & 0x6F == OPERATION_ENABLED, f"left Operation enabled: 0x{sw:04X}"
        rows.append((sw, master.value(0x606C) * VELOCITY_UNIT,
                     master.value(0x606B) * VELOCITY_UNIT,
                     master.value(0x6077) * TORQUE_UNIT, master.value(0x6074) * TORQUE_UNIT))
    return rows


def test_the_drive_says_it_offers_the_profile_modes(master):
    node = master.node
    assert node.sdo[0x6502].raw == 0x0003038C
    assert node.is_op_mode_supported("PROFILED VELOCITY")
    assert node.is_op_mode_supported("PROFILED TORQUE")
    assert not node.is_op_mode_supported("PROFILED POSITION")
    assert node.sdo[0x6088].raw == 0  # linear torque ramp
    node.nmt.state = "PRE-OPERATIONAL"
    with pytest.raises(canopen.SdoAbortedError) as exc:
        node.sdo[0x6088].raw = 1  # no sin² ramp
    assert exc.value.code == 0x06090031


def test_pv_ramps_to_a_target_sent_by_pdo(master):
    """Profile velocity, the target streamed in RPDO1: standstill (speed = 0 and target
    reached), then a step to 100 rad/s, which the velocity demand reaches at exactly the
    profile acceleration (200 rad/s²) and the motor follows within the loop's ramp lag;
    once settled, target reached again."""
    a = 200.0
    master.node.sdo[0x6083].raw = round(a / VELOCITY_UNIT)
    master.configure("PROFILED VELOCITY", 0x60FF, rpdo1=(0x6040, 0x60FF), tpdos=TPDOS)
    still = run(master, 500, 0.0)  # magnetising at standstill
    assert still[-1][0] & (SW_TARGET_REACHED | SW_SPEED_ZERO) == SW_TARGET_REACHED | SW_SPEED_ZERO
    rows = run(master, 1200, 100.0)
    demand = [r[2] for r in rows]
    steps = [b - a_ for a_, b in itertools.pairwise(demand)]
    assert max(steps) == pytest.approx(a * T, abs=2 * VELOCITY_UNIT)  # the acceleration
    assert demand.index(max(demand)) == pytest.approx(100.0 / (a * T), abs=2)  # 0.5 s
    lag = max(abs(w - dem) for _, w, dem, _, _ in rows)
    assert lag < ramp_lag(a), (lag, ramp_lag(a))
    assert lag > 0.5 * ramp_lag(a)  # the loop does lag: the check can fail
    assert not rows[400][0] & (SW_TARGET_REACHED | SW_SPEED_ZERO)  # on its way
    sw, w = rows[-1][0], rows[-1][1]
    assert sw & SW_TARGET_REACHED and not sw & SW_SPEED_ZERO
    assert abs(w - 100.0) < 0.05


def test_pv_follows_targets_sent_by_sdo_and_halts(master):
    """Profile velocity with the target written by SDO (RPDO1 carries the controlword
    only): 60 rad/s, then −60 rad/s: the demand slows down to zero at the profile
    deceleration (400 rad/s²) and speeds up the other way at the acceleration (150 rad/s²);
    then halt (controlword bit 8) stops the motor at the deceleration with the target
    kept, and target reached says the axis stands still."""
    a, d = 150.0, 400.0
    node = master.node
    node.sdo[0x6083].raw = round(a / VELOCITY_UNIT)
    master.configure("PROFILED VELOCITY", None, rpdo1=(0x6040,), tpdos=TPDOS)
    node.sdo[0x6084].raw = round(d / VELOCITY_UNIT)  # a profile parameter in operation
    run(master, 300)
    node.sdo[0x60FF].raw = round(60.0 / VELOCITY_UNIT)
    up = run(master, 800)
    assert up[-1][0] & SW_TARGET_REACHED and abs(up[-1][1] - 60.0) < 0.05
    node.sdo[0x60FF].raw = round(-60.0 / VELOCITY_UNIT)
    rows = run(master, 1000)
    demand = [60.0] + [r[2] for r in rows]
    steps = [b - a_ for a_, b in itertools.pairwise(demand)]
    slowing = [s for s, v in zip(steps, demand, strict=False) if v > 0]
    speeding = [s for s, v in zip(steps, demand, strict=False) if v < 0 and s < 0]
    assert min(slowing) == pytest.approx(-d * T, abs=2 * VELOCITY_UNIT)
    assert min(speeding) == pytest.approx(-a * T, abs=2 * VELOCITY_UNIT)
    assert max(abs(w - dem) for _, w, dem, _, _ in rows) < ramp_lag(d)
    assert abs(rows[-1][1] + 60.0) < 0.05 and rows[-1][0] & SW_TARGET_REACHED
    node.rpdo[1][0x6040].raw = 0x010F  # enable operation + halt
    halted = run(master, 600)
    assert all(r[2] >= -60.0 - VELOCITY_UNIT for r in halted) and halted[-1][2] == 0.0
    assert min(r[2] - p[2] for p, r in itertools.pairwise(halted)) >= -1e-9
    assert abs(halted[-1][1]) < 0.05
    assert halted[-1][0] & (SW_TARGET_REACHED | SW_SPEED_ZERO) == (SW_TARGET_REACHED
                                                                    | SW_SPEED_ZERO)
    assert node.sdo[0x60FF].raw == round(-60.0 / VELOCITY_UNIT)  # halt keeps the target


@pytest.mark.parametrize("by", ["pdo", "sdo"])
def test_pt_ramps_the_torque_at_the_slope(master, by):
    """Profile torque: after the flux has settled, a target of 2 N·m: the torque demand
    rises at the torque slope (20 N·m/s: 0.1 s), the torque actual value follows it (the
    field orientation is exact with the model's parameters), target reached comes when the
    ramp is done, and the motor accelerates at T/J (model (1): no friction)."""
    slope, target = 20.0, 2.0
    node = master.node
    node.sdo[0x6087].raw = round(slope / TORQUE_UNIT)
    master.configure("PROFILED TORQUE", 0x6071 if by == "pdo" else None,
                     rpdo1=(0x6040, 0x6071) if by == "pdo" else (0x6040,), tpdos=TPDOS)
    run(master, 500, 0.0 if by == "pdo" else None, TORQUE_UNIT)
    if by == "sdo":
        node.sdo[0x6071].raw = round(target / TORQUE_UNIT)
    rows = run(master, 300, target if by == "pdo" else None, TORQUE_UNIT)
    demand = [r[4] for r in rows]
    steps = [b - a for a, b in itertools.pairwise([0.0, *demand])]
    assert max(steps) == pytest.approx(slope * T, abs=1e-9)
    ramp_end = demand.index(target)
    assert ramp_end == pytest.approx(target / (slope * T) - 1, abs=1)
    assert not rows[ramp_end - 1][0] & SW_TARGET_REACHED
    assert all(r[0] & SW_TARGET_REACHED for r in rows[ramp_end:])
    # the torque actual value is the model's at the sample: the demand of the period
    assert max(abs(tq - dem) for _, _, _, tq, dem in rows) < 0.05
    J = MotorParams().J
    w0, w1 = rows[ramp_end + 10][1], rows[-1][1]
    assert (w1 - w0) / ((len(rows) - ramp_end - 11) * T) == pytest.approx(target / J, rel=0.03)


def test_the_ramps_alone():
    """The generators without a bus: PV slows down to zero first (never past it in one
    period) and then speeds up; PT's target is bounded by the torque limit."""
    s = ProfileSettings(acceleration=100.0, deceleration=1000.0)
    assert ramp_velocity(0.5, -10.0, s, 1e-3) == 0.0  # 1 rad/s per period, stops at zero
    assert ramp_velocity(0.0, -10.0, s, 1e-3) == pytest.approx(-0.1)
    assert ramp_velocity(10.0, 5.0, s, 1e-3) == pytest.approx(9.0)
    assert ramp_velocity(-10.0, -20.0, s, 1e-3) == pytest.approx(-10.1)
    ramp = ProfileRamp(OperationMode.PROFILE_TORQUE, 1e-3, torque_max=3.0)
    for _ in range(1000):
        ramp.step(50.0, ProfileSettings(torque_slope=100.0), False, 0.0)
    assert ramp.demand == 3.0
    assert ramp.supervise(0.0, 50.0, ProfileSettings(), False) == SW_TARGET_REACHED
    ramp.stop()
    assert ramp.demand is None and ramp.bits == 0


@pytest.mark.parametrize("word, mode", [("profile-velocity", 3), ("profile-torque", 4),
                                        ("velocity", 9), ("current-loop", -1)])
def test_hil_plant_run_drive_mode_sets_the_default_mode(monkeypatch, word, mode):
    """`hil-plant run --drive-mode profile-velocity|profile-torque` starts the emulator in
    that mode (0x6060, 0x6061) over its current loop (0x2202 = 1)."""
    from plant import device as device_module
    from plant.cli import main

    seen = {}

    def start(self):
        seen.update(mode=self._values[(0x6060, 0)], display=self._values[(0x6061, 0)],
                    model=self._values[(0x2202, 0)])
        raise KeyboardInterrupt  # stop at once: hil-plant's Ctrl-C

    monkeypatch.setattr(device_module.DriveDevice, "start", start)
    assert main(["run", "-i", "virtual", "-c", "cli-mode", "--drive-mode", word]) == 0
    assert seen == {"mode": mode, "display": mode, "model": 1}
