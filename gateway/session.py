"""One home for a run: :func:`run` carries out a :class:`gateway.spec.RunSpec`.

In this process (`simulate`: the sampled loop or the paper's continuous time,
:mod:`gateway.simulate`) or over a bus (`sim`, `run`: :func:`gateway.runner.run_gateway`
against a :class:`gateway.runner.BusTarget`), it ends the same way: the record's columns,
with the emulator's full-resolution truth merged in where a `sim` run has it, the metrics
computed once from them, and ``signals.csv``, the figures and ``summary.json`` written
once each by :func:`gateway.results.write_results`. SIGINT/SIGTERM stop the run (the bus's
shutdown path first) and never lose its files. The command line, the benchmarks and the
tests all come here; the CLI only parses and prints.
"""

from __future__ import annotations

import sys
import threading
import time
from collections.abc import Callable
from contextlib import AbstractContextManager, nullcontext
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Protocol

import numpy as np

from dbc.modes import DriveMode
from dbc.motor import MotorParams
from dbc.signals import SETPOINT_MESSAGE
from gateway import report
from gateway.errors import UserError
from gateway.figures import Worker
from gateway.guard import DivergenceWatch, profile_envelope
from gateway.reference import Profile
from gateway.results import merge_truth, write_results
from gateway.rundir import run_dir
from gateway.spec import RunSpec
from gateway.stop import StopReason, StopSignals

Progress = Callable[[float], None]

@dataclass(frozen=True)
class Output:
    """Where a run writes: ``dir`` (``--out``; None: a new ``runs/<time>-<name>``),
    ``force`` (reuse a non-empty ``dir``), ``figures`` (draw them; ``--no-figures``: no)."""

    dir: str | None = None
    name: str = "run"
    force: bool = False
    figures: bool = True


@dataclass
class RunResult:
    """What a run leaves: the record's columns (None: no cycle ran), the summary (as in
    summary.json), the run directory (None: nothing written) and the files written there."""

    sig: dict[str, np.ndarray] | None
    summary: dict[str, Any]
    out: Path | None = None
    files: list[Path] = field(default_factory=list)

    @property
    def exit_status(self) -> int:
        return int(self.summary["run"]["exit_status"])

    @property
    def write_errors(self) -> list[str]:
        return list(self.summary.get("write_errors", []))


class Watcher(Protocol):
    """Something that watches a run while it happens (the live scope,
    :class:`gateway.scope.feed.ScopeFeed`): given the record before the first cycle, asked
    for its own account for summary.json, told the summary at the end."""

    def attach(self, record: report.Record) -> None: ...

    def stats(self) -> dict[str, Any]: ...

    def finish(self, summary: dict[str, Any]) -> None: ...


def run(spec: RunSpec, profile: Profile, motor: MotorParams, *, target: Any = None,
        output: Output | None = None, windows: tuple = report.DEFAULT_WINDOWS,
        progress: Progress | None = None, signals: StopSignals | None = None,
        watcher: Watcher | None = None, figure_worker: Worker | None = None) -> RunResult:
    """Run ``spec`` on ``profile`` with the controller's ``motor``: in this process
    (``target`` None) or against ``target`` (:class:`gateway.runner.BusTarget`) on its bus.

    ``output``: the run directory to make and write (None: a simulation writes nothing and
    returns the record and summary; a bus run needs one, for its bus log). ``windows``: the
    metric windows (:func:`gateway.report.profile_windows`). ``progress``: called with the
    fraction done. ``signals``: the stop requests (SIGINT/SIGTERM, installed here when
    this is the main thread; a caller may request a stop through it too). ``watcher``: a
    live view of the run (:class:`Watcher`); its account goes into summary.json as
    ``scope``. ``figure_worker``: the figures are drawn by this
    :class:`gateway.drawing.FigureWorker` (the caller started it early and closes it); else
    a simulation with files starts one, and a bus run draws them itself."""
    signals = signals or StopSignals()
    if target is None:
        if output is None:
            return _simulate(spec, profile, motor, None, windows, progress, signals, watcher)
        with run_dir(output.dir, output.name, output.force) as out:
            return _simulate(spec, profile, motor, out, windows, progress, signals, watcher,
                             figure_worker, output.figures)
    if output is None:
        raise ValueError("a bus run writes its bus log: give it an Output")
    with run_dir(output.dir, output.name, output.force, (spec.bus_log,)) as out:
        return _on_bus(spec, profile, motor, target, out, windows, progress, signals,
                       watcher, output.figures, figure_worker)


def _writing_politely(signals: StopSignals) -> None:
    """From here on a signal does not interrupt: the run's files are written first."""
    signals.shutting_down = True
    signals.on_stop = lambda reason: print(
        f"\n{reason}: writing the run's files first, please wait", file=sys.stderr,
        flush=True)


# --------------------------------------------------------------------------- in process


def _watched(summary: dict[str, Any], watcher: Watcher | None) -> None:
    """The watcher's account into the summary, and the summary to the watcher."""
    if watcher is not None:
        summary["scope"] = watcher.stats()
        watcher.finish(summary)


def _simulate(spec: RunSpec, profile: Profile, motor: MotorParams, out: Path | None,
              windows: tuple, progress: Progress | None, signals: StopSignals,
              watcher: Watcher | None = None, worker: Worker | None = None,
              figures: bool = True) -> RunResult:
    """The simulation, its summary and (``out``) its files. The signal handlers stay
    installed until every file is written: a second Ctrl-C (or one that comes while the
    figures are drawn) must not lose the run's files. With files to write, a worker
    process gets ready to draw the figures while the simulation runs
    (:class:`gateway.drawing.FigureWorker`)."""
    from gateway.drawing import FigureWorker

    stop = threading.Event()
    signals.on_stop = lambda reason: stop.set()
    watch = DivergenceWatch(profile_envelope(profile, motor, spec.gains.i_max))
    installed: AbstractContextManager[Any] = (signals.installed() if out is not None
                                              else nullcontext())
    own = (FigureWorker.start() if out is not None and figures and worker is None
           else None)
    with installed, own or nullcontext():
        return _simulated(spec, profile, motor, out, windows, progress, signals, watcher,
                          stop, watch, worker or own, figures)


def _simulated(spec: RunSpec, profile: Profile, motor: MotorParams, out: Path | None,
               windows: tuple, progress: Progress | None, signals: StopSignals,
               watcher: Watcher | None, stop: threading.Event, watch: DivergenceWatch,
               worker: Worker | None, figures: bool) -> RunResult:
    """:func:`_simulate`'s run and results, with its handlers installed."""
    from gateway import simulate

    t0 = time.perf_counter()
    try:
        rec = simulate.run(profile, motor, spec, progress, stop, watch,
                           None if watcher is None else watcher.attach)
    except ValueError as exc:  # also a plant scenario's error (ScenarioError)
        raise UserError(f"the simulation could not run: {exc}") from exc
    _writing_politely(signals)
    wall = time.perf_counter() - t0
    if not len(rec):
        raise UserError(f"the simulation stopped before its first period "
                        f"({signals.reason})", exit_code=130)
    sig = rec.arrays()
    truth = _link_truth(spec, sig, rec.link) if rec.link is not None else None
    summary = _simulation_summary(spec, profile, sig, windows, watch,
                                  signals.reason if stop.is_set() else "", wall)
    if rec.link is not None:
        _link_summary(summary, rec.link, truth or report.TRUTH_MODEL,
                      signals.reason if stop.is_set() else "")
    if rec.identification is not None:
        summary["identification"] = rec.identification
    _watched(summary, watcher)
    if out is None:
        return RunResult(sig, summary)
    files = _write_simulation(out, spec, sig, summary, figures, worker)
    return RunResult(sig, summary, out, files)


def _write_simulation(out: Path, spec: RunSpec, sig: dict[str, np.ndarray],
                      summary: dict[str, Any], figures: bool = True,
                      worker: Worker | None = None) -> list[Path]:
    """A simulation's files, as `simulate` writes them (the figures by ``worker`` when
    given, else in this process)."""
    return write_results(out, sig, summary, figures=figures,
                         limits=_figure_limits(spec, True), delay_s=_delay_s(spec),
                         worker=worker)


def save(result: RunResult, spec: RunSpec, output: Output) -> RunResult:
    """A simulation run without a directory (``output`` None in :func:`run`) written
    afterwards into one, as `simulate` would have written it: a campaign keeps the
    directories of its points that failed, and only those."""
    if result.sig is None:
        raise ValueError("a run without a record has nothing to write")
    with run_dir(output.dir, output.name, output.force) as out:
        files = _write_simulation(out, spec, result.sig, result.summary)
    return RunResult(result.sig, result.summary, out, files)


def _simulation_summary(spec: RunSpec, profile: Profile, sig: dict[str, np.ndarray],
                        windows: tuple, watch: DivergenceWatch, stopped: str, wall: float
                        ) -> dict[str, Any]:
    """summary.json of a simulation: the metrics against the model's own truth, the
    quantisation, why it ended, the configuration."""
    summary: dict[str, Any] = report.metrics(sig, windows=windows)
    summary["truth"] = report.TRUTH_MODEL
    sampled = spec.sampling is not None
    summary["quantisation"] = report.quantisation(
        spec.quantize and sampled,
        SETPOINT_MESSAGE[spec.sampling.setpoint_frame] if spec.sampling else None,
        "--no-quantize" if sampled else "continuous time: no bus")
    if stopped:
        summary["stopped_early"] = f"{stopped} at t = {sig['t'][-1]:.3f} s"
    ended = (StopReason.DIVERGED if watch.reason else StopReason.INTERRUPTED
             if stopped else StopReason.END_OF_PROFILE)
    summary["run"] = {"stop": ended.name,
                      "stop_reason": watch.reason or summary.get("stopped_early")
                      or ended.value,
                      "exit_status": ended.exit_status, "cycles": len(sig["t"])}
    summary["configuration"] = {"command": "simulate", "profile": profile.source,
                                **spec.describe()}
    summary["wall_time_s"] = wall
    return summary


def _link_truth(spec: RunSpec, sig: dict[str, np.ndarray], link: Any) -> str:
    """A simulation with bus faults: its record's truth (TPDO3's) replaced by the drive
    model's full resolution cycle by cycle, as `sim` does (:func:`merge_truth`); what the
    truth rests on."""
    from gateway.simulate import emulated_drive

    assert spec.sampling is not None
    _, lsb = _speed_signal(emulated_drive(spec))
    merged = merge_truth(sig, link.truth, spec.sampling.period, lsb)
    return report.TRUTH_MODEL if merged == report.TRUTH_FULL else merged


def _link_summary(summary: dict[str, Any], link: Any, truth: str, stopped: str) -> None:
    """A simulation with bus faults: its loop's account as a bus run has it (``run``), how
    often each fault acted (``bus_faults``), and the frames before a stop."""
    from gateway.runner import run_account

    stats = link.stats
    stop = stats.stop or StopReason.INTERRUPTED
    message = stopped if stop is StopReason.INTERRUPTED and stopped else stats.stop_reason
    summary["truth"] = truth
    summary["run"] = run_account(stats, stop, message, stop.exit_status, 0.0)
    if stop not in (StopReason.END_OF_PROFILE, StopReason.INTERRUPTED):
        summary["run"]["frames_before_stop"] = [
            {"time": t, "dir": d, "cob_id": f"0x{c:03X}", "data": data}
            for t, d, c, data in link.recent]
    summary["bus_faults"] = link.bus_faults


def _delay_s(spec: RunSpec) -> float:
    """The time from a sample to the interval its setpoints act on (Fig. 3's shift), s."""
    return 0.0 if spec.sampling is None else spec.sampling.delay * spec.sampling.period


# --------------------------------------------------------------------------------- bus


def _on_bus(spec: RunSpec, profile: Profile, motor: MotorParams, target: Any, out: Path,
            windows: tuple, progress: Progress | None, signals: StopSignals,
            watcher: Watcher | None = None, figures: bool = True,
            worker: Worker | None = None) -> RunResult:
    """The loop on the target's bus (opened and closed here), then its results, written
    once with the emulator's truth merged first (the figures: ``figures`` and the drive
    sends the truth they need; drawn by ``worker`` where there is one)."""
    from gateway.runner import RUNNING_MARKER, run_gateway

    with signals.installed():
        done = run_gateway(target, profile, motor, spec, out, progress, signals,
                           None if watcher is None else watcher.attach)
        _writing_politely(signals)
        summary = done.summary
        drive = target.drive
        summary["quantisation"] = report.quantisation(True, drive.setpoints, dbc=drive.dbc,
                                                      messages=drive.messages)
        speed = maps_speed(drive)
        if done.sig is not None and speed:  # tracking errors need the drive's speed
            where, lsb = _speed_signal(drive)
            if drive.truth:
                on_bus = (report.TRUTH_TPDO3 if where == f"{drive.truth}.w_m"
                          else f"{where}, ω to {lsb:.3g} rad/s; ψr: {drive.truth}")
                summary["truth"] = merge_truth(done.sig, target.truth, spec.period, lsb,
                                               on_bus)
            else:  # a standard drive: its velocity actual value, no flux
                summary["truth"] = (f"{where}, the drive's measured speed, ω to {lsb:.3g} "
                                    "rad/s; no rotor flux")
            summary.update(report.metrics(done.sig, windows))
        elif done.sig is not None and _in_process_truth(done.sig, target, spec.period):
            speed = True  # a drive that sends no truth (a lean mapping), `sim`'s own record
            summary["truth"] = report.TRUTH_FULL
            summary.update(report.metrics(done.sig, windows))
        _watched(summary, watcher)
        files = write_results(out, done.sig, summary, figures=figures and speed,
                              limits=_figure_limits(spec, drive.emulator),
                              delay_s=_delay_s(spec), errors=summary.pop("write_errors", []),
                              worker=worker)
        if out / "summary.json" in files:
            (out / RUNNING_MARKER).unlink(missing_ok=True)
    return RunResult(done.sig, summary, out, files)


def _in_process_truth(sig: dict[str, np.ndarray], target: Any, period: float) -> bool:
    """`sim` against a drive profile that sends no truth (no ``w_m``): the emulator's
    full-resolution state of every cycle, recorded in process, put into ``sig``; False
    when there is none (a real drive) or a cycle lacks it."""
    truth = getattr(target, "truth", None)
    if truth is None or not len(sig["t"]):
        return False
    full = truth.columns(np.rint(sig["t"] / period))
    if full is None:
        return False
    sig.update(full)
    return True


def has_truth(target: Any) -> bool:
    """The run will have the speed its figures and metrics need: the drive maps it
    (:func:`maps_speed`), or `sim` records the emulator's truth in process."""
    return maps_speed(target.drive) or getattr(target, "truth", None) is not None


def maps_speed(drive: Any) -> bool:
    """The drive's process data carry its speed (role ``w_m``: the emulator's truth, or a
    standard drive's velocity actual value)."""
    from gateway.process_data import process_data

    return "w_m" in process_data(drive).roles


def _speed_signal(drive: Any) -> tuple[str, float]:
    """The message and signal of the drive's DBC that carry its speed (role ``w_m``), and
    its resolution, rad/s."""
    from gateway.process_data import process_data

    pdo = process_data(drive).pdo("w_m")
    k = pdo.roles.index("w_m")
    return f"{pdo.name}.{pdo.signals[k][0]}", pdo.codec.signals[k].factor


def _figure_limits(spec: RunSpec, emulated: bool) -> dict[str, float]:
    """The limits Fig. 3 draws: the controller's current limit, and where the drive is the
    emulated one (``emulated``; simulated or over the bus) its voltage limit (none for an
    ideal current source) and over-current trip; a real drive's are its own."""
    i_trip = u_lim = None
    if emulated:
        from gateway.sim import emulator_limits

        i_trip, u_lim = emulator_limits()
    return report.limits_for(spec.gains, None if spec.drive_mode is DriveMode.IDEAL else u_lim,
                             i_trip)
