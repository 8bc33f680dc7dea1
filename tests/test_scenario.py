"""Plant scenarios: the loader, what they do to the plant, and the three commands."""

from __future__ import annotations

import json
import math
import os
import subprocess
import sys

import numpy as np
import pytest
from sim_support import sim_config

from dbc.motor import MotorParams
from gateway.cli import main
from gateway.reference import paper_profile
from gateway.report import read_csv
from gateway.simulate import run
from plant.cli import main as plant_main
from plant.drive import Drive, Setpoints
from plant.params import DriveParams
from plant.scenario import (
    PlantScenario,
    ScenarioError,
    TorqueStep,
    load_scenario,
    parse_scenario,
    resolve_scenario,
    shipped_names,
)

MOTOR = MotorParams.paper()
EXACT = ("t", "i_sa", "i_sb", "u_sa", "u_sb", "i_sd_ref", "i_sq_ref", "u_sd_ref", "u_sq_ref",
         "eps_0", "w_0", "w_hat", "psi_rd_hat", "psi_rq_hat")


# ---------------------------------------------------------------------------------- loader


@pytest.mark.parametrize(("text", "needles"), [
    ("[motr]\nRs = 1.1\n", ["[motr]", "unknown table", "motor"]),
    ("[motor]\nRss = 1.1\n", ["[motor].Rss", "unknown key", "Rs"]),
    ("[motor]\nRs = 0\n", ["[motor].Rs = 0", "> 0"]),
    ("[motor]\nRs = 1.1\nR_s = 1.2\n", ["[motor].R_s", "twice"]),
    ("[motor]\nRs = \"hot\"\n", ["[motor].Rs", "must be a number"]),
    ("[sensors]\ngain_b = -1.0\n", ["[sensors].gain_b", "> 0"]),
    ("[sensors]\nnoise = -0.1\n", ["[sensors].noise", "≥ 0"]),
    ("[sensors]\nseed = 1.5\n", ["[sensors].seed", "integer"]),
    ("[inverter]\ndead_time = 1e-3\n", ["[inverter].dead_time", "< 5e-05"]),
    ("[load]\nknown = \"no\"\n", ["[load].known", "true", "false"]),
    ("[load]\ntorque = \"dyno\"\n", ["[load].torque", "'rpdo'", "'profile'"]),
    ("[load]\nsteps = [{ t = 0.5, value = 1.0, ramp = 0.2 }, { t = 0.6, value = 0.0, "
     "ramp = 0.1 }]\n", ["[load].steps[1].t", "previous step ends at 0.7"]),
    ("[load]\nsteps = [{ t = 0.5, value = 1.0 }]\n", ["[load].steps[0].ramp", "missing"]),
    ("[motor\n", ["not valid TOML"]),
])
def test_loader_errors_name_file_key_and_fix(tmp_path, text, needles):
    f = tmp_path / "bad.toml"
    f.write_text(text)
    with pytest.raises(ScenarioError) as exc:
        load_scenario(f)
    msg = str(exc.value)
    assert msg.startswith(str(f))
    for n in needles:
        assert n in msg, msg
    assert "\n" not in msg


def test_missing_file_lists_the_shipped_scenarios():
    with pytest.raises(ScenarioError, match=r"no such file.*rs\+10"):
        resolve_scenario("/no/such/scenario.toml")


def test_shipped_scenarios_cover_the_issue_table():
    names = set(shipped_names())
    assert {"nominal", "rs+5", "rs-5", "rs+10", "rs-10", "offset10mA", "offset10mA-rs+5",
            "rr+20", "rr-20", "unknown-load", "continuous-load"} <= names
    for n in names:
        s = resolve_scenario(n)
        assert s.name == n
        s.plant_motor(MOTOR)
        s.drive_params(DriveParams())
    assert resolve_scenario("nominal").nominal
    assert not resolve_scenario("rs+5").nominal


def test_motor_factors_and_drift_applied():
    s = parse_scenario("[motor]\nRs = 1.1\nRr = 0.8\nJ = 2\nM_drift = -0.01\n", "x.toml")
    p = s.plant_motor(MOTOR)
    assert (p.R_s, p.R_r, p.J, p.L_s, p.M) == pytest.approx(
        (1.1 * MOTOR.R_s, 0.8 * MOTOR.R_r, 2 * MOTOR.J, MOTOR.L_s, MOTOR.M), rel=1e-15)
    assert s.drive_options()["motor_drift"] == {"M": -0.01}
    assert PlantScenario().plant_motor(MOTOR) is MOTOR
    bad = parse_scenario("[motor]\nM = 1.2\n", "m.toml")
    with pytest.raises(ScenarioError, match=r"m.toml.*M² ≥ L_s·L_r.*\[motor\]"):
        bad.plant_motor(MOTOR)


def test_sensor_and_inverter_errors_in_drive_params():
    s = parse_scenario("[sensors]\noffset_a = 0.01\noffset_b = 0.02\ngain_b = 1.02\n"
                       "noise = 0.005\nseed = 3\n[inverter]\ndead_time = 2e-6\n"
                       "dc_ripple = 0.05\ndc_ripple_hz = 100\n")
    base = DriveParams(mode="current-loop")
    p = s.drive_params(base)
    # Clarke of phase offsets: α = o_a, β = (o_a + 2·o_b)/√3
    assert p.i_offset_ab == pytest.approx(complex(0.01, 0.05 / math.sqrt(3.0)), abs=1e-15)
    assert p.i_gain_phase == pytest.approx((0.0, 0.02))
    assert (p.i_noise_rms, p.seed, p.dead_time, p.u_dc_ripple, p.u_dc_ripple_hz) == (
        0.005, 3, 2e-6, 0.05, 100.0)
    assert p.mode == "current-loop"
    assert PlantScenario().drive_params(base) is base


def test_extra_torque_is_a_quintic_step_within_periods():
    s = PlantScenario(load_initial=1.0, load_steps=(TorqueStep(0.5, 3.0, 0.01),))
    assert s.extra_torque(0.0) == 1.0 and s.extra_torque(0.5) == 1.0
    assert s.extra_torque(0.505) == pytest.approx(2.0)
    assert s.extra_torque(0.51) == pytest.approx(3.0) and s.extra_torque(9.0) == 3.0
    f = s.load_function(None)
    assert f(0.505, 4.0) == pytest.approx(6.0)  # rpdo: RPDO3's T_L plus the extra torque
    assert PlantScenario().load_function(None) is None  # plain: hold RPDO3's T_L
    prof = PlantScenario(load_torque="profile").load_function(lambda t: 10.0 * t)
    assert prof(0.3, 99.0) == pytest.approx(3.0)  # RPDO3 ignored
    with pytest.raises(ScenarioError, match=r"simulate.*sim"):
        PlantScenario(load_torque="profile").load_function(None)


# ----------------------------------------------------------------------- on the plant


def test_profile_load_applied_within_the_period_costs_accuracy():
    """The issue's observation: a held load flatters the sampled loop (0.269 → 0.276)."""
    prof = paper_profile()
    held = run(prof, MOTOR, sim_config(flux="true", duration=1.2)).arrays()
    cont = run(prof, MOTOR, sim_config(flux="true", duration=1.2,
                                      plant=resolve_scenario("continuous-load"))).arrays()

    def rms(a):
        return float(np.sqrt(np.mean((a["w_m"] - a["w_ref"]) ** 2)))

    assert rms(cont) > rms(held) * 1.01
    assert rms(cont) < rms(held) * 1.2
    # the load steps at 0.5 s over 10 ms: within-period torque differs from the held one
    k = np.searchsorted(held["t"], 0.5)
    assert not np.array_equal(held["w_m"][k:k + 20], cont["w_m"][k:k + 20])


def test_offset_is_regulated_into_the_true_current_of_the_loop():
    """With a phase-a offset the current loop regulates the measurement: the controller's
    measured current equals its setpoint on average, the true current is off by the offset."""
    s = resolve_scenario("offset10mA")
    params = s.drive_params(DriveParams(mode="current-loop"))
    d = Drive(MOTOR, params)
    d.enable(True)
    d.set_setpoints(Setpoints("ab", 2.0 + 0j, 2.0 * MOTOR.R_s))
    for _ in range(200):
        m = d.advance(1e-3, 0.0)
    assert m.i_s_ab == pytest.approx(2.0 + 0j, abs=1e-3)
    assert d.state.i_s_ab == pytest.approx(2.0 - params.i_offset_ab, abs=1e-3)


def test_rs_error_changes_nothing_with_true_flux_and_much_with_the_estimator():
    """The current-fed law with the true flux never uses R_s; the estimator (24) does."""
    prof = paper_profile()
    for flux, same in (("true", True), ("estimated", False)):
        a = run(prof, MOTOR, sim_config(flux=flux, duration=0.8)).arrays()
        b = run(prof, MOTOR, sim_config(flux=flux, duration=0.8,
                                       plant=resolve_scenario("rs+5"))).arrays()
        assert np.array_equal(a["w_m"], b["w_m"]) == same


def test_continuous_time_takes_motor_factors_but_refuses_sensors():
    cfg = sim_config(period=None, flux="true", duration=0.6, plant=resolve_scenario("rr+20"))
    a = run(paper_profile(), MOTOR, cfg).arrays()
    b = run(paper_profile(), MOTOR, sim_config(period=None, flux="true", duration=0.6)).arrays()
    assert np.max(np.abs(a["w_m"] - a["w_ref"])) > 10 * np.max(np.abs(b["w_m"] - b["w_ref"]))
    from gateway.errors import UserError

    with pytest.raises(UserError, match="continuous time models the motor factors"):
        sim_config(period=None, plant=resolve_scenario("offset10mA"))


# --------------------------------------------------------------------------- commands


def test_simulate_records_the_scenario(tmp_path):
    f = tmp_path / "mine.toml"
    f.write_text("[motor]\nRs = 1.07\n[sensors]\nnoise = 0.001\n")
    out = tmp_path / "run"
    assert main(["simulate", "--plant", str(f), "--duration", "0.2s", "--out", str(out)]) == 0
    ps = json.loads((out / "summary.json").read_text())["configuration"]["plant_scenario"]
    assert ps["file"] == str(f) and ps["name"] == "mine"
    assert ps["motor_factors"]["R_s"] == 1.07 and ps["sensors"]["noise"] == 0.001
    out2 = tmp_path / "nominal"
    assert main(["simulate", "--duration", "0.1s", "--out", str(out2)]) == 0
    ps = json.loads((out2 / "summary.json").read_text())["configuration"]["plant_scenario"]
    assert ps["file"] is None and ps["name"] == "nominal"


def test_simulate_bad_scenario_exits_2(tmp_path, capsys):
    f = tmp_path / "bad.toml"
    f.write_text("[motor]\nRs = -1\n")
    assert main(["simulate", "--plant", str(f), "--out", str(tmp_path / "o")]) == 2
    err = capsys.readouterr().err
    assert "bad.toml: [motor].Rs = -1" in err and "Traceback" not in err


def test_sim_over_canopen_equals_simulate_with_the_scenario(tmp_path):
    """`sim --plant` builds the emulator from the scenario: the bus run equals `simulate`
    with the same scenario bit for bit (sensor offsets, gains, noise, dead time, drift)."""
    f = tmp_path / "plant.toml"
    f.write_text("[motor]\nRs = 1.05\nRs_drift = 0.1\n[sensors]\noffset_a = 0.01\n"
                 "gain_b = 1.01\nnoise = 0.002\n[inverter]\ndead_time = 1e-6\n"
                 "[load]\ntorque = \"profile\"\n")
    out = tmp_path / "sim"
    assert main(["sim", "--plant", str(f), "--drive-mode", "current-loop", "--duration", "0.6s",
                 "--discretisation", "euler", "--flux", "true",
                 "--out", str(out)]) == 0
    bus = read_csv(out / "signals.csv")
    sim = run(paper_profile(), MOTOR, sim_config(drive="current-loop", duration=0.6,
                                                flux="true",
                                                plant=load_scenario(f))).arrays()
    for col in EXACT:
        np.testing.assert_array_equal(bus[col], sim[col], err_msg=col)
    nominal = run(paper_profile(), MOTOR, sim_config(drive="current-loop", duration=0.6)).arrays()
    assert not np.array_equal(nominal["i_sa"], sim["i_sa"])
    ps = json.loads((out / "summary.json").read_text())["configuration"]["plant_scenario"]
    assert ps["file"] == str(f) and ps["motor_drift_per_s"]["R_s"] == 0.1


def test_hil_plant_run_takes_the_scenario():
    env = {k: v for k, v in os.environ.items() if not k.startswith("CAN_")}
    proc = subprocess.Popen([sys.executable, "-m", "plant", "run", "-i", "virtual", "-c", "t",
                             "--plant", "rs+10"], stdout=subprocess.PIPE,
                            stderr=subprocess.PIPE, text=True, env=env)
    try:
        line = proc.stdout.readline()
        assert line == "hil-plant: node 1 ready on virtual:t (PRE-OPERATIONAL), plant rs+10\n"
        proc.terminate()
        _, err = proc.communicate(timeout=10)
    finally:
        proc.kill()
    assert proc.returncode == 0, err


def test_hil_plant_run_refuses_a_profile_load_and_bad_files(capsys, tmp_path):
    assert plant_main(["run", "-i", "virtual", "-c", "x", "--plant", "unknown-load"]) == 2
    err = capsys.readouterr().err
    assert "--plant" in err and "torque = \"profile\"" in err and err.count("\n") == 1
    f = tmp_path / "b.toml"
    f.write_text("[sensors]\ngain_a = 0\n")
    assert plant_main(["run", "-i", "virtual", "-c", "x", "--plant", str(f)]) == 2
    assert "[sensors].gain_a" in capsys.readouterr().err


def test_device_applies_the_scenario_to_its_motor_and_sensors():
    import can

    from plant.device import DriveDevice

    s = resolve_scenario("offset10mA-rs+10")
    bus = can.Bus(interface="virtual", channel=f"scn-{os.getpid()}")
    try:
        dev = DriveDevice(bus, 1, s.plant_motor(MOTOR), s.drive_params(DriveParams()),
                          drive_options=s.drive_options())
        assert dev.drive.motor.R_s == pytest.approx(1.1 * MOTOR.R_s)
        assert dev.drive.params.i_offset_ab == pytest.approx(complex(0.01, 0.01 / 3 ** 0.5))
    finally:
        bus.shutdown()
