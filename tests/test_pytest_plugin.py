"""The pytest plugin (gateway/pytest_plugin.py): the drive_run fixture, the checks of
gateway/drivecheck.py with their messages, the needs_vcan marker, and the example a user
copies (examples/test_my_drive.py), run by plain pytest from another directory."""

from __future__ import annotations

import importlib.metadata
import math
import os
import subprocess
import sys
import tomllib
from pathlib import Path

import numpy as np
import pytest

from gateway.drivecheck import (
    assert_current_peak_below,
    assert_no_fault,
    assert_overshoot_below,
    assert_settles,
    assert_steady_state_error,
    overshoot,
    settling_time,
    steady_state_error,
)
from gateway.drivetest import DriveRun, MissingColumnError, Where, run_scenario, signal_table
from gateway.errors import UserError
from gateway.pytest_plugin import VCAN_HINT, require_vcan
from gateway.vcan import vcan_problem

ROOT = Path(__file__).resolve().parents[1]
PLUGIN = "gateway.pytest_plugin"


def _synthetic(t: np.ndarray, y: np.ndarray, ref: np.ndarray) -> DriveRun:
    summary = {"run": {"stop": "END_OF_PROFILE", "exit_status": 0},
               "configuration": {"profile": "synthetic"}}
    return DriveRun(Where.SIMULATE, {"t": t, "w_m": y, "w_ref": ref}, summary)


# ------------------------------------------------------------------ the checks, exactly


def test_settling_time_of_a_first_order_step():
    """y = 1 − e^(−t/τ) enters the 2 % band for good at τ·ln 50."""
    tau = 0.02
    t = np.arange(0.0, 0.5, 1e-4)
    run = _synthetic(t, np.where(t > 0, 1 - np.exp(-t / tau), 0.0),
                     np.where(t > 0, 1.0, 0.0))
    ts = settling_time(run, 0.0)
    assert ts == pytest.approx(tau * math.log(50), abs=2e-4)
    assert assert_settles(run, within=0.1, after=0.0) == ts
    with pytest.raises(AssertionError) as exc:
        assert_settles(run, within=0.05, after=0.0)
    assert str(exc.value).startswith(f"w_m settled {ts:.4g} s after t = 0 s, not within "
                                     "0.05 s: it stays within ±0.02 (2 % of the +1 step of "
                                     "w_ref) of 1 only from")
    assert "run: simulate run of synthetic" in str(exc.value)


def test_overshoot_of_an_underdamped_step():
    """A second-order step response overshoots by e^(−πζ/√(1−ζ²))."""
    zeta, wn = 0.3, 60.0
    wd = wn * math.sqrt(1 - zeta ** 2)
    t = np.arange(0.0, 0.6, 1e-5)
    y = 100 * (1 - np.exp(-zeta * wn * t) * (np.cos(wd * t) + zeta * wn / wd * np.sin(wd * t)))
    run = _synthetic(t, y, np.where(t > 0, 100.0, 0.0))
    over, at = overshoot(run, 0.0)
    assert over == pytest.approx(100 * math.exp(-math.pi * zeta / math.sqrt(1 - zeta ** 2)),
                                 rel=1e-4)
    assert at == pytest.approx(math.pi / wd, abs=1e-4)
    assert assert_overshoot_below(run, 40.0, after=0.0) == over
    with pytest.raises(AssertionError, match=r"w_m overshoots the \+100 step of w_ref \(to "
                                             r"100\) by 37.2 % at t = 0.05"):
        assert_overshoot_below(run, 30.0, after=0.0)
    with pytest.raises(ValueError, match=r"w_ref does not step between 0\.3 and"):
        overshoot(run, 0.3)  # nothing to overshoot: the reference is flat there


def test_a_signal_that_never_settles_is_named_with_where_it_ends():
    t = np.linspace(0.0, 1.0, 101)
    run = _synthetic(t, 0.5 * np.ones_like(t), np.where(t > 0.1, 1.0, 0.0))
    assert settling_time(run, 0.1) is None
    with pytest.raises(AssertionError, match=r"w_m never settled after t = 0.1 s: at t = 1 s "
                                             r"it is 0.5, outside ±0.02"):
        assert_settles(run, within=1.0, after=0.1)


# ------------------------------------------------------------------- runs, honestly


@pytest.fixture(scope="module")
def ifoc(tmp_path_factory):
    """The built-in baseline over CANopen on profiles/quick.toml."""
    return run_scenario("quick", where="sim", controller="ifoc",
                        out=tmp_path_factory.mktemp("ifoc") / "run")


def test_the_checks_measure_what_the_run_recorded(ifoc):
    sig = {name: ifoc.column(name) for name in ("t", "w_m", "w_ref", "i_sa", "i_sb")}
    sel = (sig["t"] >= 0.30) & (sig["t"] <= 0.34)
    e = sig["w_m"][sel] - sig["w_ref"][sel]
    st = assert_steady_state_error(ifoc, 0.5, window=(0.30, 0.34))
    assert st.max_abs == np.max(np.abs(e)) and st.mean == np.mean(e)
    assert assert_current_peak_below(ifoc, 15.0) == ifoc.summary["peak_current"]
    assert_no_fault(ifoc)
    assert ifoc.stop.name == "END_OF_PROFILE" and ifoc.exit_status == 0
    assert ifoc.out is not None and (ifoc.out / "bus.blf").is_file()


def test_the_checks_fail_with_what_happened_and_where_the_files_are(ifoc):
    st = steady_state_error(ifoc, (0.30, 0.34))
    with pytest.raises(AssertionError) as exc:
        assert_steady_state_error(ifoc, 0.1, window=(0.30, 0.34))
    text = str(exc.value)
    assert text.startswith(f"w_m − w_ref reaches {st.max_abs:.4g} at t = {st.t_max:.4g} s in "
                           "[0.3, 0.34] s, not below 0.1 (mean ")
    assert "sim run of profiles/quick.toml (controller ifoc, ideal drive): END_OF_PROFILE, " \
           f"exit status 0; its files: {ifoc.out}" in text
    with pytest.raises(AssertionError, match=r"the stator current \|i_s\| reaches 9.6\d+ A at "
                                             r"t = 0.2\d+ s, not below 9 A"):
        assert_current_peak_below(ifoc, 9.0)
    with pytest.raises(MissingColumnError, match="no column 'w_hat' in this run's signals; "
                                                 "it has t, w_ref"):
        ifoc.column("w_hat")  # ifoc has no speed estimate


def test_a_run_that_diverged_is_a_fault(tmp_path):
    run = run_scenario("zero-speed", plant="rs+10", estimator="drift-free",
                       discretisation="euler", identify=False)
    assert run.out is None  # a simulation without out= writes nothing
    with pytest.raises(AssertionError, match=r"the run did not go cleanly: it stopped early: "
                                             r"DIVERGED \(cycle \d+ "):
        assert_no_fault(run)
    assert run.exit_status == 1


def test_drive_run_runs_in_the_tests_directory(drive_run, tmp_path):
    run = drive_run("quick", duration="0.1s", controller="ifoc")
    assert run.out == tmp_path / "run1-simulate" and (run.out / "summary.json").is_file()
    pandas = pytest.importorskip("pandas")  # the test extra installs it
    assert isinstance(run.signals, pandas.DataFrame)
    assert len(run.signals) == 100 and list(run.signals)[:3] == ["t", "w_ref", "psi_ref"]
    second = drive_run("quick", duration="0.1s", where="sim", controller="ifoc")
    assert second.out == tmp_path / "run2-sim"
    assert np.array_equal(second.column("w_m"), run.column("w_m"))  # lockstep = simulate


def test_without_pandas_the_signals_are_numpy_arrays(monkeypatch):
    monkeypatch.setitem(sys.modules, "pandas", None)  # import pandas raises ImportError
    table = signal_table({"t": np.arange(3.0), "w_m": np.ones(3)})
    assert isinstance(table, dict) and set(table) == {"t", "w_m"}
    run = run_scenario("quick", duration="0.05s")
    assert isinstance(run.signals, dict) and isinstance(run.signals["w_m"], np.ndarray)
    assert run.column("t")[-1] == pytest.approx(0.05)


def test_bad_scenarios_are_named(tmp_path):
    with pytest.raises(UserError, match=r"no shipped profile of that name \(shipped: paper, "
                                        r"quick"):
        run_scenario("quik")
    with pytest.raises(UserError, match="where='bus': give 'simulate', 'sim', 'vcan'"):
        run_scenario("quick", where="bus")
    with pytest.raises(UserError, match="give it a run directory"):
        run_scenario("quick", where="sim")
    with pytest.raises(UserError, match=r"nope: no controller of that name"):
        run_scenario("quick", controller="nope")
    with pytest.raises(UserError, match=r"plant 'bus-drop' injects bus faults .* run it with "
                                        r"where='sim' or 'simulate'"):
        run_scenario("quick", where="vcan", plant="bus-drop")


@pytest.mark.parametrize("where", ["sim", "simulate"])
def test_a_bus_fault_scenario_runs_and_the_run_says_what_was_injected(drive_run, where):
    from gateway.drivecheck import assert_no_fault

    run = drive_run("quick", where=where, plant="bus-babble")
    assert run.stop.name == "FOREIGN_WRITER" and run.exit_status == 1
    injected = run.summary["bus_faults"]
    assert [f["kind"] for f in injected] == ["babble"] and injected[0]["acted"] > 0
    with pytest.raises(AssertionError, match="it stopped early: FOREIGN_WRITER"):
        assert_no_fault(run)


# ---------------------------------------------------------------------- vcan marker


def test_without_vcan_a_test_skips_with_the_reason_and_fails_in_ci(monkeypatch):
    monkeypatch.delenv("CI", raising=False)
    why = vcan_problem("nocan9")  # this host's reason: no SocketCAN, or no such interface
    assert why is not None
    with pytest.raises(pytest.skip.Exception) as exc:
        require_vcan("nocan9")
    assert str(exc.value) == f"{why}; {VCAN_HINT}"
    monkeypatch.setenv("CI", "true")
    with pytest.raises(pytest.fail.Exception, match=r"CI=true and no usable nocan9: .*sudo "
                                                    r"modprobe vcan"):
        require_vcan("nocan9")


def _pytest(args: list[str], cwd: Path, env: dict[str, str]) -> subprocess.CompletedProcess:
    return subprocess.run([sys.executable, "-m", "pytest", "-p", "no:cacheprovider", *args],
                          cwd=cwd, env=env, capture_output=True, text=True, timeout=600)


def _env_with_the_entry_point(tmp_path: Path) -> dict[str, str]:
    """This environment, with the plugin's entry point (pyproject.toml's pytest11) visible
    to importlib.metadata even where the package was installed before it had one: a
    distribution's metadata of that entry point alone on PYTHONPATH."""
    env = {k: v for k, v in os.environ.items() if k != "CI"}
    installed = any(ep.value == PLUGIN for ep in importlib.metadata.entry_points(
        group="pytest11"))
    if not installed:
        project = tomllib.loads((ROOT / "pyproject.toml").read_text())["project"]
        entry = project["entry-points"]["pytest11"]
        meta = tmp_path / "site" / "can_drive_hil_plugin-0.dist-info"
        meta.mkdir(parents=True)
        (meta / "METADATA").write_text("Metadata-Version: 2.1\nName: can-drive-hil-plugin\n"
                                       "Version: 0\n")
        (meta / "entry_points.txt").write_text(
            "[pytest11]\n" + "".join(f"{k} = {v}\n" for k, v in entry.items()))
        env["PYTHONPATH"] = os.pathsep.join(
            [str(meta.parent), str(ROOT), *filter(None, [env.get("PYTHONPATH")])])
    return env


def test_the_marker_skips_with_the_reason_or_fails_under_ci(tmp_path):
    (tmp_path / "test_m.py").write_text(
        "import pytest\n\n@pytest.mark.needs_vcan('nocan9')\ndef test_m():\n    pass\n")
    env = _env_with_the_entry_point(tmp_path)
    p = _pytest(["-rs", "-vv", "test_m.py"], tmp_path, env)
    assert p.returncode == 0 and "1 skipped" in p.stdout, p.stdout + p.stderr
    assert f"{vcan_problem('nocan9')}; create it: sudo modprobe vcan" in p.stdout
    p = _pytest(["test_m.py"], tmp_path, {**env, "CI": "true"})
    assert p.returncode == 1 and "1 error" in p.stdout, p.stdout + p.stderr  # in its setup
    assert "CI=true and no usable nocan9" in p.stdout


def test_the_example_passes_with_plain_pytest_from_another_directory(tmp_path):
    example = ROOT / "examples" / "test_my_drive.py"
    p = _pytest(["-q", str(example)], tmp_path, _env_with_the_entry_point(tmp_path))
    assert p.returncode == 0 and "1 passed" in p.stdout, p.stdout + p.stderr


def test_the_readme_shows_the_example_as_shipped():
    text = (ROOT / "README.md").read_text(encoding="utf-8")
    example = (ROOT / "examples" / "test_my_drive.py").read_text(encoding="utf-8")
    body = example[example.index("from gateway"):]
    assert body in text
    assert len([line for line in body.splitlines() if line.strip()]) <= 10


def test_loading_the_plugin_imports_nothing_heavy():
    """It loads in every pytest run once installed: only its own module, no numpy, no
    python-can, nothing of the project's run machinery."""
    code = ("import sys, gateway.pytest_plugin; "
            "print(sorted(m for m in sys.modules if m.split('.')[0] in "
            "{'numpy', 'pandas', 'can', 'canopen', 'cantools', 'matplotlib', 'scipy', "
            "'gateway', 'plant', 'dbc'}))")
    p = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True,
                       env={**os.environ, "PYTHONPATH": str(ROOT)}, timeout=120)
    assert p.returncode == 0, p.stderr
    assert p.stdout.strip() == "['gateway', 'gateway.pytest_plugin']"


# ---------------------------------------------------------------------------- over vcan


@pytest.mark.vcan
@pytest.mark.needs_vcan("vcan0")
def test_drive_run_over_vcan_sends_what_sim_sends(drive_run):
    """`hil-plant run` in another process on vcan0, the gateway in this one: the same
    setpoints, bit for bit, as over the in-process bus."""
    from gateway.drivecheck import assert_no_fault

    run = drive_run("quick", where="vcan", controller="ifoc", duration="0.2s")
    assert_no_fault(run)
    assert run.summary["configuration"]["bus"] == "socketcan:vcan0"
    assert (run.out / "plant.out").read_text().startswith("hil-plant: node 1 ready")
    sim = drive_run("quick", where="sim", controller="ifoc", duration="0.2s")
    for name in ("i_sd_ref", "i_sq_ref", "eps_0", "w_0", "T_ref"):
        assert np.array_equal(run.column(name), sim.column(name)), name
    # a `run` directory makes a report like any other
    from gateway.cli import main

    assert main(["report", str(run.out)]) == 0
    page = (run.out / "report.html").read_text(encoding="utf-8")
    assert "over CANopen (socketcan, lockstep)" in page and "median, µs" in page
