"""Commissioning at standstill (`hil-gateway identify`, gateway/control/identify.py): the
values it finds against the plant's on the shipped scenarios, the motor file it writes and
what a later run does with it, over `simulate` and over CANopen, and its refusals."""

from __future__ import annotations

import json
import math

import pytest

from dbc.motor import MotorParams, commissioning
from gateway.cli import main
from plant.scenario import resolve_scenario

SQRT3 = math.sqrt(3.0)


def _identify(tmp_path, *options: str) -> tuple[int, dict, MotorParams, dict]:
    out = tmp_path / "motor.toml"
    rc = main(["identify", "-o", str(out), "--out", str(tmp_path / "run"), "--no-figures",
               *options])
    summary = json.loads((tmp_path / "run" / "summary.json").read_text())
    if not out.exists():
        return rc, summary, MotorParams.paper(), {}
    return rc, summary, MotorParams.from_toml(out), commissioning(out)


def _plant(name: str) -> tuple[MotorParams, object]:
    scenario = resolve_scenario(name)
    return scenario.plant_motor(MotorParams.paper()), scenario


@pytest.mark.parametrize("scenario", ["nominal", "offset10mA-rs+10", "rs-10", "rr+20",
                                      "rr-20", "noise5mA", "real-drive"])
def test_the_motor_file_is_the_plants_within_2_percent_and_offsets_within_1_mA(
        tmp_path, scenario):
    rc, s, found, extra = _identify(tmp_path, "--plant", scenario)
    assert rc == 0, s["identification"]
    plant, sc = _plant(scenario)
    for name in ("R_s", "R_r", "L_s", "L_r", "M"):  # R_s: at the start (real-drive warms)
        assert getattr(found, name) == pytest.approx(getattr(plant, name), rel=0.02), name
    assert found.J == MotorParams.paper().J  # not measured: the nameplate's
    assert extra["offset_a"] == pytest.approx(sc.offset_a, abs=1e-3)
    assert extra["offset_b"] == pytest.approx(sc.offset_b, abs=1e-3)
    assert extra["gain_b"] == pytest.approx(sc.gain_b / sc.gain_a, abs=2e-3)
    drift = sc.motor_drift.get("R_s", 0.0)
    assert extra["R_s_drift"] == pytest.approx(drift, abs=2e-3)
    verdicts = {k: v["verdict"] for k, v in s["identification"]["values"].items()}
    assert set(verdicts.values()) == {"good"}, verdicts


def test_the_inverters_dead_time_is_found_through_the_drives_current_loop(tmp_path):
    scenario = tmp_path / "dead.toml"
    scenario.write_text('[motor]\nRs = 1.1\n[inverter]\ndead_time = 2e-6\n')
    rc, s, found, extra = _identify(tmp_path, "--plant", str(scenario), "--drive-mode",
                                    "current-loop")
    assert rc == 0, s["identification"]
    assert extra["u_dead"] == pytest.approx(2e-6 * 10e3 * 560.0, rel=0.05)  # dead_time·f·u_dc
    assert found.R_s == pytest.approx(1.1 * 5.3, rel=0.02)
    assert found.R_r == pytest.approx(3.3, rel=0.02)


def test_over_canopen_against_the_emulator(tmp_path, capsys):
    rc, s, found, extra = _identify(tmp_path, "--on", "sim", "--plant", "offset10mA-rs+10")
    assert rc == 0 and s["configuration"]["controller"]["name"] == "identify"
    assert found.R_s == pytest.approx(1.1 * 5.3, rel=0.01)
    assert extra["offset_a"] == pytest.approx(0.010, abs=1e-3)
    out = capsys.readouterr().out
    assert "R_s, Ω" in out and "+10.0 %" in out and "wrote" in out


def test_a_run_with_the_identified_motor_file_reaches_the_nominal_precision(tmp_path):
    rc, _, _, _ = _identify(tmp_path, "--plant", "rs+10")
    assert rc == 0
    assert main(["simulate", "--motor", str(tmp_path / "motor.toml"), "--no-figures",
                 "--out", str(tmp_path / "after")]) == 0
    after = json.loads((tmp_path / "after" / "summary.json").read_text())
    assert after["speed_error"]["rms"] <= 0.005
    assert MotorParams.from_toml(tmp_path / "motor.toml").R_s == pytest.approx(5.83, rel=0.01)


@pytest.mark.parametrize("options, words", [
    (["--controller", "paper"], "the test's own"),
    (["--reference", "profiles/quick.toml"], "the test's own"),
    (["--drive-mode", "voltage"], "current setpoints"),
    (["--current", "-1"], "positive current"),
    (["-o", "motor.json"], "TOML"),
])
def test_bad_input_is_refused_in_one_paragraph(tmp_path, capsys, options, words):
    argv = ["identify", "--out", str(tmp_path / "run"), "--no-figures"]
    if "-o" not in options:
        argv += ["-o", str(tmp_path / "m.toml")]
    assert main([*argv, *options]) == 2
    err = capsys.readouterr().err
    assert words in err and "Traceback" not in err


def test_an_existing_motor_file_is_kept_unless_replaced(tmp_path, capsys):
    out = tmp_path / "m.toml"
    out.write_text("J = 1.0\n")
    assert main(["identify", "-o", str(out), "--out", str(tmp_path / "r")]) == 2
    assert "--replace" in capsys.readouterr().err and out.read_text() == "J = 1.0\n"
    assert main(["identify", "-o", str(out), "--replace", "--no-figures", "--out",
                 str(tmp_path / "r2")]) == 0
    assert MotorParams.from_toml(out).R_s == pytest.approx(5.3, rel=1e-3)
