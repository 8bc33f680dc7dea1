"""The benchmarks (bench/) report a run that did not complete as a failed measurement: the
reason in place of the figure, ``null`` and ``"failed"`` in the JSON line, exit status 1,
no traceback (bench/_common.py). The benchmarks run as scripts, in a subprocess, as a user
runs them. No figure is compared with a threshold: only what is reported and how.
"""

from __future__ import annotations

import importlib.util
import json
import math
import os
import re
import subprocess
import sys
import textwrap
from pathlib import Path

import pytest

from dbc.errors import UserError

ROOT = Path(__file__).resolve().parents[1]
BENCH = ROOT / "bench"


@pytest.fixture
def bench(tmp_path):
    """Run ``bench/<script> args`` (or ``python -c code args``) from the repository, its run
    directories (tempfile) under the test's tmp_path."""
    env = {**os.environ, "TMPDIR": str(tmp_path)}

    def run(*args: str, code: str | None = None, timeout: float = 120
            ) -> subprocess.CompletedProcess[str]:
        cmd = [sys.executable, "-c", code, *args] if code else [sys.executable, *args]
        return subprocess.run(cmd, cwd=ROOT, capture_output=True, text=True, timeout=timeout,
                              stdin=subprocess.DEVNULL, env=env)

    return run


def _json_line(stdout: str) -> dict:
    """The --json line: the last line of stdout."""
    return json.loads(stdout.strip().splitlines()[-1])


def _common():
    """bench/_common.py as a module (not through sys.path: bench/ is not a package)."""
    spec = importlib.util.spec_from_file_location("bench_common_under_test",
                                                  BENCH / "_common.py")
    assert spec and spec.loader
    mod = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(mod)
    return mod


@pytest.fixture
def tripping_drive(tmp_path) -> Path:
    """The emulator's drive profile with the drive's watch of the gateway's heartbeat at
    1 ms: the gateway sends it every 10 ms at the fastest, so the drive trips (EMCY 0x8130,
    heartbeat of the master lost) within the first cycles of every run, lockstep or not."""
    text = (ROOT / "gateway" / "drives" / "emulator.toml").read_text()
    text, n = re.subn(r"(?m)^heartbeat_timeout_ms\s*=\s*\d+", "heartbeat_timeout_ms = 1", text)
    assert n == 1, "no heartbeat_timeout_ms in gateway/drives/emulator.toml"
    path = tmp_path / "trip.toml"
    path.write_text(text)
    return path


def test_bench_loop_reports_a_run_stopped_early_as_failed(bench, tripping_drive):
    """bench_loop.py whose runs all stop in their first cycles (before: FileNotFoundError
    for signals.csv): every figure FAILED with the drive's reason, the JSON line with null
    figures and their reasons, exit status 1, no traceback."""
    p = bench("bench/bench_loop.py", "--quick", "--repeats", "1", "--realtime-seconds", "1",
               "--drive", str(tripping_drive), "--json")
    out = p.stdout + p.stderr
    assert p.returncode == 1, out
    assert "Traceback" not in out, out
    for transport in ("virtual", "inprocess"):
        line = next(ln for ln in p.stdout.splitlines() if ln.startswith(f"[{transport}]"))
        assert "FAILED: lockstep run 1 of 1: run stopped in cycle" in line, line
        assert "EMCY 0x8130" in line, line
    assert "real time at 1 ms for 1 s: FAILED: real-time run of 1 s: " in p.stdout, p.stdout
    data = _json_line(p.stdout)
    for name in ("virtual_cycles_per_s", "inprocess_cycles_per_s",
                 "inprocess_reaction_p99_us"):
        assert data[name] is None
        assert "EMCY 0x8130" in data["failed"][name], data["failed"]
    assert data["realtime_cycles"] is None and data["failed"]["realtime_cycles"]
    assert data["python"] and data["where"]  # what is not a failed figure is kept


def test_bench_loop_quick_run_gives_its_figures(bench):
    """A normal quick run (lockstep only: the real-time run's outcome depends on the host's
    load, and its failure path is the test above): exit 0, the documented keys, nothing
    failed."""
    p = bench("bench/bench_loop.py", "--quick", "--repeats", "1", "--realtime-seconds", "0",
               "--json")
    out = p.stdout + p.stderr
    assert p.returncode == 0, out
    assert "FAILED" not in out and "Traceback" not in out, out
    data = _json_line(p.stdout)
    assert data["failed"] == {}
    for t in ("virtual", "inprocess"):
        assert data[f"{t}_cycles_per_s"] > 0
        assert len(data[f"{t}_cycles_per_s_runs"]) == 1
        assert data[f"{t}_reaction_cycles"] == 2500  # the paper scenario at 1 ms
        assert math.isfinite(data[f"{t}_reaction_p99_us"])
    assert "realtime_cycles" not in data


def test_bench_motulator_quick_run_gives_its_ratio(bench):
    """`--quick --json`: ours measured and the headline ``ratio`` key — ours over motulator
    in its default configuration, or null with the reason in ``motulator_note`` where
    motulator is not installed (it is not a dependency: installed by hand)."""
    p = bench("bench/bench_motulator.py", "--quick", "--t-sim", "0.02", "--repeats", "1",
              "--json")
    out = p.stdout + p.stderr
    assert p.returncode == 0, out
    assert "Traceback" not in out, out
    data = _json_line(p.stdout)
    assert data["failed"] == {} and data["ours_x_real_time"] > 0
    if data["motulator"] is None:
        assert data["ratio"] is None and "install" in data["motulator_note"]
    else:
        assert data["ratio"] == data["motulator_250us_ZOH_ours_over_it"] > 0


def test_bench_twoproc_relaxed_drive_profile_loads(tmp_path):
    """``bench_twoproc.py --no-deadlines`` runs the gateway with a copy of the emulator's
    profile whose drive deadlines are at their longest: the gateway must accept it (a 0,
    which the profile refuses as switching the watch off, made the real-time run exit 2)."""
    from gateway.drive_profile import load_drive_profile

    sys.path.insert(0, str(BENCH))
    try:
        import bench_twoproc
    finally:
        sys.path.remove(str(BENCH))
    path = tmp_path / "drive.toml"
    path.write_text(bench_twoproc.relaxed_drive())
    prof = load_drive_profile(path)
    assert (prof.heartbeat_timeout_ms, prof.rpdo_timeout_ms) == (65535, 65535)
    assert prof.drive_heartbeat_timeout_ms == 5000


PLANT_FAILS = textwrap.dedent("""
    import sys
    sys.path.insert(0, "bench")
    sys.argv[0] = "bench/bench_plant.py"
    from plant.drive import Drive

    real = Drive.advance

    def advance(self, T, T_L):
        if self.params.mode == "voltage":
            raise FloatingPointError("the model blew up (injected)")
        return real(self, T, T_L)

    Drive.advance = advance
    import bench_plant

    sys.exit(bench_plant.main(sys.argv[1:]))
""")


def test_bench_plant_mode_that_raises_is_failed_and_the_others_measured(bench):
    """An exception from the system under measurement (here the drive model in one mode)
    fails that mode's figures only; the other modes are measured."""
    p = bench("--quick", "--json", code=PLANT_FAILS)
    out = p.stdout + p.stderr
    assert p.returncode == 1, out
    assert "Traceback" not in out, out
    row = next(ln for ln in p.stdout.splitlines() if ln.startswith("voltage"))
    assert "FAILED: FloatingPointError: the model blew up (injected)" in row
    data = _json_line(p.stdout)
    assert data["voltage_x_real_time"] is None and data["voltage_us_per_step"] is None
    assert set(data["failed"]) == {"voltage_x_real_time", "voltage_us_per_step"}
    assert data["ideal_x_real_time"] > 0 and data["current-loop_x_real_time"] > 0
    assert data["target_met"] in (True, False)


def test_common_turns_what_the_run_raises_into_a_reason():
    c = _common()
    with (pytest.raises(c.RunError, match=r"^the run: cannot read it; give another$"),
          c.the_run("the run")):
        raise UserError("cannot read it;\n give another")
    with pytest.raises(c.RunError, match=r"^FileNotFoundError: \[Errno 2\] x$"), c.the_run():
        raise FileNotFoundError(2, "x")
    with pytest.raises(KeyboardInterrupt), c.the_run():
        raise KeyboardInterrupt
    with pytest.raises(c.RunError, match="run stopped in cycle 0: EMCY 0x8130"):
        c.require_completed({"run": {"stop": "DRIVE_FAULT", "stop_cycle": 0,
                                     "stop_reason": "EMCY 0x8130: heartbeat lost"}})
    with pytest.raises(c.RunError, match=r"wrote no signals\.csv$"):
        c.require_completed({"run": {"stop": "END_OF_PROFILE"}}, Path("/nonexistent"),
                            ["signals.csv"])


def test_common_figures_json_and_exit_status(capsys):
    c = _common()
    fig = c.Figures(python="3")
    fig.put("a", math.inf)
    assert fig.measure("b", lambda: 2.0) == 2.0
    assert fig.exit_status() == 0 and fig.exit_status(ok=False) == 1

    def fails():
        raise c.RunError("stopped early")

    assert fig.measure("c", fails) is None
    assert fig.show("b", "{:.1f}") == "2.0" and fig.show("c") == "FAILED: stopped early"
    fig.emit("-")
    assert json.loads(capsys.readouterr().out) == {
        "python": "3", "a": "inf", "b": 2.0, "c": None, "failed": {"c": "stopped early"}}
    assert fig.exit_status() == 1
