"""A scenario run for a drive test: in this process (`simulate`), over CANopen against the
emulated drive in this process (`sim`, lockstep on the in-process bus), or over SocketCAN
against the emulated drive in another process (`hil-plant run` on a vcan), returned as a
:class:`DriveRun`: its signals by column, its summary and why it stopped.

The pytest plugin's ``drive_run`` fixture (:mod:`gateway.pytest_plugin`) calls
:func:`run_scenario`; the checks a drive engineer makes of a run are in
:mod:`gateway.drivecheck`.
"""

from __future__ import annotations

import os
import signal
import subprocess
import sys
import time
from collections.abc import Iterator, Mapping
from contextlib import contextmanager, suppress
from dataclasses import dataclass
from enum import StrEnum
from pathlib import Path
from typing import Any

import numpy as np

from dbc.motor import MotorParams, ParamsError
from gateway.errors import UserError
from gateway.stop import StopReason


class Where(StrEnum):
    """Where a scenario runs."""

    SIMULATE = "simulate"  #: the sampled loop in this process, no CAN (fastest)
    SIM = "sim"  #: over CANopen against the emulated drive in this process, lockstep
    VCAN = "vcan"  #: over SocketCAN against `hil-plant run` in another process, lockstep


class MissingColumnError(KeyError):
    """A column the run's signals do not have; the message names those they have."""

    def __str__(self) -> str:
        return str(self.args[0])


@dataclass(frozen=True)
class DriveRun:
    """One run of a scenario: ``signals`` (a pandas DataFrame when pandas is installed, else
    a dict of numpy arrays by column name: the columns of signals.csv, docs/outputs.md),
    ``summary`` (as summary.json), the run directory ``out`` (None: a simulation that wrote
    nothing), and ``where`` it ran."""

    where: Where
    signals: Any
    summary: dict[str, Any]
    out: Path | None = None

    @property
    def stop(self) -> StopReason:
        """Why it stopped (``END_OF_PROFILE`` when it ran to the end)."""
        return StopReason[self.summary["run"]["stop"]]

    @property
    def stop_reason(self) -> str:
        """The stop in words (summary.json's ``run.stop_reason``)."""
        return str(self.summary["run"].get("stop_reason", self.stop.value))

    @property
    def exit_status(self) -> int:
        """What the command would have exited with: 0, 1 (a fault, a file not written) or
        130 (interrupted)."""
        return int(self.summary["run"]["exit_status"])

    @property
    def columns(self) -> list[str]:
        return [str(c) for c in self.signals]

    def column(self, name: str) -> np.ndarray:
        """One signal as a float array; :class:`MissingColumnError` naming the columns there are."""
        if name not in self.columns:
            raise MissingColumnError(f"no column {name!r} in this run's signals; it has "
                                f"{', '.join(self.columns)}")
        return np.asarray(self.signals[name], dtype=float)

    def describe(self) -> str:
        """One line for failure messages: where, what, how it ended, where its files are."""
        conf = self.summary.get("configuration", {})
        name = (conf.get("controller") or {}).get("name", "paper")
        files = f"; its files: {self.out}" if self.out else ""
        return (f"{self.where} run of {conf.get('profile', '?')} (controller {name}, "
                f"{conf.get('drive_mode', '?')} drive): {self.stop.name}, exit status "
                f"{self.exit_status}{files}")


def signal_table(sig: Mapping[str, np.ndarray]) -> Any:
    """The columns as a pandas DataFrame when pandas is installed, else as they are (a dict
    of numpy arrays by name)."""
    try:
        import pandas
    except ImportError:
        return dict(sig)
    return pandas.DataFrame({name: np.asarray(v) for name, v in sig.items()})


def run_scenario(profile: str | Path = "quick", *, where: Where | str = Where.SIMULATE,
                 out: Path | None = None, controller: str = "paper",
                 controller_params: Mapping[str, Any] | None = None,
                 plant: str | None = None, duration: float | str | None = None,
                 drive_mode: str | None = None, period: str = "1ms",
                 motor: str | Path | None = None, windows: str = "auto",
                 channel: str = "vcan0", node: int = 1, start_timeout: float = 60.0,
                 **options: Any) -> DriveRun:
    """Run reference ``profile`` (a file, or a shipped name: paper, quick, …) ``where``.

    ``out``: the run directory to write (signals.csv, summary.json, figures, bus log);
    needed over a bus, optional for a simulation (None: nothing written). ``controller``
    and ``controller_params``: as ``--controller`` and its parameters; ``plant``: a plant
    scenario (``--plant``: a file or a shipped name such as "rs+10"); ``duration``: s or
    "0.2s" (None: the profile's); ``drive_mode``: as ``--drive-mode`` (None: the
    controller's); ``period``: "1ms", "250us"; ``motor``: the controller's motor file
    (``--motor``; over vcan the emulated drive's too); ``windows``: the metric windows
    (``--windows``). Over vcan: the SocketCAN ``channel``, the drive's ``node``, and how long
    `hil-plant run` may take to be ready (``start_timeout``, s). ``options``: further fields
    of :class:`gateway.spec.RunSpec` (``law``, ``flux``, ``estimator``, ``gains``,
    ``identify``, ``load``, ``timing``, ``delay``, ``setpoint_frame``, …).

    Bad input raises :class:`UserError` with what to change; a run that stops early is
    returned (its :attr:`DriveRun.stop` says why)."""
    from gateway import report, session
    from gateway.reference import ProfileError, resolve_profile
    from gateway.sim import load_scenario

    where = _where(where)
    try:
        ref = resolve_profile(profile)
    except ProfileError as exc:
        raise UserError(str(exc)) from exc
    scenario = load_scenario(plant) if plant is not None else None
    if scenario is not None and scenario.bus_faults and where is Where.VCAN:
        raise UserError(f"plant {plant!r} injects bus faults ([[bus.fault]]), which act on "
                        "the bus between the gateway and the emulated drive in this process, "
                        "or on simulate's PDO link: run it with where='sim' or 'simulate' "
                        "(over vcan: `hil-gateway bridge`)")
    spec = _spec(where, controller, controller_params, scenario, duration, drive_mode, period,
                 options)
    motor_params = _motor(motor)
    win = report.profile_windows(ref, windows)
    if where is Where.SIMULATE:
        output = None if out is None else session.Output(str(out), "simulate")
        result = session.run(spec, ref, motor_params, output=output, windows=win)
        return DriveRun(where, signal_table(result.sig), result.summary, result.out)
    if out is None:
        raise UserError(f"a {where} run writes its bus log: give it a run directory (out=...)")
    out = Path(out)
    if out.is_dir() and any(out.iterdir()):
        raise UserError(f"{str(out)!r} exists and is not empty: a run never overwrites "
                        "another; give a new directory")
    if where is Where.SIM:
        from gateway.sim import sim_target

        target = sim_target(spec.drive_mode, scenario, ref.load,
                            plant_label=f"plant {plant!r}")
        result = session.run(spec, ref, motor_params, target=target,
                             output=session.Output(str(out), "sim"), windows=win)
    else:
        with _emulator_process(channel, node, plant, motor, out, start_timeout):
            result = session.run(spec, ref, motor_params, target=_vcan_target(spec, channel,
                                                                              node),
                                 # the directory holds the emulator's output already
                                 output=session.Output(str(out), "run", force=True),
                                 windows=win)
    return DriveRun(where, signal_table(result.sig or {}), result.summary, result.out)


def _where(where: Where | str) -> Where:
    try:
        return Where(where)
    except ValueError:
        raise UserError(f"where={where!r}: give {', '.join(repr(w.value) for w in Where)} "
                        "(in this process, over the in-process bus, over vcan)") from None


def _spec(where: Where, controller: str, params: Mapping[str, Any] | None, scenario: Any,
          duration: float | str | None, drive_mode: str | None, period: str,
          options: dict[str, Any]) -> Any:
    """The run's :class:`RunSpec`, with the CLI's defaults for what is not given."""
    from dbc.timing import Sampling
    from gateway.control.interface import ControllerChoice, controller_factory
    from gateway.sim import emulator_rate
    from gateway.spec import RunSpec, default_drive_mode, default_load
    from gateway.units import parse_duration, parse_period

    controller_factory(controller)  # found, or a UserError naming those registered
    law = options.get("law", "current-fed")
    mode = drive_mode or default_drive_mode(controller, law)
    load = options.pop("load", None) or default_load(scenario)
    sampling = Sampling(parse_period(period, "period", emulator_rate()),
                        options.pop("delay", 1), options.pop("setpoint_frame", "dq"))
    if isinstance(duration, str):
        duration = parse_duration(duration, "duration")
    return RunSpec(controller=ControllerChoice(controller, dict(params or {})),
                   drive_mode=mode, sampling=sampling, duration=duration, load=load,
                   plant=scenario if where is not Where.VCAN else None, **options)


def _motor(motor: str | Path | None) -> MotorParams:
    if motor is None:
        return MotorParams.paper()
    try:
        return MotorParams.from_toml(motor)
    except ParamsError as exc:
        raise UserError(f"{exc}; the paper's motor, gateway/motors/paper.toml, is a "
                        "template to copy") from exc


def _vcan_target(spec: Any, channel: str, node: int) -> Any:
    """The emulator's built-in profile for the run's drive mode, on SocketCAN ``channel``."""
    from dbc.bus import BusConfig, open_bus
    from gateway.drive_profile import emulator_profile, load_drive_profile
    from gateway.runner import BusTarget

    cfg = BusConfig("socketcan", channel)

    def open_buses(*_: Any) -> tuple[Any, str, Any]:
        bus = open_bus(cfg)
        return bus, cfg.label(), bus.shutdown

    drive = load_drive_profile(None, emulator_profile(spec.drive_mode))
    return BusTarget(drive, open_buses, node=node, command="run")


@contextmanager
def _emulator_process(channel: str, node: int, plant: str | None, motor: str | Path | None,
                      out: Path, start_timeout: float) -> Iterator[subprocess.Popen]:
    """`hil-plant run` on SocketCAN ``channel`` in a process of its own (its own session),
    its output in ``out``/plant.out and plant.err, until its ready line; stopped with
    SIGTERM (then SIGKILL) when the block ends, whatever happened."""
    out.mkdir(parents=True, exist_ok=True)
    cmd = [sys.executable, "-m", "plant", "run", "-i", "socketcan", "-c", channel,
           "--node", str(node)]
    cmd += ["--plant", plant] if plant else []
    cmd += ["--motor", str(motor)] if motor else []
    stdout, stderr = out / "plant.out", out / "plant.err"
    with stdout.open("wb") as fo, stderr.open("wb") as fe:
        proc = subprocess.Popen(cmd, stdin=subprocess.DEVNULL, stdout=fo, stderr=fe,
                                env={**os.environ, "PYTHONUNBUFFERED": "1"},
                                start_new_session=True)
    try:
        deadline = time.monotonic() + start_timeout
        while "ready" not in stdout.read_text(errors="replace"):
            if proc.poll() is not None or time.monotonic() > deadline:
                why = (f"ended with status {proc.returncode}" if proc.poll() is not None
                       else f"was not ready within {start_timeout:g} s")
                raise UserError(f"the emulated drive (`{' '.join(cmd[2:])}`) {why}: "
                                f"{stderr.read_text(errors='replace').strip()[-800:]}")
            time.sleep(0.05)
        yield proc
    finally:
        _stop(proc)


def _stop(proc: subprocess.Popen) -> None:
    """SIGTERM to the emulator's process group (it switches its power stage off and
    exits), SIGKILL if it has not ended within 15 s."""
    with suppress(ProcessLookupError, PermissionError):
        os.killpg(proc.pid, signal.SIGTERM)
    try:
        proc.wait(15)
    except subprocess.TimeoutExpired:
        with suppress(ProcessLookupError, PermissionError):
            os.killpg(proc.pid, signal.SIGKILL)
        proc.wait(5)
