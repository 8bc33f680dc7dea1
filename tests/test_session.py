"""One home for a run: a RunSpec (gateway/spec.py) carried out by gateway.session.run, in
this process or on a bus, its results written once (README, "A run from Python")."""

from __future__ import annotations

import json
import re
from pathlib import Path

import pytest

from dbc.errors import UserError
from dbc.modes import DriveMode
from dbc.motor import MotorParams
from dbc.timing import Sampling
from gateway.control.interface import ControllerChoice
from gateway.drive_profile import load_drive_profile
from gateway.reference import load_profile
from gateway.runner import RUNNING_MARKER, BusTarget
from gateway.session import Output, run
from gateway.sim import open_emulator
from gateway.spec import RunSpec

ROOT = Path(__file__).resolve().parents[1]
QUICK = load_profile(str(ROOT / "profiles" / "quick.toml"))
MOTOR = MotorParams.paper()


def test_the_readme_example_runs_as_written(tmp_path, monkeypatch):
    text = (ROOT / "README.md").read_text(encoding="utf-8")
    section = text[text.index("### A run from Python"):]
    code = re.search(r"```python\n(.*?)```", section, re.S).group(1)
    monkeypatch.chdir(tmp_path)
    exec(compile(code, "README.md", "exec"), {})
    summary = json.loads((tmp_path / "runs" / "paper" / "summary.json").read_text())
    assert summary["run"]["stop"] == "END_OF_PROFILE"
    assert summary["speed_error"]["rms"] < 0.01  # the paper's law, sensorless (rad/s)


def test_a_simulation_without_output_writes_nothing(tmp_path, monkeypatch):
    monkeypatch.chdir(tmp_path)
    result = run(RunSpec(duration=0.2), QUICK, MOTOR)
    assert result.out is None and result.files == [] and not list(tmp_path.iterdir())
    assert len(result.sig["t"]) == 200 and result.exit_status == 0
    assert result.summary["configuration"]["command"] == "simulate"


def test_the_spec_refuses_what_cannot_run():
    with pytest.raises(UserError, match="continuous time"):
        RunSpec(sampling=None, controller=ControllerChoice("ifoc"))
    with pytest.raises(UserError, match="drive-mode"):
        RunSpec(law="full-order", drive_mode="ideal")
    with pytest.raises(UserError, match="bus log"):
        RunSpec(bus_log="bus.txt")
    with pytest.raises(UserError, match="max-missed"):
        RunSpec(max_missed=0)
    with pytest.raises(UserError, match="max-miss-rate"):
        RunSpec(max_miss_rate=1.5)
    with pytest.raises(UserError, match="unknown law"):
        RunSpec(law="fast")
    with pytest.raises(UserError, match="R_s adaptation"):  # it moves the flux read
        RunSpec(load="observed", estimator="rs-adaptive")


def test_the_spec_describes_itself_as_json():
    d = RunSpec(sampling=Sampling(2e-3, 0, "ab"), drive_mode=DriveMode.CURRENT_LOOP).describe()
    assert json.loads(json.dumps(d)) == d
    assert (d["period"], d["delay"], d["setpoint_frame"]) == (2e-3, 0, "ab")
    assert d["controller"] == {"name": "paper", "params": {}}
    assert d["plant_scenario"] is None


def test_a_bus_run_writes_each_file_once_and_leaves_no_marker(tmp_path):
    drive = load_drive_profile(None)
    opened: list[str] = []

    def open_bus(spec, motor, node):
        bus, label, close = open_emulator("inprocess", node, motor, spec.drive_mode)
        opened.append(label)
        return bus, label, close

    result = run(RunSpec(duration=0.2), QUICK, MOTOR, target=BusTarget(drive, open_bus),
                 output=Output(str(tmp_path / "o")))
    assert len(opened) == 1 and result.exit_status == 0, result.summary["run"]
    names = [p.name for p in result.files]
    assert names[0] == "signals.csv" and names[-1] == "summary.json"
    assert len(names) == len(set(names))
    assert not (tmp_path / "o" / RUNNING_MARKER).exists()
    assert (tmp_path / "o" / "bus.blf").stat().st_size > 0
    assert result.summary["run"]["cycles"] == 200
    assert result.summary["configuration"]["bus"] == opened[0]


def test_a_run_directory_deleted_during_the_run_is_made_again_and_said(tmp_path):
    """Deleted mid-run (a user's rm, a cleaner): the results are written into it made
    again, the lost bus log is named, exit 1; never a false "wrote"."""
    import shutil

    drive = load_drive_profile(None)
    out = tmp_path / "o"

    def open_bus(spec, motor, node):
        return open_emulator("inprocess", node, motor, spec.drive_mode)

    deleted = []

    def progress(fraction: float) -> None:
        if fraction > 0.3 and not deleted:
            shutil.rmtree(out)
            deleted.append(fraction)

    result = run(RunSpec(duration=0.4), QUICK, MOTOR, target=BusTarget(drive, open_bus),
                 output=Output(str(out)), progress=progress)
    assert deleted and result.exit_status == 1
    errors = result.summary["write_errors"]
    assert any("deleted or moved during the run" in e for e in errors), errors
    assert (out / "signals.csv").is_file() and (out / "summary.json").is_file()
    assert not (out / "bus.blf").exists()
    assert result.summary["run"]["bus_log_error"] == "deleted with the run directory"
    assert json.loads((out / "summary.json").read_text())["write_errors"] == errors
