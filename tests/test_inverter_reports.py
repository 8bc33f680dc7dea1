"""The inverter's errors read from what the drive reports (docs/robustness.md §12): the DC
link a drive measures (TPDO2's u_dc, the period's mean) and the voltage an uncompensated
modulator applies (C3); the dead time's error over an interval from its two sampled
currents (C2′); J read on the speed reference's ramps only where the load is observed."""

from __future__ import annotations

import cmath
import json
import math
import re
from pathlib import Path

import pytest

from dbc.motor import MotorParams
from dbc.timing import Sampling
from gateway.cli import main
from gateway.control.correction import CorrectedController, SensorCorrection
from gateway.control.interface import Command, Sample
from gateway.cycle import ControlCycle, sample_from
from gateway.drive_profile import load_drive_profile
from gateway.errors import UserError
from gateway.reference.signals import References
from plant.drive import Drive, Setpoints
from plant.params import DriveParams

MOTOR = MotorParams()


def _voltage_drive(mode: str = "voltage", **kw: object) -> Drive:
    d = Drive(MOTOR, DriveParams(mode=mode, **kw))  # type: ignore[arg-type]
    d.enable(True)
    d.set_setpoints(Setpoints("ab", 0j, 30.0 + 0j))
    return d


def test_the_drive_reports_its_dc_links_mean_over_the_period() -> None:
    """u_dc = 560·(1 + 0.05·mean of sin(2π·300·t) at the internal steps' midpoints): the
    closed form against the sum, period by period; its mean over whole ripple periods is
    the nominal DC link."""
    T, r, f = 1e-3, 0.05, 300.0
    d = _voltage_drive(u_dc_ripple=r, u_dc_ripple_hz=f)
    h = 1.0 / d.params.f_pwm
    n = round(T / h)
    seen = []
    for k in range(30):
        m = d.advance(T, 0.0)
        mean = sum(math.sin(2.0 * math.pi * f * (k * T + (j + 0.5) * h)) for j in range(n)) / n
        assert m.u_dc == pytest.approx(560.0 * (1.0 + r * mean), rel=1e-12)
        seen.append(m.u_dc)
    assert max(seen) - min(seen) > 0.05 * 560.0  # it ripples (±4.3 % at 1 ms)
    assert sum(seen) / len(seen) == pytest.approx(560.0, rel=1e-9)  # 30 ms = 9 periods


@pytest.mark.parametrize("mode, kw", [("voltage", {}), ("ideal", {"u_dc_ripple": 0.05})])
def test_without_a_ripple_or_an_inverter_the_dc_link_is_the_nominal(mode, kw) -> None:
    d = _voltage_drive(mode, **kw)
    assert {d.advance(1e-3, 0.0).u_dc for _ in range(5)} == {560.0}


def test_the_emulators_profile_says_its_modulator_assumes_its_dc_link() -> None:
    assert load_drive_profile(None).modulator_dc_link_v == DriveParams().u_dc
    assert load_drive_profile(None, "emulator-standard").modulator_dc_link_v is None


@pytest.mark.parametrize("value", ["0.0", "-560.0", "1e6"])
def test_a_modulator_dc_link_out_of_range_is_refused_by_name(tmp_path: Path, value) -> None:
    import gateway

    text = (Path(gateway.__file__).parent / "drives" / "emulator.toml").read_text()
    path = tmp_path / "drive.toml"
    path.write_text(text.replace("modulator_dc_link_v = 560.0", f"modulator_dc_link_v = {value}"))
    with pytest.raises(UserError, match=r"\[drive\]\.modulator_dc_link_v = .* in V"):
        load_drive_profile(str(path))


def test_an_uncompensated_modulators_voltage_is_scaled_by_the_dc_link() -> None:
    """(C3): u_applied = u_reported·u_dc/U_mod; nothing without the key or without u_dc."""
    measured = {"i_sa": 1.0, "i_sb": 2.0, "u_sa": 100.0, "u_sb": -50.0, "u_dc": 588.0}
    assert sample_from(measured, 560.0).u_s_ab == pytest.approx(complex(105.0, -52.5))
    assert sample_from(measured).u_s_ab == complex(100.0, -50.0)
    without = {k: v for k, v in measured.items() if k != "u_dc"}
    assert sample_from(without, 560.0).u_s_ab == complex(100.0, -50.0)


class _Still:
    """A reference profile that asks for nothing."""

    def at(self, t: float) -> References:
        return References(0.0, 0.0, 0.0, 1.0, 0.0, 0.0, 0.0, 0.0)


class _Seen:
    signals = ()

    def __init__(self) -> None:
        self.samples: list[Sample] = []

    def step(self, refs, sample: Sample) -> Command:
        self.samples.append(sample)
        return Command(i_s_dq_ref=0j, u_s_dq_ref=0j, eps_0=0.0, w_0=0.0)


def test_the_controller_gets_the_applied_voltage_and_the_record_the_reported() -> None:
    inner = _Seen()
    cycle = ControlCycle(inner, _Still(), Sampling(1e-3), 560.0)
    out = cycle.step(1, {"i_sa": 0.0, "i_sb": 0.0, "u_sa": 56.0, "u_sb": 0.0, "u_dc": 532.0})
    assert inner.samples[-1].u_s_ab == pytest.approx(53.2)
    assert (out.row.u_sa, out.row.u_sb) == (56.0, 0.0)


class _Recorder:
    signals = ()

    def __init__(self, cmd: Command) -> None:
        self.cmd, self.seen = cmd, []

    def step(self, refs, sample):
        self.seen.append(sample)
        return self.cmd

    def coast(self):
        pass

    def withhold(self):
        pass


def test_the_dead_time_over_an_interval_follows_the_currents_sampled_at_its_ends() -> None:
    """(C2′): the command was corrected along the current it asked for, which kept phase a
    positive (b too, c negative); the currents read at the interval's ends cross phase a's
    zero halfway, and the sample is corrected by (C2) along the line between them."""
    T, u_dead = 1e-3, 10.0
    c = SensorCorrection(u_dead=u_dead)
    asked = cmath.rect(1.0, 0.5 * math.pi - 0.2)  # phases a, b positive, c negative
    cmd = Command(i_s_dq_ref=asked, u_s_dq_ref=complex(5.0, 60.0), eps_0=0.0, w_0=0.0)
    inner = _Recorder(cmd)
    ctl = CorrectedController(inner, c, T, 0)
    u_rep = complex(20.0, -3.0)
    i0, i1 = cmath.rect(1.0, 0.5 * math.pi - 0.05), cmath.rect(1.0, 0.5 * math.pi + 0.05)
    ctl.step(None, Sample(i0, u_rep))
    ctl.step(None, Sample(i1, u_rep))
    sampled = c.voltage_error_over(i0, i1)
    assert inner.seen[-1].u_s_ab == pytest.approx(u_rep - sampled, abs=1e-12)
    commanded = c.voltage_error(asked)  # phase a positive throughout
    # phase a's mean sign 0 (halfway) against +1: the error differs by u_dead·(2/3)
    assert abs(sampled - commanded) == pytest.approx(u_dead * 2.0 / 3.0, rel=1e-3)
    ctl.coast()
    # the interval after the lost sample (the drive held its setpoints through it): its
    # start was not read, and the error is the one at the sample's own current, as before
    ctl.step(None, Sample(i1, u_rep))
    assert inner.seen[-1].u_s_ab == pytest.approx(u_rep - c.voltage_error(i1), abs=1e-12)
    ctl.step(None, Sample(i0, u_rep))  # read at both ends again
    assert inner.seen[-1].u_s_ab == pytest.approx(u_rep - c.voltage_error_over(i1, i0),
                                                  abs=1e-12)


def _summary(out: Path) -> dict:
    return json.loads((out / "summary.json").read_text())


@pytest.mark.slow
def test_the_real_drive_plant_completes_with_the_full_order_law_and_its_load_observed(
        tmp_path: Path) -> None:
    """`real-drive` on the voltage drive with the defaults (its load observed): it stopped at
    2.0 s; now it completes (measured 1.09 rad/s RMS). Its J is the file's: the load steps
    at constant speed are not read as inertia (ρ̂ went to 0 at the first), and the test
    asks 8σ with the load observed (at 4σ the file's J was rejected at 0.482 s for one 12 %
    low)."""
    out = tmp_path / "rd"
    assert main(["simulate", "--no-figures", "--out", str(out), "--plant", "real-drive",
                 "--law", "full-order", "--drive-mode", "voltage"]) == 0
    s = _summary(out)
    assert s["speed_error"]["rms"] < 2.0, s["speed_error"]
    inertia = s["identification"]["inertia"]
    assert not inertia["applied"] and 0.8 < inertia["ratio"] < 1.25, inertia
    assert inertia["T_L_observed"] == pytest.approx(0.5, abs=0.5), inertia  # the profile's end


def test_a_drive_that_sends_no_dc_link_cannot_say_its_modulator_is_uncompensated(
        emulator, tmp_path: Path, capsys) -> None:
    """A profile with ``modulator_dc_link_v`` whose voltages' PDO carries no u_dc: the run
    is refused at bring-up, by name, before the drive is enabled (its voltages would be
    taken as applied, silently)."""
    import gateway
    from dbc import DBC_PATH

    text = (Path(gateway.__file__).parent / "drives" / "emulator.toml").read_text()
    dbc = "\n".join(line for line in DBC_PATH.read_text().split("\n") if "u_dc" not in line)
    (tmp_path / "d.dbc").write_text(dbc.replace("BO_ 641 TPDO2: 6 DRIVE", "BO_ 641 TPDO2: 4 DRIVE"))
    path = tmp_path / "drive.toml"
    path.write_text(text.replace('dbc = "builtin:drive.dbc"', 'dbc = "d.dbc"'))
    emu = emulator("voltage")
    rc = main(["run", "-i", "virtual", "-c", emu.channel, "--drive", str(path), "--law",
               "full-order", "--drive-mode", "voltage", "--reference", "profiles/quick.toml",
               "--out", str(tmp_path / "run")])
    err = capsys.readouterr().err
    assert rc == 2, err
    assert "needs u_dc" in err and "modulator_dc_link_v" in err and "0x6079" in err, err
    assert "Traceback" not in err
    # `profile check` says it too: no drive mode of the paper's laws can run
    assert main(["profile", "check", str(path)]) == 1
    out = capsys.readouterr().out
    assert re.search(r"--drive-mode voltage\s+cannot run the paper's laws: no u_dc", out), out
