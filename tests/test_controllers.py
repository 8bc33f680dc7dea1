"""The controller interface (docs/controllers.md): a controller of a user's own package runs in
`simulate`, `sim` and `run` like the paper's laws, found by its registered name or as
module:Class, with its own signals in signals.csv, its figure, and `compare`; the built-in
baseline (ifoc); and the refusals (unknown name, bad parameters, continuous time)."""

from __future__ import annotations

import json
import sys
from pathlib import Path

import pytest
from gw_support import gateway_run

from gateway.cli import main
from gateway.control.interface import CONTROLLER_GROUP, registered
from gateway.report import read_csv

ROOT = Path(__file__).resolve().parents[1]
EXAMPLE = ROOT / "examples" / "pi_foc"
GAINS = str(EXAMPLE / "gains.toml")
QUICK = str(ROOT / "profiles" / "quick.toml")


def _summary(out: Path) -> dict:
    return json.loads((out / "summary.json").read_text())


@pytest.fixture
def example_on_path(monkeypatch):
    """The example's source on sys.path, as PYTHONPATH would put it (module:Class)."""
    monkeypatch.syspath_prepend(str(EXAMPLE / "src"))


def _own_signals_recorded(out: Path, names: tuple[str, ...]) -> dict:
    sig = read_csv(out / "signals.csv")
    for name in names:
        assert name in sig, f"{name} not in signals.csv"
    assert (out / "fig4_controller.png").stat().st_size > 10_000
    return sig


def test_the_built_ins_and_the_example_are_registered():
    """paper and ifoc by can-drive-hil's own pyproject.toml; pi-foc by the example's, which
    scripts/bootstrap --test installs (pip install -e examples/pi_foc)."""
    names = registered()
    assert {"paper", "ifoc"} <= set(names)
    assert "pi-foc" in names, (f"the example is not installed: pip install -e {EXAMPLE} "
                               f"(it registers pi-foc in {CONTROLLER_GROUP})")


def test_a_users_controller_by_name_in_simulate(tmp_path):
    out = tmp_path / "sim"
    assert main(["simulate", "--controller", "pi-foc", "--controller-params", GAINS,
                 "--out", str(out)]) == 0
    s = _summary(out)
    assert s["configuration"]["controller"] == {"name": "pi-foc",
                                                "params": {"kp": 100.0, "ki": 2500.0,
                                                           "i_max": 15.0}}
    sig = _own_signals_recorded(out, ("torque_demand", "flux_model"))
    # it controls: the paper scenario's speed within a few rad/s, its flux model near ψ*
    assert s["speed_error"]["rms"] < 2.0 and abs(s["speed_error"]["final"]) < 0.1
    assert abs(sig["flux_model"][-1] - sig["psi_ref"][-1]) < 0.05
    assert "estimation_error" not in s  # it has no speed estimate


def test_sim_over_canopen_equals_simulate_for_any_controller(tmp_path, example_on_path):
    """module:Class, not installed: the bus loop and the simulation give the same numbers."""
    a, b = tmp_path / "simulate", tmp_path / "sim"
    args = ["--controller", "pi_foc:PiSpeedFoc", "--reference", QUICK]
    assert main(["simulate", *args, "--out", str(a)]) == 0
    assert main(["sim", *args, "--out", str(b)]) == 0
    sa, sb = read_csv(a / "signals.csv"), read_csv(b / "signals.csv")
    for name in ("w_m", "i_sd_ref", "i_sq_ref", "eps_0", "w_0", "torque_demand", "flux_model"):
        assert (sa[name] == sb[name]).all(), name
    _own_signals_recorded(b, ("torque_demand", "flux_model"))


def test_run_against_the_emulator_with_a_users_controller(emulator, tmp_path):
    emu = emulator()
    out = tmp_path / "run"
    rc = gateway_run(emu, out, "--controller", "pi-foc", "--reference", QUICK,
                     "--duration", "0.5s")
    assert rc == 0
    s = _summary(out)
    assert s["run"]["stop_reason"] == "end of the profile"
    assert s["configuration"]["controller"]["name"] == "pi-foc"
    sig = _own_signals_recorded(out, ("torque_demand", "flux_model"))
    assert "statusword" in sig  # the bus's columns follow the controller's


def test_compare_puts_a_users_controller_beside_the_papers(tmp_path, capsys):
    paper, mine = tmp_path / "paper", tmp_path / "mine"
    assert main(["simulate", "--reference", QUICK, "--out", str(paper)]) == 0
    assert main(["simulate", "--controller", "pi-foc", "--reference", QUICK,
                 "--out", str(mine)]) == 0
    capsys.readouterr()
    assert main(["compare", str(paper), str(mine), "-o", str(tmp_path / "c.png")]) == 0
    out = capsys.readouterr().out
    assert "controller.name: paper | pi-foc" in out
    assert "estimation error rms" in out and "—" in out  # pi-foc has no estimate
    assert "torque_demand final / rms" in out and "flux_model final / rms" in out
    assert (tmp_path / "c.png").stat().st_size > 10_000


def test_ifoc_baseline_in_simulate_and_sim(tmp_path):
    a, b = tmp_path / "simulate", tmp_path / "sim"
    assert main(["simulate", "--controller", "ifoc", "--out", str(a)]) == 0
    assert main(["sim", "--controller", "ifoc", "--out", str(b)]) == 0
    sa, sb = _summary(a), _summary(b)
    assert sa["speed_error"]["rms"] == sb["speed_error"]["rms"]  # bit for bit
    # a PI speed loop without load feed-forward: the 5.8 N·m steps cost a few rad/s
    assert sa["speed_error"]["rms"] < 1.0 and abs(sa["speed_error"]["final"]) < 0.05
    _own_signals_recorded(a, ("T_ref", "w_slip", "psi_r_mod_hat", "w_int"))


def test_paper_by_name_is_the_default_bit_for_bit(tmp_path):
    a, b = tmp_path / "default", tmp_path / "named"
    args = ["--reference", QUICK]
    assert main(["simulate", *args, "--out", str(a)]) == 0
    assert main(["simulate", *args, "--controller", "paper", "--out", str(b)]) == 0
    assert (a / "signals.csv").read_bytes() == (b / "signals.csv").read_bytes()


@pytest.mark.parametrize("args, words", [
    (["--controller", "nope"], ["no controller of that name", "ifoc", "paper"]),
    (["--controller", "no_such_module:X"], ["cannot import 'no_such_module'"]),
    (["--controller", "json:NoSuchThing"], ["json has no 'NoSuchThing'"]),
    (["--controller", "ifoc", "--controller-params", "PARAMS"],
     ["controller 'ifoc' refused", "unknown parameter(s) gain"]),
    (["--controller", "ifoc", "--controller-params", "MISSING"], ["cannot read it"]),
    (["--controller", "paper", "--controller-params", "PARAMS"],
     ["from the command line"]),
    (["--controller", "ifoc", "--period", "continuous"], ["integrates the paper's laws only"]),
])
def test_refusals_are_one_paragraph_and_exit_2(tmp_path, capsys, args, words):
    params = tmp_path / "p.toml"
    params.write_text("gain = 3\n")
    args = [str(params) if a == "PARAMS" else str(tmp_path / "missing.toml")
            if a == "MISSING" else a for a in args]
    assert main(["simulate", *args, "--out", str(tmp_path / "o")]) == 2
    err = capsys.readouterr().err
    assert "Traceback" not in err
    for w in words:
        assert w in err, err


def test_a_controller_is_refused_by_a_drive_without_what_it_requires(foreign, tmp_path,
                                                                     capsys, monkeypatch):
    """A controller's ``requires`` (ifoc: the drive's speed) is checked against the drive
    profile before anything is written to the drive: here a role no drive has."""
    from gateway.control.ifoc import IndirectFieldOriented

    monkeypatch.setattr(IndirectFieldOriented, "requires", ("w_m", "torque_sensor"))
    drive, channel, profile = foreign(42)
    rc = main(["run", "-i", "virtual", "-c", channel, "--drive", str(profile),
               "--controller", "ifoc", "--reference", QUICK, "--out", str(tmp_path / "o")])
    err = capsys.readouterr().err
    assert rc == 2, err
    assert "torque_sensor" in err and "controller ifoc" in err and "Traceback" not in err
    assert drive.state != 0x0237  # never enabled


def test_the_interface_is_all_a_controller_needs():
    """A minimal controller (zero setpoints) written here passes the interface check; one
    without coast() is refused by name."""
    from gateway.control.interface import (
        Command,
        ControllerError,
        DriveController,
        check_controller,
    )

    class Idle:
        signals = ("nothing",)

        def step(self, refs, sample):
            return Command(0j, 0j, 0.0, 0.0, 0j, 0j, logged=(0.0,))

        def withhold(self):
            pass

        def coast(self):
            pass

    assert isinstance(Idle(), DriveController)
    check_controller(Idle(), "idle")

    class NoCoast:
        signals = ()

        def step(self, refs, sample):
            raise AssertionError

        def withhold(self):
            pass

    with pytest.raises(ControllerError, match="lacks coast"):
        check_controller(NoCoast(), "nocoast")
    assert "pi_foc" not in sys.modules or sys.modules["pi_foc"].__file__
