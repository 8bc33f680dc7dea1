"""No input yields a silent wrong result, a traceback or a lost run directory.

Bad inputs are refused before anything runs (exit 2, one paragraph, no run directory);
run directories are unique and never overwritten; a long `simulate` stops on the first
SIGINT and keeps its files; metrics are fitted to the profile; `compare` compares runs.
"""

from __future__ import annotations

import json
import signal
import subprocess
import sys
import threading
import time
from pathlib import Path

import numpy as np
import pytest

from dbc.timing import SIM_HEARTBEAT_TIMEOUT_MS
from gateway import rundir
from gateway.cli import Progress, main
from gateway.errors import UserError
from gateway.reference import demand, load_profile, paper_profile, sample_times
from gateway.report import profile_windows, read_csv

ROOT = Path(__file__).resolve().parents[1]
PAPER = str(ROOT / "profiles" / "paper.toml")
QUICK = str(ROOT / "profiles" / "quick.toml")


def run_cli(*args: str, cwd: Path) -> subprocess.CompletedProcess:
    return subprocess.run([sys.executable, "-m", "gateway", *args], capture_output=True,
                          text=True, cwd=cwd, timeout=120)


HUGE = """\
[units]
time = "s"
speed = "rad/s"
flux = "Wb"
torque = "N*m"
[profile]
name = "huge"
duration = 1e7
[flux]
initial = 0.001
steps = [ { t = 0.0, value = 1.16, ramp = 0.3 } ]
[speed]
initial = 0.0
steps = [ { t = 0.32, value = 100.0, ramp = 0.18 } ]
"""


@pytest.mark.parametrize(
    ("args", "needle"),
    [
        (["simulate", "--period", "1"], "has no unit"),  # would have been a 1 s period
        (["simulate", "--period", "0.001"], "1ms if you meant 0.001 seconds"),
        (["simulate", "--period", "50us"], "outside 100us … 100ms"),
        (["simulate", "--period", "200ms"], "outside 100us … 100ms"),
        (["simulate", "--period", "150.5us"], "whole number of microseconds"),
        (["simulate", "--period", "137us"], "above its 100 kHz limit"),
        (["sim", "--period", "137us"], "above its 100 kHz limit"),
        (["sim", "--period", "1"], "has no unit"),
        (["sim", "--duration", "0.5ms"], "shorter than one period (1ms)"),
        (["simulate", "--duration", "0.5ms"], "shorter than one period (1ms)"),
        (["simulate", "--period", "continuous", "--duration", "0.1ms"],
         "shorter than one period"),
        (["simulate", "--duration", "1e9"], "--allow-long"),
        (["sim", "--duration", "1e7"], "--allow-long"),
        (["sim", "--node", "0"], "--node 0: a CANopen node id is 1..127"),
        (["sim", "--node", "128"], "1..127"),
        (["simulate", "--windows", "7,x"], "--windows"),
        (["reference", "plot", PAPER, "-o", "q.txt"], ".png, .svg, .pdf"),
        (["compare", "nothing-here"], "not a run directory"),
        (["simulate", "--period", "-1ms"], "--period '-1ms' must be greater than zero"),
        (["sim", "--duration", "-1s"], "--duration '-1s' must be greater than zero"),
        (["simulate", "--motor", "nope.toml"], "gateway/motors/paper.toml"),
        (["simulate", "--no-such-option"], "unrecognized arguments: --no-such-option (see "
                                           "hil-gateway --help)"),
    ],
)
def test_bad_input_is_refused_before_anything_runs(args, needle, tmp_path):
    r = run_cli(*args, cwd=tmp_path)
    assert r.returncode == 2, r.stderr
    assert r.stderr.startswith("hil-gateway: error: "), r.stderr
    assert needle in r.stderr
    assert "Traceback" not in r.stderr
    assert len(r.stderr.strip().splitlines()) == 1  # one paragraph
    assert not (tmp_path / "runs").exists()  # no (empty) run directory left behind
    assert not (tmp_path / "q.txt").exists()


def test_simulate_and_sim_give_the_same_answer_on_the_period():
    """One check for every command (dbc.timing.check_period)."""
    msgs = []
    for cmd in ("simulate", "sim", "run"):
        with pytest.raises(UserError) as exc:
            main([cmd, "--period", "137us", "--debug"] + (["-i", "virtual", "-c", "x"]
                                                          if cmd == "run" else []))
        msgs.append(str(exc.value))
    assert msgs[0] == msgs[1] == msgs[2]


def test_sim_runs_150us_like_simulate_bit_for_bit(tmp_path):
    """150 µs: the emulator steps at 20 kHz (a whole number of Hz, 3 steps a period), in
    `simulate` as on the bus; lockstep equals simulate, now also in the truth columns."""
    a, b = tmp_path / "simulate", tmp_path / "sim"
    assert main(["simulate", "--period", "150us", "--duration", "60ms", "--out", str(a)]) == 0
    # 765 us of frames a cycle do not fit 150 us on a 1 Mbit/s bus: sim's bus has no bit rate
    assert main(["sim", "--period", "150us", "--allow-bus-overload", "--duration", "60ms",
                 "--out", str(b)]) == 0
    sa, sb = read_csv(a / "signals.csv"), read_csv(b / "signals.csv")
    assert len(sa["t"]) == len(sb["t"]) == 400
    for col in ("t", "i_sa", "i_sb", "u_sa", "u_sb", "i_sd_ref", "i_sq_ref", "eps_0", "w_0",
                "w_hat", "w_m", "psi_r_mod", "T_e"):
        np.testing.assert_array_equal(sa[col], sb[col], err_msg=col)


def test_sim_gives_the_emulated_drive_a_one_second_watch_of_the_gateway(tmp_path):
    """`sim` runs the emulator in the gateway's interpreter: the drive's consumer heartbeat
    (0x1016 sub 1, written by the gateway over SDO) is 1 s, not the emulator profile's 300 ms,
    which a stalled process tripped before cycle 1 on busy hosts. Read from the run's bus log."""
    import can

    out = tmp_path / "sim"
    assert main(["sim", "--duration", "50ms", "--out", str(out)]) == 0
    writes = []
    with can.BLFReader(str(out / "bus.blf")) as log:
        for msg in log:
            d = bytes(msg.data)
            if 0x601 <= msg.arbitration_id <= 0x67F and d[:4] == b"\x23\x16\x10\x01":
                writes.append(int.from_bytes(d[4:8], "little"))
    assert writes, "no SDO download to 0x1016 sub 1 in the bus log"
    # configured as node 0x7F (the gateway) within 1000 ms; the shutdown switches it off (0)
    assert SIM_HEARTBEAT_TIMEOUT_MS == 1000
    assert writes[0] == (0x7F << 16) | 1000 and set(writes[1:]) <= {0}, writes


def test_sim_summary_uses_the_emulators_full_resolution_truth(tmp_path):
    out = tmp_path / "sim"
    assert main(["sim", "--duration", "0.4s", "--out", str(out)]) == 0
    s = json.loads((out / "summary.json").read_text())
    assert s["truth"] == "emulator, full resolution"
    sig = read_csv(out / "signals.csv")
    moving = sig["w_m"][np.abs(sig["w_m"]) > 1.0]
    assert moving.size > 10
    # not on TPDO3's 0.03125 rad/s grid: the model's own values
    assert np.any(np.abs(moving / 0.03125 - np.round(moving / 0.03125)) > 1e-3)
    assert s["speed_error"]["max"] == pytest.approx(np.max(np.abs(sig["w_m"] - sig["w_ref"])))
    q = s["quantisation"]
    assert q["applied"] and q["source"] == "dbc/drive.dbc"
    assert q["signals"]["w_m"] == {"message": "TPDO3", "lsb": 0.03125, "unit": "rad/s",
                                   "bits": 16, "signed": True, "min": -1024.0,
                                   "max": 1023.96875}
    assert q["signals"]["i_sa"]["lsb"] == 0.001 and q["signals"]["i_sa"]["unit"] == "A"
    assert q["signals"]["u_sa"]["lsb"] == 0.02 and q["signals"]["T_L"]["unit"] == "N·m"
    assert "RPDO2_AB" not in {v["message"] for v in q["signals"].values()}
    assert s["configuration"]["command"] == "sim"


def test_summary_table_states_truth_and_resolution(tmp_path, capsys):
    assert main(["simulate", "--duration", "50ms", "--out", str(tmp_path / "a")]) == 0
    out = capsys.readouterr().out
    assert "truth (ω, |ψr|): simulated motor state, full resolution" in out
    assert "bus resolution (1 LSB): i 1 mA, u 20 mV" in out


def test_a_closed_stdout_is_no_traceback(tmp_path):
    """`hil-gateway simulate | head -1`: the reader leaves; the run's files are written."""
    out = tmp_path / "piped"
    proc = subprocess.Popen([sys.executable, "-m", "gateway", "simulate", "--duration", "20ms",
                             "--out", str(out)], cwd=tmp_path, stdout=subprocess.PIPE,
                            stderr=subprocess.PIPE, text=True)
    proc.stdout.close()
    stderr = proc.stderr.read()
    assert proc.wait(timeout=120) == 1
    assert "Traceback" not in stderr and "BrokenPipe" not in stderr
    assert (out / "summary.json").exists()


# ------------------------------------------------------------------------ run directories


def test_default_run_directories_are_unique_in_the_same_second(tmp_path, monkeypatch):
    from datetime import datetime

    class Frozen(datetime):
        @classmethod
        def now(cls, tz=None):
            return datetime(2026, 1, 2, 3, 4, 5)

    monkeypatch.chdir(tmp_path)
    monkeypatch.setattr(rundir, "datetime", Frozen)
    for _ in range(3):
        assert main(["simulate", "--duration", "20ms"]) == 0
    dirs = sorted(p.name for p in (tmp_path / "runs").iterdir())
    assert dirs == ["20260102-030405-simulate-current-fed",
                    "20260102-030405-simulate-current-fed-2",
                    "20260102-030405-simulate-current-fed-3"]
    for d in dirs:
        assert (tmp_path / "runs" / d / "summary.json").exists()


def test_out_of_an_existing_run_is_refused_unless_force(tmp_path, capsys):
    out = tmp_path / "run"
    assert main(["simulate", "--duration", "20ms", "--out", str(out)]) == 0
    first = (out / "summary.json").read_text()
    assert main(["simulate", "--duration", "30ms", "--out", str(out)]) == 2
    assert "--force" in capsys.readouterr().err
    assert (out / "summary.json").read_text() == first  # untouched
    (out / "fig3_currents_voltages.png").unlink()
    (out / "fig3_currents_voltages.png").write_text("stale")
    assert main(["simulate", "--duration", "30ms", "--out", str(out), "--force"]) == 0
    assert len(read_csv(out / "signals.csv")["t"]) == 30
    assert (out / "fig3_currents_voltages.png").read_bytes()[:4] == b"\x89PNG"


def test_an_empty_existing_out_dir_is_used(tmp_path):
    out = tmp_path / "empty"
    out.mkdir()
    assert main(["simulate", "--duration", "20ms", "--out", str(out)]) == 0


def test_debug_goes_before_or_after_the_subcommand():
    for argv in (["--debug", "simulate", "--period", "1"], ["simulate", "--period", "1",
                                                             "--debug"]):
        with pytest.raises(UserError):
            main(argv)
    assert main(["simulate", "--period", "1"]) == 2


def test_progress_does_not_jump_to_100_percent_when_stopped(capsys):
    p = Progress("x", enabled=True)
    p(0.25)
    p.done(complete=False)
    err = capsys.readouterr().err
    assert "100.0%" not in err and "stopped at 25.0%" in err
    p = Progress("y", enabled=True)
    p(0.5)
    p.done()
    assert "100.0%" in capsys.readouterr().err


# ----------------------------------------------------------------------------- stopping


@pytest.mark.parametrize("period", ["1ms", "continuous"])
def test_simulate_stops_within_half_a_second_of_the_request(period):
    from gateway.simulate import run
    from gateway.spec import RunSpec

    if period == "continuous":
        cfg = RunSpec(sampling=None, duration=3600.0)
    else:
        from dbc.timing import Sampling

        cfg = RunSpec(sampling=Sampling(1e-3), duration=3600.0)
    stop = threading.Event()
    t_set: list[float] = []

    def request() -> None:
        t_set.append(time.perf_counter())
        stop.set()

    timer = threading.Timer(1.0, request)
    timer.start()
    from dbc.motor import MotorParams

    rec = run(paper_profile(), MotorParams.paper(), cfg, None, stop)
    latency = time.perf_counter() - t_set[0]
    assert latency < 5.0  # of a 3600 s run: the request is checked as it runs
    assert 0 < len(rec) < 3_600_000
    # a stop requested before the run starts ends it at once, with what exists
    rec = run(paper_profile(), MotorParams.paper(), cfg, None, stop)
    assert 0 < len(rec) <= 2


def test_sigint_keeps_the_files_and_figures_even_twice(tmp_path):
    out = tmp_path / "long"
    proc = subprocess.Popen([sys.executable, "-m", "gateway", "simulate", "--duration", "300s",
                             "--progress", "--out", str(out)], cwd=tmp_path,
                            stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    try:
        deadline = time.monotonic() + 60
        while not out.exists() and time.monotonic() < deadline:
            time.sleep(0.05)
        time.sleep(1.5)
        proc.send_signal(signal.SIGINT)
        time.sleep(0.3)
        proc.send_signal(signal.SIGINT)  # while the files are written
        _stdout, stderr = proc.communicate(timeout=120)
    finally:
        proc.kill()
    assert proc.returncode == 130, stderr
    assert "Traceback" not in stderr and "stopped early" in stderr
    assert "100.0%" not in stderr
    summary = json.loads((out / "summary.json").read_text())
    assert summary["stopped_early"].startswith("SIGINT received")
    for name in ("fig1_references.png", "fig2_errors.png", "fig3_currents_voltages.png"):
        assert (out / name).stat().st_size > 10_000, name
    sig = read_csv(out / "signals.csv")
    assert 0.2 < sig["t"][-1] < 300.0


# ------------------------------------------------------------------------------ metrics


def test_windows_follow_the_profile():
    w = profile_windows(load_profile(QUICK))
    assert [x[0] for x in w] == [0.0, 0.15, 0.35]
    assert w[0][2] == "start: flux 0.001 → 1.16 Wb"
    assert w[1][2] == "speed 0 → 100 rad/s" and w[2][2] == "load 0 → 2 N·m"
    assert [x[:2] for x in profile_windows(paper_profile(), "paper")] == [
        (0.0, 0.5), (0.5, 1.5), (1.5, float("inf"))]
    assert profile_windows(paper_profile(), "none") == ()
    assert [x[0] for x in profile_windows(paper_profile(), "1,2")] == [0.0, 1.0, 2.0]
    with pytest.raises(UserError):
        profile_windows(paper_profile(), "3")  # beyond the profile


def test_a_quick_profile_reports_no_window_it_does_not_have(tmp_path):
    out = tmp_path / "q"
    assert main(["simulate", "--profile", QUICK, "--out", str(out)]) == 0
    s = json.loads((out / "summary.json").read_text())
    froms = [w["from"] for w in s["speed_error"]["windows"]]
    assert froms == [0.0, 0.15, 0.35]  # no "[0.5, 1.5)" column for a 0.5 s profile
    assert s["speed_error"]["windows"][-1]["to"] == pytest.approx(0.5)
    out = tmp_path / "short"
    assert main(["simulate", "--duration", "0.4", "--out", str(out)]) == 0
    s = json.loads((out / "summary.json").read_text())
    assert [w["from"] for w in s["speed_error"]["windows"]] == [0.0, 0.32]


def test_paper_windows_on_request(tmp_path):
    out = tmp_path / "p"
    assert main(["simulate", "--windows", "paper", "--out", str(out)]) == 0
    s = json.loads((out / "summary.json").read_text())
    assert [w["from"] for w in s["flux_error"]["windows"]] == [0.0, 0.5, 1.5]


# ------------------------------------------------------------------------------ profiles


def test_a_huge_profile_is_checked_without_gigabytes(tmp_path):
    path = tmp_path / "huge.toml"
    path.write_text(HUGE)
    prof = load_profile(path)
    t = sample_times(prof)
    assert t.size < 300_000 and t[-1] == 1e7
    from dbc.motor import MotorParams

    d = demand(prof, MotorParams.paper())
    d_short = demand(paper_profile(), MotorParams.paper())
    assert d.i_s_peak == pytest.approx(d_short.i_s_peak, rel=1e-3)  # at 0.41 s in both
    r = run_cli("reference", "check", str(path), cwd=tmp_path)
    assert r.returncode == 0, r.stderr
    assert "peak current" in r.stdout


def test_profile_plot_default_goes_under_runs(tmp_path):
    r = run_cli("reference", "plot", PAPER, cwd=tmp_path)
    assert r.returncode == 0, r.stderr
    assert (tmp_path / "runs" / "profile-paper.png").stat().st_size > 10_000
    assert [p.name for p in tmp_path.iterdir()] == ["runs"]
    r = run_cli("reference", "plot", PAPER, "-o", "p.svg", cwd=tmp_path)
    assert r.returncode == 0 and (tmp_path / "p.svg").read_text().startswith("<?xml")


# ------------------------------------------------------------------------------- compare


def test_compare_prints_errors_side_by_side_and_writes_a_figure(tmp_path, capsys,
                                                                 monkeypatch):
    a, b = tmp_path / "a", tmp_path / "b"
    assert main(["simulate", "--profile", QUICK, "--out", str(a)]) == 0
    assert main(["simulate", "--profile", QUICK, "--period", "250us", "--out", str(b)]) == 0
    capsys.readouterr()
    before = sorted(p.name for p in a.iterdir())
    monkeypatch.chdir(tmp_path)
    assert main(["compare", str(a), str(b)]) == 0
    out = capsys.readouterr().out
    lines = out.splitlines()
    assert lines[0].split() == ["a", "b"]
    assert any(line.startswith("speed error max") for line in lines)
    assert "configuration differences:" in out and "period: 0.001 | 0.00025" in out
    assert (tmp_path / "compare.png").read_bytes()[:4] == b"\x89PNG"
    assert sorted(p.name for p in a.iterdir()) == before  # the run directory is untouched
    fig = tmp_path / "cmp.pdf"
    assert main(["compare", str(a), str(b), "-o", str(fig)]) == 0
    assert fig.read_bytes()[:4] == b"%PDF"


# ------------------------------------------------------------------------------- figures


def test_figure_titles_name_the_whole_configuration(tmp_path):
    from gateway.report import title_for

    out = tmp_path / "t"
    assert main(["simulate", "--duration", "20ms", "--period", "250us", "--setpoint-frame",
                 "ab", "--estimator", "drift-free", "--out", str(out)]) == 0
    conf = json.loads((out / "summary.json").read_text())["configuration"]
    assert title_for(conf) == ("current-fed law, estimated flux (drift-free), ideal drive, "
                               "T = 250 µs, delay 1, ab setpoints — simulate, INT16 bus signals")
    bus = {"law": "full-order", "flux": "true", "drive_mode": "voltage", "period": 0.001,
           "delay": 0, "setpoint_frame": "dq", "command": "sim", "bus": "inprocess:hil-sim",
           "timing": "realtime"}
    assert title_for(bus).endswith("delay 0, dq setpoints — over CANopen (inprocess, realtime)")
    assert "continuous time — simulate" in title_for({"law": "current-fed", "flux": "true",
                                                      "drive_mode": "ideal",
                                                      "period": "continuous",
                                                      "command": "simulate"})


def test_fig3_zooms_on_start_up_a_load_step_and_steady_state():
    from gateway.report import metrics, zoom_windows

    t = np.arange(1, 2501) * 1e-3
    ref = paper_profile().sample(t)
    sig = {"t": t, "w_ref": ref["w_ref"], "psi_ref": ref["psi_ref"], "T_L": ref["T_L"],
           "w_m": ref["w_ref"], "psi_r_mod": ref["psi_ref"], "w_hat": ref["w_ref"],
           "i_sa": t, "i_sb": t, "u_sa": t, "u_sb": t}
    windows = metrics(sig, profile_windows(paper_profile()))["speed_error"]["windows"]
    zooms = zoom_windows(sig, windows)
    assert [z[0] for z in zooms] == ["start-up", "load step at 0.5 s", "steady state (end)"]
    assert zooms[0][1:] == (pytest.approx(1e-3), pytest.approx(0.5))
    assert zooms[1][1] < 0.5 < zooms[1][2]
    assert zooms[2][2] == pytest.approx(2.5)


def test_compare_names_a_truncated_signals_file(tmp_path, capsys):
    run = tmp_path / "a"
    assert main(["simulate", "--profile", QUICK, "--out", str(run)]) == 0
    text = (run / "signals.csv").read_text()
    (run / "signals.csv").write_text(text[: len(text) // 2])  # cut inside a line
    capsys.readouterr()
    assert main(["compare", str(run), "-o", str(tmp_path / "c.png")]) == 2
    err = capsys.readouterr().err
    assert "signals.csv, line" in err and "truncated" in err and "Traceback" not in err, err


def test_after_a_run_the_cli_says_what_to_look_at_next(tmp_path, capsys):
    out = tmp_path / "o"
    assert main(["simulate", "--duration", "20ms", "--out", str(out)]) == 0
    line = capsys.readouterr().out.strip().splitlines()[-1]
    assert line.startswith("next:") and f"{out}/fig2_errors.png" in line
    assert f"hil-gateway compare {out}" in line
