"""`hil-gateway simulate` and `profile`: outputs, the summary's content, and bad input."""

from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from gateway.cli import main
from gateway.report import read_csv

ROOT = Path(__file__).resolve().parents[1]


def run_cli(*args: str) -> subprocess.CompletedProcess:
    """The CLI in a subprocess (to see exit status, stdout and stderr as a user does)."""
    return subprocess.run([sys.executable, "-m", "gateway", *args], capture_output=True,
                          text=True, cwd=ROOT, timeout=300)


def test_simulate_continuous_reproduces_section_6(tmp_path):
    out = tmp_path / "cont"
    assert main(["simulate", "--period", "continuous", "--flux", "true", "--out", str(out)]) == 0
    summary = json.loads((out / "summary.json").read_text())
    for key in ("speed_error", "flux_error", "estimation_error"):
        assert set(summary[key]) >= {"max", "rms", "final", "windows"}
        # one window per segment of the profile: start-up, speed ramp, load on, load off,
        # field weakening
        assert [w["from"] for w in summary[key]["windows"]] == [0.0, 0.32, 0.5, 1.0, 1.5]
    assert summary["speed_error"]["windows"][1]["label"] == "speed 0 → 100 rad/s"
    assert summary["speed_error"]["windows"][-1]["to"] == pytest.approx(2.5)
    assert summary["truth"] == "simulated motor state, full resolution"
    assert summary["quantisation"]["applied"] is False
    assert summary["speed_error"]["max"] < 5e-3  # mrad/s range
    assert abs(summary["speed_error"]["final"]) < 1e-4
    assert abs(summary["estimation_error"]["final"]) < 1e-4
    assert 7.0 < summary["peak_current"] < 10.0
    assert summary["configuration"]["period"] == "continuous"
    assert summary["run"] == {"stop": "END_OF_PROFILE", "stop_reason": "end of the profile",
                              "exit_status": 0, "cycles": 2501}
    sig = read_csv(out / "signals.csv")
    assert sig["t"][-1] == pytest.approx(2.5)
    assert np.max(np.abs(sig["w_m"] - sig["w_ref"])) == pytest.approx(summary["speed_error"]["max"])
    pngs = {p.name for p in out.glob("*.png")}
    assert {"fig1_references.png", "fig2_errors.png"} <= pngs


def test_a_diverging_simulation_stops_and_exits_1(tmp_path):
    """The bus loop's divergence guard in `simulate`: a loop that lost the motor (zero speed
    under load, R_s +10 %, the drift-free estimator: the runaway of docs/robustness.md §4) is
    stopped with exit 1, the cause named, and the files hold the run up to the trip."""
    from dbc.motor import MotorParams
    from gateway.cycle import CycleRow
    from gateway.guard import profile_envelope
    from gateway.reference import load_profile

    out = tmp_path / "runaway"
    profile = ROOT / "gateway" / "profiles" / "zero-speed.toml"
    p = run_cli("simulate", "--profile", str(profile), "--plant", "rs+10", "--estimator",
                "drift-free", "--discretisation", "euler", "--no-identify", "--out", str(out))
    assert p.returncode == 1, p.stderr
    assert "the loop diverged and the simulation stopped: cycle" in p.stderr
    assert "Traceback" not in p.stderr
    s = json.loads((out / "summary.json").read_text())
    run = s["run"]
    assert run["stop"] == "DIVERGED" and run["exit_status"] == 1
    assert "3 cycles in a row" in run["stop_reason"]
    sig = read_csv(out / "signals.csv")
    n = len(sig["t"])
    assert run["cycles"] == n and sig["t"][-1] < load_profile(profile).duration - 0.1
    # the record ends with the trip: its last three rows outside the envelope, the one
    # before inside (else the watch would have tripped a cycle earlier)
    env = profile_envelope(load_profile(profile), MotorParams(), 20.0)
    rows = [CycleRow(**{f: float(sig[f][i]) for f in CycleRow._fields}) for i in range(n)]
    assert all(env.check(r) for r in rows[-3:]) and env.check(rows[-4]) is None
    assert run["stop_reason"].startswith(f"cycle {n} ")


def test_divergence_watch_needs_the_cycles_in_a_row():
    from gateway.cycle import CycleRow
    from gateway.guard import DivergenceWatch, Envelope

    env = Envelope(w_max=10.0, i_max=10.0, psi_max=2.0, u_max=100.0, e_max=5.0)
    zero = CycleRow(**{f: 0.0 for f in CycleRow._fields})
    out = zero._replace(w_hat=11.0, w_ref=11.0, w_m=11.0)  # only the speed bound crossed
    watch = DivergenceWatch(env, cycles=3)
    seq = [out, out, zero, out, out]
    assert [watch.check(r, k) for k, r in enumerate(seq, 1)] == [False] * 5
    assert watch.reason is None and watch.outside == 2
    assert watch.check(out, 6) and watch.reason.startswith("cycle 6 (t = 0.0000 s): speed "
                                                           "estimate |ω̂| = 11 rad/s beyond 10")
    with pytest.raises(ValueError, match="cycles = 0"):
        DivergenceWatch(env, cycles=0)


def test_simulate_sampled_summary_shows_delay(tmp_path):
    rms = {}
    for delay in ("0", "1"):
        out = tmp_path / f"d{delay}"
        assert main(["simulate", "--period", "1ms", "--delay", delay, "--flux", "true",
                     "--no-identify", "--out", str(out)]) == 0
        s = json.loads((out / "summary.json").read_text())
        assert s["configuration"]["delay"] == int(delay)
        rms[delay] = s["speed_error"]["rms"]
    assert rms["0"] < rms["1"]


@pytest.mark.parametrize(
    ("args", "needle"),
    [
        (["simulate", "--profile", "nope.toml"], "nope.toml"),
        (["simulate", "--period", "1 parsec"], "--period '1 parsec' is not a duration"),
        (["simulate", "--law", "full-order", "--drive", "ideal"],
         "--drive-mode voltage or current-loop"),
        (["simulate", "--period", "continuous", "--drive", "current-loop"], "continuous time"),
        (["simulate", "--out", "/proc/forbidden/run"], "cannot write the run directory"),
        (["simulate", "--k-w", "-3"], "must be > 0"),
        (["simulate", "--k-w-t-max", "0"], "--k-w-t-max 0.0: give a positive number"),
        (["profile", "check", "README.md"], "README.md"),
    ],
)
def test_bad_input_gives_one_paragraph_and_status_2(args, needle):
    r = run_cli(*args)
    assert r.returncode == 2, r.stderr
    assert needle in r.stderr
    assert "Traceback" not in r.stderr
    assert r.stderr.startswith("hil-gateway: error: ")


def test_bad_profile_names_file_and_key(tmp_path):
    bad = tmp_path / "bad.toml"
    bad.write_text((ROOT / "profiles" / "paper.toml").read_text().replace(
        "initial = 0.001", "initial = -0.2"))
    r = run_cli("simulate", "--profile", str(bad))
    assert r.returncode == 2
    assert str(bad) in r.stderr and "[flux]" in r.stderr
    assert "Traceback" not in r.stderr


def test_profile_check_prints_set_points_and_demand():
    r = run_cli("profile", "check", "profiles/paper.toml")
    assert r.returncode == 0, r.stderr
    assert "valid" in r.stdout
    assert "1.16" in r.stdout and "200" in r.stdout
    assert "peak" in r.stdout.lower()


def test_profile_plot_writes_png(tmp_path):
    out = tmp_path / "paper.png"
    r = run_cli("profile", "plot", "profiles/paper.toml", "-o", str(out))
    assert r.returncode == 0, r.stderr
    assert out.stat().st_size > 10_000
    assert out.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"


def test_help_explains_every_command():
    r = run_cli("--help")
    assert r.returncode == 0
    for cmd in ("simulate", "sim", "run", "profile"):
        assert cmd in r.stdout
    r = run_cli("simulate", "--help")
    assert "--setpoint-frame" in r.stdout and "continuous" in r.stdout


def test_sigterm_keeps_what_was_simulated(tmp_path):
    import signal
    import time

    out = tmp_path / "long"
    proc = subprocess.Popen([sys.executable, "-m", "gateway", "simulate", "--duration", "600s",
                             "--out", str(out)], cwd=ROOT, stdout=subprocess.PIPE,
                            stderr=subprocess.PIPE, text=True)
    try:
        deadline = time.monotonic() + 60
        while not out.exists() and time.monotonic() < deadline:
            time.sleep(0.1)
        time.sleep(2.0)
        proc.send_signal(signal.SIGTERM)
        _stdout, stderr = proc.communicate(timeout=60)
    finally:
        proc.kill()
    assert proc.returncode == 130, stderr
    assert "stopped early" in stderr and "Traceback" not in stderr
    summary = json.loads((out / "summary.json").read_text())
    assert summary["stopped_early"].startswith("SIGTERM received")
    sig = read_csv(out / "signals.csv")
    assert 0.5 < sig["t"][-1] < 600.0
    assert len(sig["t"]) == round(sig["t"][-1] / 1e-3)
