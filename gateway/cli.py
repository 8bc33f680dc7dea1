"""`hil-gateway`: the command line of the gateway.

Every subcommand returns an exit status; bad input ends in one paragraph on stderr
(what failed, where, how to fix) and exit status 2, never a traceback unless --debug.
"""

from __future__ import annotations

import argparse
import contextlib
import logging
import math
import os
import re
import sys
import time
from collections.abc import Callable, Sequence
from dataclasses import dataclass, replace
from pathlib import Path
from typing import Any, NoReturn

from gateway.errors import UserError
from gateway.units import format_duration, parse_duration, parse_period

PROG = "hil-gateway"

EPILOG = """\
examples:
  hil-gateway sim                                   the loop over CANopen against the emulated
                                                    drive, in one process (no hardware)
  hil-gateway simulate --period continuous --flux true
                                                    the paper's section 6, continuous time
  hil-gateway simulate --period 1ms --setpoint-frame ab --delay 1
  hil-gateway run -i socketcan -c can0 --node 1     against a real drive or `hil-plant run`
  hil-gateway compare runs/A runs/B                  did my change help? errors side by side
  hil-gateway compare --baseline runs/A runs/B --tolerance examples/tolerance.toml --junit g.xml
                                                    the regression gate: exit 1 past a limit
  hil-gateway report runs/A                         runs/A/report.html: the run on one page
  hil-gateway sim --scope 8765                      watch the run live at http://127.0.0.1:8765/
  hil-gateway sim --plant bus-drop                  a bus fault injected (plant/scenarios/bus-*)
  hil-gateway profile new-drive --eds drive.eds --node 5 -o mydrive.toml
                                                    a drive profile from the drive's EDS
  hil-gateway campaign campaigns/motor-population.toml
                                                    1000 runs on a local Dask cluster
  hil-gateway reference check profiles/paper.toml
"""


# ----------------------------------------------------------------------------- helpers


def _check_duration(duration: float, step: float, what: str) -> int:
    """The number of periods (record steps) in ``duration``; refuses less than one."""
    if duration < step * (1 - 1e-9):
        raise UserError(f"{what} is shorter than one period ({format_duration(step)}): "
                        f"nothing would run; give at least {format_duration(step)}, or a "
                        "shorter --period")
    return max(1, round(duration / step))


def _load_profile(path: str | None, drive: Any = None):
    """``--reference``, checked against the emulated drive's limits (the PDO signals' ranges,
    its over-speed limit), or against none for another ``drive`` (its own are its own)."""
    from gateway.reference import ProfileError, load_profile, paper_profile

    limits = None if drive is None or drive.emulator else {}
    try:
        return paper_profile() if path is None else load_profile(path, limits)
    except ProfileError as exc:
        raise UserError(str(exc)) from exc


def _load_motor(path: str | None):
    from dbc.motor import MotorParams, ParamsError

    if path is None:
        return MotorParams.paper()
    try:
        return MotorParams.from_toml(path)
    except ParamsError as exc:
        raise UserError(f"{exc}; the paper's motor, gateway/motors/paper.toml, is a "
                        "template to copy") from exc


def _correction(args: argparse.Namespace, sampled: bool):
    """``--commissioning``: the motor file's sensor and inverter corrections
    (:class:`gateway.control.correction.SensorCorrection`), or None."""
    from dbc.motor import COMMISSIONING, ParamsError, commissioning
    from gateway.control.correction import SensorCorrection

    asked = getattr(args, "commissioning", None)
    if asked is False:
        return None
    how = ("give --motor FILE with a [commissioning] table (`hil-gateway identify -o FILE` "
           "writes one), or leave --commissioning out")
    if args.motor is None:
        if asked:
            raise UserError(f"--commissioning: no motor file; {how}")
        return None
    try:
        table = commissioning(args.motor)
        correction = SensorCorrection.from_table(table)
    except ParamsError as exc:
        raise UserError(str(exc)) from exc
    except (TypeError, ValueError) as exc:
        raise UserError(f"{args.motor} [{COMMISSIONING}]: {exc}; `hil-gateway identify -o "
                        "FILE` writes the table") from exc
    if correction is None:
        if asked:
            raise UserError(f"--commissioning: {args.motor} has no [{COMMISSIONING}] "
                            f"offsets, gain or dead time; {how}")
        return None
    if not sampled and not asked:
        return None  # continuous time runs the laws alone (the spec refuses an explicit ask)
    return correction


def _load_scenario(arg: str | None):
    """``--plant``: a scenario file or a shipped scenario's name; nominal when not given."""
    from gateway.sim import load_scenario

    return load_scenario(arg)


def _add_plant_option(p: argparse.ArgumentParser) -> None:
    p.add_argument("--plant", metavar="SCENARIO",
                   help="plant scenario (TOML file, or a shipped name such as rs+10): how the "
                        "emulated motor, sensors, inverter and load differ from the "
                        "controller's model; default: the nominal plant")


class Progress:
    """A one-line progress bar on stderr (only on a terminal, or when forced)."""

    def __init__(self, label: str, enabled: bool | None = None) -> None:
        self.label = label
        self.enabled = sys.stderr.isatty() if enabled is None else enabled
        self._t0 = time.perf_counter()
        self._last = -1.0

    def __call__(self, fraction: float) -> None:
        if not self.enabled or (fraction - self._last < 0.01 and fraction < 1.0):
            return
        self._last = fraction
        width = 30
        filled = round(width * fraction)
        elapsed = time.perf_counter() - self._t0
        sys.stderr.write(f"\r{self.label} [{'#' * filled}{'.' * (width - filled)}] "
                         f"{100 * fraction:5.1f}%  {elapsed:5.1f}s")
        sys.stderr.flush()

    def done(self, complete: bool = True) -> None:
        """End the line: at 100 % when the run is complete, else where it stopped."""
        if self.enabled:
            if complete:
                self(1.0)
            else:
                sys.stderr.write(f"  stopped at {100 * max(self._last, 0.0):.1f}%")
            sys.stderr.write("\n")
            sys.stderr.flush()


def _choices(enum: Any) -> list[str]:
    return [m.value for m in enum]


def _controller_choice(args: argparse.Namespace, given: dict[str, Any] | None = None) -> Any:
    """``--controller`` and ``--controller-params``, checked before anything runs: the
    controller is found (a registered name or module:Class) and its parameters read
    (``given``: the parameters themselves, in place of the file's)."""
    import tomllib

    from gateway.control.interface import ControllerChoice, controller_factory

    name = _controller_name(args)
    controller_factory(name)  # found, or a UserError naming what is registered
    params: dict[str, Any] = {}
    if given is not None:
        params = dict(given)
    elif args.controller_params:
        path = Path(args.controller_params)
        try:
            params = tomllib.loads(path.read_text(encoding="utf-8"))
        except OSError as exc:
            why = exc.strerror or exc
            raise UserError(f"--controller-params {path}: cannot read it ({why})") from exc
        except tomllib.TOMLDecodeError as exc:
            raise UserError(f"--controller-params {path}: not valid TOML: {exc}") from exc
    return ControllerChoice(name, params)


def _controller_name(args: argparse.Namespace) -> str:
    """--controller, else 'paper'."""
    return args.controller or "paper"


def _drive_defaults(args: argparse.Namespace, drive: Any) -> None:
    """A drive profile that names the drive mode its runs use ([modes].default: a standard
    drive) gives it to a run without --drive-mode, and 'stream' to one without
    --controller."""
    if drive.default_mode is None or args.drive_mode is not None:
        return
    args.drive_mode = drive.default_mode
    if args.controller is None and drive.default_mode.standard:
        args.controller = "stream"


def _add_control_options(p: argparse.ArgumentParser) -> None:
    from gateway.control.controller import (
        Discretisation,
        EstimatorKind,
        FluxSource,
        InertiaSource,
        Law,
    )
    from gateway.control.laws import Gains

    g = Gains()
    p.add_argument("--reference", "--profile", dest="profile", metavar="FILE",
                   help="reference profile ω*(t), ψ*(t), T_L(t) (TOML); default: the paper's "
                        "section 6 scenario")
    p.add_argument("--controller", metavar="NAME", default=None,
                   help="the controller in the loop: 'paper' (default: the laws of Marino, "
                        "Tomei & Verrelli, with the options below), 'ifoc' (indirect "
                        "field-oriented control with a speed sensor, the baseline of a "
                        "vector drive), a name another installed package registers "
                        "(entry-point group can_drive_hil.controllers), or "
                        "package.module:Class; for a standard drive (CST, CSV, CSP): "
                        "'speed-pi' (a speed PI over its torque) or 'stream' (the profile as "
                        "its target; the default for a drive profile whose [modes].default "
                        "is a standard mode); docs/controllers.md")
    p.add_argument("--controller-params", metavar="FILE.toml",
                   help="the controller's parameters: a TOML table of names to values, "
                        "passed to its factory (not for 'paper', whose options are below)")
    p.add_argument("--law", type=Law, choices=list(Law), default=Law.CURRENT_FED,
                   help="control law: current-fed (15),(16),(20) or full-order (25)-(27),(32)")
    p.add_argument("--flux", type=FluxSource, choices=list(FluxSource),
                   default=FluxSource.ESTIMATED,
                   help="rotor flux for the law: estimated by (24) (sensorless, default) or the "
                        "true flux (the paper's 'flux measurements available' comparison)")
    p.add_argument("--estimator", type=EstimatorKind, choices=list(EstimatorKind),
                   default=EstimatorKind.OPEN_LOOP,
                   help="flux estimator: the paper's open-loop integrator, the drift-free "
                        "one, or drift-free with on-line R_s adaptation (rs-adaptive, "
                        "docs/robustness.md)")
    p.add_argument("--discretisation", type=Discretisation, choices=list(Discretisation),
                   help="sampled controller: exact (the sampled-data design of "
                        "docs/sampled-control.md) or euler (the continuous laws stepped with "
                        "forward Euler, the earlier design); default exact; the "
                        "full-order law has an exact design for voltage-fed "
                        "(d, q) drives only")
    p.add_argument("--motor", metavar="FILE", help="motor parameters (TOML, SI units; template: "
                   "gateway/motors/paper.toml); default: the paper's 0.6 kW motor")
    p.add_argument("--load", choices=("known", "observed", "untold"),
                   help="the load torque for the laws: known (the profile's T_L, the paper, "
                        "docs/paper.md §E6; with J tracked on an ideal current source, "
                        "watched once J is known: a told load the readings reject is "
                        "corrected by the load observed, docs/robustness.md §10), observed "
                        "(estimated on line: in the exact design from the measured flux "
                        "with the inertia, either law (the full-order law with (d, q) "
                        "setpoints), docs/robustness.md §10; in the Euler design by its "
                        "load observer, current-fed law, §2) or untold (the laws assume "
                        "none: T_L = 0); default: the plant "
                        "scenario's [load].known, else known where the drive applies the "
                        "profile's load (the emulator, a drive profile with a T_L signal) and "
                        "untold where it cannot")
    p.add_argument("--identify", action=argparse.BooleanOptionalAction, default=None,
                   help="identify R_s and R_r from the standstill magnetisation (once the "
                        "flux reference has settled, or when the speed or load reference "
                        "first moves) and use them from then on; summary.json says what was "
                        "found (docs/robustness.md §5). On by default in sampled runs; "
                        "--no-identify: the motor file's values throughout")
    p.add_argument("--inertia", type=InertiaSource, choices=list(InertiaSource),
                   default=InertiaSource.TRACKED,
                   help="the rotor's inertia J in the laws: tracked (default: estimated on "
                        "line from the measured flux and applied once the data reject the "
                        "motor file's J; sampled-data design, either law, load known (or "
                        "observed), not with the R_s adaptation nor without the standstill "
                        "identification; elsewhere the file's J, and "
                        "summary.json says why) or file (the motor file's J throughout, the "
                        "paper); docs/robustness.md §9")
    p.add_argument("--commissioning", action=argparse.BooleanOptionalAction, default=None,
                   help="correct the current sensors' offsets and gain and the inverter's "
                        "dead time that the motor file's [commissioning] table holds "
                        "(`hil-gateway identify -o FILE` writes it) around the controller "
                        "(docs/robustness.md §7). On by default when --motor names such a "
                        "file and the run is sampled; --no-commissioning: read the sensors "
                        "as they are")
    p.add_argument("--k-w", type=float, default=g.k_w, help="speed gain kω, 1/s (%(default)s)")
    p.add_argument("--gamma-1", type=float, default=g.gamma_1,
                   help="observer gain γ1 of (20) (%(default)s)")
    p.add_argument("--gamma-2", type=float, default=g.gamma_2,
                   help="observer gain γ2 of (32), full-order law (%(default)s)")
    p.add_argument("--k-e", type=float, default=g.k_e,
                   help="current-error gain ke of (32), 1/s (%(default)s)")
    p.add_argument("--i-max", type=float, default=g.i_max,
                   help="current-vector limit of the setpoints, A (%(default)s)")
    p.add_argument("--k-w-t-max", type=float, default=g.k_w_T_max,
                   help="full-order law, sampled-data design: kω is lowered to this over "
                        "the period where kω·T would exceed it (the sampled speed loop "
                        "through the current loop is stable for kω·T < 1; 450 1/s at 2 ms, "
                        "the paper's 800 at 1 ms and faster; docs/robustness.md §11). inf: "
                        "the paper's kω at every period (%(default)s)")


def _design(args: argparse.Namespace) -> Any:
    """--discretisation, else :class:`gateway.spec.RunSpec`'s (the sampled-data design: it
    has every estimator and load mode)."""
    from gateway.spec import RunSpec

    return RunSpec.discretisation if args.discretisation is None else args.discretisation


def _load_mode(args: argparse.Namespace, plant: Any, drive: Any = None) -> str:
    """--load; else :func:`gateway.spec.default_load` for the plant scenario and whether
    the drive applies the profile's load (a drive profile that maps a T_L signal)."""
    from gateway.spec import default_load

    if args.load:
        return args.load
    applies = None
    if drive is not None:
        from gateway.process_data import process_data

        applies = "T_L" in process_data(drive).roles
    return default_load(plant, applies).value


def _gains(args: argparse.Namespace):
    from gateway.control.laws import Gains

    for name in ("k_w", "gamma_1", "gamma_2", "k_e"):
        if not math.isfinite(getattr(args, name)):
            raise UserError(f"--{name.replace('_', '-')} {getattr(args, name)}: give a finite "
                            "positive number")
    if not args.k_w_t_max > 0.0:
        raise UserError(f"--k-w-t-max {args.k_w_t_max}: give a positive number, the bound on "
                        "kω·T (inf: the asked kω at every period)")
    try:
        return Gains(k_w=args.k_w, gamma_1=args.gamma_1, gamma_2=args.gamma_2, k_e=args.k_e,
                     i_max=args.i_max, k_w_T_max=args.k_w_t_max)
    except ValueError as exc:
        raise UserError(f"{exc}; all gains must be positive numbers") from exc


# --------------------------------------------------------------------------- simulate


@dataclass(frozen=True)
class RunInputs:
    """What a command line asks of :func:`gateway.session.run`: the checked ``spec``, the
    reference ``profile``, the controller's ``motor``, the metric ``windows``, the bus
    ``target`` (None: in this process) and the period's words (``label``). Made by
    :func:`simulate_inputs` and :func:`sim_inputs`, which `simulate`, `sim` and a
    campaign's points (:mod:`gateway.campaign`) all go through."""

    spec: Any
    profile: Any
    motor: Any
    windows: tuple
    target: Any = None
    label: str = ""


@dataclass(frozen=True)
class SimulateOptions:
    """`simulate`'s options that do not depend on the plant scenario, each checked: the
    reference ``profile``, the controller's ``motor``, the ``sampling`` (None:
    continuous), the ``duration``, the ``drive_mode``, the ``gains``, the sensor
    ``correction``, the ``controller``, the metric ``windows`` and the period's words
    (``label``). Made by :func:`simulate_options`; a campaign's points that differ only
    in their plant share one (:mod:`gateway.campaign.runpoint`)."""

    profile: Any
    motor: Any
    sampling: Any
    duration: float | None
    drive_mode: Any
    gains: Any
    correction: Any
    controller: Any
    windows: tuple
    label: str


def simulate_options(args: argparse.Namespace,
                     controller_params: dict[str, Any] | None = None) -> SimulateOptions:
    """The plant-independent part of :func:`simulate_inputs` (UserError on a bad option)."""
    from dbc.timing import Sampling
    from gateway import report
    from gateway.cycle import CycleRow
    from gateway.simulate import emulator_rate
    from gateway.spec import RunSpec

    profile = _load_profile(args.profile)
    motor = _load_motor(args.motor)
    period = (None if args.period == "continuous"
              else parse_period(args.period, "--period", emulator_rate()))
    duration = parse_duration(args.duration, "--duration") if args.duration else None
    sampling = None if period is None else Sampling(period, args.delay, args.setpoint_frame)
    label = "continuous" if period is None else format_duration(period)
    total = duration or profile.duration
    step = sampling.period if sampling is not None else RunSpec.record_step
    n_rows = _check_duration(total, step, _duration_words(args, profile))
    report.check_record_size(n_rows, len(CycleRow._fields), args.allow_long,
                             f"simulating {total:g} s at {label}")
    return SimulateOptions(
        profile=profile, motor=motor, sampling=sampling, duration=duration,
        drive_mode=_drive_mode(args), gains=_gains(args),
        correction=_correction(args, period is not None),
        controller=_controller_choice(args, controller_params),
        windows=report.profile_windows(profile, args.windows), label=label)


def simulate_inputs(args: argparse.Namespace, plant: Any = None,
                    controller_params: dict[str, Any] | None = None,
                    options: SimulateOptions | None = None) -> RunInputs:
    """`simulate`'s options → what its run needs, every input checked (UserError) before
    anything runs. ``plant``: the plant scenario itself, in place of ``--plant``;
    ``controller_params``: the controller's parameters, in place of the
    ``--controller-params`` file's; ``options``: :func:`simulate_options` of the same
    ``args`` and ``controller_params``, made before."""
    from gateway.spec import RunSpec

    o = options if options is not None else simulate_options(args, controller_params)
    plant = plant if plant is not None else _load_scenario(args.plant)
    load = _load_mode(args, plant)
    spec = RunSpec(
        law=args.law, flux=args.flux, estimator=args.estimator, drive_mode=o.drive_mode,
        sampling=o.sampling, quantize=not args.no_quantize, gains=o.gains,
        duration=o.duration, discretisation=_design(args), plant=plant, load=load,
        identify=args.identify, inertia=args.inertia, correction=o.correction,
        controller=o.controller,
    )
    if plant is not None and plant.bus_faults:
        _check_simulated_faults(spec, args.plant or plant.source)
    return RunInputs(spec, o.profile, o.motor, o.windows, label=o.label)


def _check_simulated_faults(spec: Any, name: str) -> None:
    """A plant scenario's bus faults act on the frames of a sampled, quantised run's PDO
    link (:mod:`gateway.faultlink`): a UserError, naming what to change, otherwise."""
    from gateway.faultbus import check_faults
    from gateway.faultlink import check_link_faults
    from gateway.process_data import process_data
    from gateway.simulate import emulated_drive

    if spec.sampling is None:
        raise UserError(f"--plant {name} injects bus faults ([[bus.fault]]), which act on "
                        "the PDOs of a sampled run: choose a --period such as 1ms (or run "
                        f"it over the bus with `hil-gateway sim --plant {name}`)")
    if not spec.quantize:
        raise UserError(f"--plant {name} injects bus faults ([[bus.fault]]), which act on "
                        "the PDOs' frames; --no-quantize has none: drop --no-quantize")
    check_link_faults(spec.plant.bus_faults, name)
    check_faults(spec.plant.bus_faults, process_data(emulated_drive(spec)), f"--plant {name}")


def cmd_simulate(args: argparse.Namespace) -> int:
    """`hil-gateway simulate`: the closed loop without CAN. A worker process gets ready to
    draw the figures first (:class:`gateway.drawing.FigureWorker`), while the rest loads."""
    from gateway.drawing import FigureWorker

    with (FigureWorker.start() if args.figures else None) or contextlib.nullcontext() as worker:
        return _simulate(args, worker)


def _simulate(args: argparse.Namespace, worker: Any) -> int:
    from gateway.session import Output, run

    inputs = simulate_inputs(args)
    spec, profile, label = inputs.spec, inputs.profile, inputs.label
    progress = Progress(f"simulate {args.law} {label}", True if args.progress else None)
    try:
        with _live_scope(args, f"simulate {profile.name}") as scope:
            result = run(spec, profile, inputs.motor,
                         output=Output(args.out, f"simulate-{args.law}", args.force,
                                       args.figures),
                         windows=inputs.windows, progress=progress, watcher=scope,
                         figure_worker=worker)
    except BaseException:
        progress.done(complete=False)
        raise
    progress.done(complete=result.summary["run"]["stop"] == "END_OF_PROFILE")
    _print_simulation(spec, profile, label, result, args.figures)
    _print_next(result)
    return result.exit_status  # 1 when a file could not be written (write_results)


def _live_scope(args: argparse.Namespace, title: str) -> Any:
    """``--scope`` and ``--plotjuggler``: the live view of the run
    (:func:`gateway.scope.live_scope`), imported only when asked for (it brings an HTTP
    server)."""
    if args.scope is None and args.plotjuggler is None:
        return contextlib.nullcontext(None)
    from gateway.scope import live_scope

    return live_scope(args.scope, title, args.plotjuggler)


def _print_next(result: Any) -> None:
    """What to look at and run next, after a run that drew its figures."""
    names = {p.name for p in result.files}
    if "fig2_errors.png" not in names:
        return
    print(f"next: look at {result.out}/fig2_errors.png (the tracking errors) and "
          "fig3_currents_voltages.png; change one thing (--plant rs+10, --controller ifoc, "
          f"--period 2ms, ...) and put the runs side by side: {PROG} compare "
          f"{result.out} <other run>")


def _duration_words(args: argparse.Namespace, profile: Any) -> str:
    return (f"--duration {args.duration}" if args.duration
            else f"the profile's duration ({profile.duration:g} s)")


def _print_simulation(spec: Any, profile: Any, label: str, result: Any,
                      figures: bool = True) -> None:
    """What `simulate` did: configuration, the metrics, the files, why it stopped early."""
    from gateway import report

    s, summary = spec.sampling, result.summary
    print(f"{PROG} simulate: {profile.name}, {spec.who}, drive "
          f"{spec.drive_mode}, plant {getattr(spec.plant, 'name', 'nominal')}, load "
          f"{spec.load}, period {label}"
          + ("" if s is None else
             f", delay {s.delay}, setpoints in ({s.setpoint_frame[0]}, "
             f"{s.setpoint_frame[1]}), {spec.discretisation} design"))
    print(report.summary_table(summary))
    for e in result.write_errors:
        print(f"{PROG}: {e}", file=sys.stderr)
    drawn = any(p.suffix == ".png" for p in result.files)
    print(f"{summary['run']['cycles']} samples, {summary['wall_time_s']:.2f} s wall time; "
          f"wrote {result.out}/" + ", ".join(p.name for p in result.files)
          + ("" if drawn or result.write_errors or not figures
             else " (install matplotlib for the figures)"))
    if "bus_faults" in summary:  # the loop's account, as a bus run prints it
        from gateway.runner import timing_table

        print(timing_table(summary))
        for f in summary["bus_faults"]:
            print(f"bus fault {f['fault']}: acted {f['acted']} time(s)")
    stop = summary["run"]["stop"]
    if stop == "DIVERGED":
        print(f"{PROG}: the loop diverged and the simulation stopped: "
              f"{summary['run']['stop_reason']} (the bus loop's divergence envelope, README "
              "\"Faults and the shutdown\"); the files hold the run up to there",
              file=sys.stderr)
    elif "stopped_early" in summary:
        print(f"{PROG}: stopped early ({summary['stopped_early']}); the files hold the run so "
              "far", file=sys.stderr)
    elif stop != "END_OF_PROFILE":  # a bus fault's reaction
        print(f"{PROG}: the run stopped early ({stop.lower().replace('_', ' ')}): "
              f"{summary['run']['stop_reason']}; the files hold the run up to there",
              file=sys.stderr)


# ------------------------------------------------------------------------- run / sim


def _add_run_options(p: argparse.ArgumentParser) -> None:
    from dbc.modes import DriveMode
    from dbc.timing import Timing

    _add_control_options(p)
    p.add_argument("--node", type=int, help="CANopen node id of the drive (default: the drive "
                   "profile's, 1)")
    p.add_argument("--gateway-node", type=int, metavar="N",
                   help="the gateway's own node id (its heartbeat, which the drive watches); "
                        "default: the drive profile's [drive].gateway_node, 127 (0x7F)")
    p.add_argument("--period", default="1ms",
                   help="cycle period (SYNC) with its unit, 100us … 100ms in whole µs, e.g. "
                        "1ms (default) or 250us")
    from gateway.drive_profile import Mapping

    p.add_argument("--mapping", type=Mapping, choices=list(Mapping), default=None,
                   help="the emulator's process data: default (every signal, truth and load "
                        "included: 765 us of bus time a cycle at 1 Mbit/s, periods from "
                        "900 us) or lean (SYNC, 2 TPDOs, 1 RPDO: 410 us, periods from 483 us: "
                        "2 kHz; gateway/drives/emulator-lean.toml). With --drive: the "
                        "profile's [pdo].mapping must say the same")
    p.add_argument("--allow-bus-overload", action="store_true",
                   help="run a period whose cycle's frames take more than 85%% of it on a bus "
                        "of the drive profile's bit rate (worst-case stuffing), which is "
                        "refused otherwise: `sim`'s in-process bus has no bit rate; a real "
                        "bus would miss cycles")
    p.add_argument("--timing", type=Timing, choices=list(Timing), default=Timing.LOCKSTEP,
                   help="lockstep: next SYNC as soon as the RPDOs are out (deterministic, "
                        "faster than real time against the emulator); realtime: SYNC on an "
                        "absolute schedule")
    p.add_argument("--drive-mode", type=DriveMode, choices=list(DriveMode),
                   help="what the drive does with the setpoints: ideal current source or PI "
                        "current loop (CiA 402 current vector mode; 'ideal' only on the "
                        "emulator), or voltage-fed (voltage vector mode); or a standard "
                        "drive's cyclic synchronous torque or velocity mode (CST, CSV: its "
                        "own field orientation; --controller speed-pi or stream; the "
                        "emulator's standard profile); default: ideal for the current-fed law, "
                        "voltage for the full-order law, torque for speed-pi, velocity for "
                        "stream")
    p.add_argument("--delay", type=int, choices=(0, 1), default=1,
                   help="1: the drive applies RPDOs at the next SYNC (CiA 301); 0: on receipt "
                        "(emulator option)")
    p.add_argument("--duration", help="run this long instead of the profile's duration "
                   "(10s, 500ms; a bare number is seconds)")
    p.add_argument("--max-missed", type=int,
                   help="consecutive missed cycles that stop the loop (default: real time 50 "
                        "ms worth, at least 5 (50 at 1 ms); lockstep 5, each after 1 s)")
    p.add_argument("--max-miss-rate", type=float, default=0.2, metavar="FRACTION",
                   help="the fraction of cycles that may be missed within any 100 ms before "
                        "the run stops (default 0.2; 1 switches the rate limit off)")
    p.add_argument("--log", default="bus.blf", metavar="NAME",
                   help="raw bus log in the run directory; .blf (default), .asc, .csv, .log "
                        "(candump) or .trc by suffix")
    _add_output_options(p, "runs/<time>-<command>")


def _add_output_options(p: argparse.ArgumentParser, default_dir: str) -> None:
    """The run directory, its reuse, the record-size guard, the metric windows, progress."""
    from gateway.report import RECORD_LIMIT

    p.add_argument("--out", metavar="DIR",
                   help=f"run directory (default {default_dir}, never reused: a second run in "
                        "the same second gets -2, -3, …); an existing non-empty DIR is refused")
    p.add_argument("--force", action="store_true",
                   help="reuse an existing --out DIR (the earlier run's files are removed)")
    p.add_argument("--allow-long", action="store_true",
                   help=f"run even when the record would need more than "
                        f"{RECORD_LIMIT / (1 << 30):g} GiB of memory (estimated from duration, "
                        "period and columns before anything runs)")
    p.add_argument("--windows", metavar="SPEC", default="auto",
                   help="metric windows: auto (default: one per segment of the reference "
                        "profile), paper ([0,0.5), [0.5,1.5), [1.5,end)), none, or boundaries "
                        "in s such as 0.5,1.5 (docs/outputs.md)")
    p.add_argument("--no-figures", dest="figures", action="store_false",
                   help="write signals.csv and summary.json only, no figures (faster; "
                        "`hil-gateway compare` and the scope read the run as well)")
    p.add_argument("--progress", action="store_true", help="progress bar even when not a tty")
    p.add_argument("--scope", metavar="[HOST:]PORT",
                   help="serve a live scope of the run at http://HOST:PORT/ (HOST 127.0.0.1 "
                        "by default; PORT 0: any free port, printed): speed, flux, currents, "
                        "voltages, torque, timing, the drive's state and stop reason, with "
                        "signal choice, pause, zoom, time base and a trigger")
    p.add_argument("--plotjuggler", metavar="[HOST:]PORT", nargs="?", const="9870",
                   help="stream the scope's rows to PlotJuggler's UDP server (JSON, one "
                        "datagram a row, timestamp field t; HOST 127.0.0.1 by default, PORT "
                        "9870 when not given)")


def _drive_mode(args: argparse.Namespace) -> Any:
    """--drive-mode; else the controller's (:func:`gateway.spec.default_drive_mode`)."""
    from gateway.spec import default_drive_mode

    if args.drive_mode is not None:
        return args.drive_mode
    return default_drive_mode(_controller_name(args), args.law)


def _emulator_profile(args: argparse.Namespace) -> str:
    """The built-in emulator profile for the run's drive mode and --mapping."""
    from gateway.drive_profile import emulator_profile

    return emulator_profile(_drive_mode(args), args.mapping)


def _check_mapping(args: argparse.Namespace, drive: Any) -> None:
    """--mapping with --drive: the profile's [pdo].mapping must be the one asked for."""
    if args.mapping is not None and drive.mapping is not args.mapping:
        raise UserError(f"--mapping {args.mapping.value}: the drive profile {drive.source} "
                        f"has the {drive.mapping.value} mapping ([pdo].mapping); drop "
                        "--mapping, or give a profile with that mapping")


def _run_spec(args: argparse.Namespace, drive: Any, plant: Any = None,
              controller_params: dict[str, Any] | None = None):
    """The run's specification, checked against what the drive can do."""
    from dbc.modes import DriveMode
    from dbc.timing import Sampling, Timing
    from gateway.control.controller import FluxSource
    from gateway.process_data import process_data
    from gateway.spec import RunSpec

    law = args.law
    mode = _drive_mode(args)
    if not drive.emulator and mode is DriveMode.IDEAL:
        if args.drive_mode:
            raise UserError("--drive-mode ideal (an ideal current source) exists only on the "
                            "emulator; a real drive runs its current loop: use --drive-mode "
                            "current-loop")
        mode = DriveMode.CURRENT_LOOP
    if args.flux is FluxSource.TRUE and not drive.truth:
        raise UserError(f"--flux true needs the drive's true rotor flux, which only the "
                        f"emulator sends (TPDO3); {drive.name} has none: use --flux estimated")
    if drive.emulator:
        from gateway.sim import emulator_rate

        period = parse_period(args.period, "--period", emulator_rate())
    else:
        period = parse_period(args.period, "--period")
    load = _load_mode(args, plant, drive)
    return RunSpec(
        law=law, flux=args.flux, estimator=args.estimator, drive_mode=mode,
        sampling=Sampling(period, args.delay, process_data(drive).setpoint_frame),
        timing=args.timing, gains=_gains(args), bus_log=args.log,
        # real time: 50 ms worth of cycles; lockstep waits 1 s per cycle already: 5
        max_missed=(args.max_missed if args.max_missed is not None
                    else max(5, round(0.05 / period)) if args.timing is Timing.REALTIME
                    else 5),
        max_miss_rate=args.max_miss_rate,
        duration=args.duration and parse_duration(args.duration, "--duration"),
        plant=plant, load=load, discretisation=_design(args),
        identify=args.identify, inertia=args.inertia, correction=_correction(args, True),
        controller=_controller_choice(args, controller_params),
    )


def _print_run(result: Any) -> None:
    from gateway import report
    from gateway.runner import timing_table

    summary = result.summary
    if "speed_error" in summary:
        print(report.summary_table(summary))
    elif summary.get("identification"):  # no truth from the drive: no table, but this
        print(report.identification_line(summary["identification"]))
    print(timing_table(summary))
    run = summary["run"]
    logged = [run["bus_log"]] if run.get("bus_log") and not run.get("bus_log_error") else []
    print(f"wrote {result.out}/ ("
          + ", ".join([p.name for p in result.files if p.suffix != ".png"] + logged)
          + (", figures" if any(p.suffix == ".png" for p in result.files) else "") + ")")


def _finish_run(summary: dict[str, Any]) -> int:
    """Exit status from the stop's cause (:class:`gateway.stop.StopReason`): 0 when the
    profile ran to its end, 130 when interrupted, 1 otherwise (fault, drive lost, error),
    and 1 whenever the drive was not confirmed safe or a result could not be written."""
    run = summary["run"]
    for err in summary.get("write_errors", []):
        print(f"{PROG}: error: {err}", file=sys.stderr)
    shutdown = summary.get("shutdown")
    if shutdown is not None and not shutdown["safe"]:
        steps = "; ".join(shutdown["steps"])
        print(f"{PROG}: the drive's power stage was NOT confirmed off ({steps}). Check the "
              "drive before touching the motor.", file=sys.stderr)
    if run["stop"] != "END_OF_PROFILE":
        print(f"{PROG}: the run stopped early ({run['stop'].lower().replace('_', ' ')}): "
              f"{run['stop_reason']}", file=sys.stderr)
    return run["exit_status"]


def bus_inputs(args: argparse.Namespace, target: Any, plant: Any = None,
               controller_params: dict[str, Any] | None = None) -> RunInputs:
    """What `run` and `sim` share before the run: the options → the spec against
    ``target``'s drive, its node ids, the duration and record size, all checked (UserError)
    before the run directory is made; ``controller_params`` as in :func:`simulate_inputs`."""
    from gateway import report
    from gateway.bustime import check_bus_time
    from gateway.loop import LoopRow

    drive = target.drive
    profile = _load_profile(args.profile, drive)
    motor = _load_motor(args.motor)
    spec = _run_spec(args, drive, plant, controller_params)
    if not args.allow_bus_overload:  # a cycle that cannot fit: refused before the bus
        check_bus_time(drive, spec.period)
    node = args.node if args.node is not None else drive.node
    if not 1 <= node <= 127:
        raise UserError(f"--node {node}: a CANopen node id is 1..127")
    gateway_node = args.gateway_node if args.gateway_node is not None else drive.gateway_node
    if not 1 <= gateway_node <= 127 or gateway_node == node:
        raise UserError(f"--gateway-node {gateway_node}: the gateway's node id is 1..127 and "
                        f"not the drive's ({node})")
    total = spec.duration or profile.duration
    n_rows = _check_duration(total, spec.period, _duration_words(args, profile))
    report.check_record_size(n_rows, len(LoopRow._fields), args.allow_long,
                             f"running {total:g} s at {format_duration(spec.period)}")
    return RunInputs(spec, profile, motor, report.profile_windows(profile, args.windows),
                     replace(target, node=node, gateway_node=args.gateway_node),
                     format_duration(spec.period))


def _gateway_session(args: argparse.Namespace, target: Any, plant: Any = None) -> int:
    """What `run` and `sim` share: inputs checked before the run directory is made
    (:func:`bus_inputs`), the run (:func:`gateway.session.run`), the report, the exit
    status. Where figures will be drawn (the drive maps its speed), a worker process gets
    ready for them first, at a lower priority than the loop
    (:class:`gateway.drawing.FigureWorker`)."""
    from gateway.drawing import FigureWorker
    from gateway.session import has_truth

    worker = FigureWorker.start(nice=10) if args.figures and has_truth(target) else None
    with worker or contextlib.nullcontext():
        return _on_the_bus(args, target, plant, worker)


def _on_the_bus(args: argparse.Namespace, target: Any, plant: Any, worker: Any) -> int:
    from gateway.bustime import profile_load
    from gateway.session import Output, run

    kind = target.command
    inputs = bus_inputs(args, target, plant)
    spec, profile, target = inputs.spec, inputs.profile, inputs.target
    drive, node = target.drive, target.node
    print(f"{PROG} {kind}: {drive.name}: {profile_load(drive).describe(spec.period)}",
          flush=True)
    progress = Progress(kind, True if args.progress else None)
    try:
        with _live_scope(args, f"{kind} {profile.name}") as scope:
            result = run(spec, profile, inputs.motor, target=target,
                         output=Output(args.out, kind, args.force, args.figures),
                         windows=inputs.windows, progress=progress, watcher=scope,
                         figure_worker=worker)
    except BaseException:
        progress.done(complete=False)
        raise
    progress.done(complete=result.exit_status == 0)
    conf = result.summary["configuration"]
    print(f"{PROG} {kind}: {profile.name} on {conf['bus']} node {node} ({drive.name}, "
          f"{spec.drive_mode}), {spec.who}, load {spec.load}, {spec.timing}, "
          f"period {format_duration(spec.period)}, delay {spec.sampling.delay}, "
          f"{spec.discretisation} design")
    _print_run(result)
    _print_next(result)
    return _finish_run(result.summary)


def cmd_run(args: argparse.Namespace) -> int:
    """`hil-gateway run`: the loop against a drive on a CAN bus."""
    from dbc.bus import bus_config, open_bus
    from gateway.drive_profile import load_drive_profile
    from gateway.runner import BusTarget

    drive = load_drive_profile(args.drive, _emulator_profile(args))
    _check_mapping(args, drive)
    _drive_defaults(args, drive)
    bus_cfg = bus_config(args)

    def open_buses(*_: Any) -> tuple[Any, str, Callable[[], None]]:
        bus = open_bus(bus_cfg)
        return bus, bus_cfg.label(), bus.shutdown

    return _gateway_session(args, BusTarget(drive, open_buses, command="run"))


def _sim_target(args: argparse.Namespace, plant: Any) -> Any:
    """`sim`'s target (:func:`gateway.sim.sim_target`) for these options and ``plant``."""
    from gateway.sim import sim_target

    return sim_target(_drive_mode(args), plant, _load_profile(args.profile).load,
                      args.transport, args.gateway_node,
                      f"--plant {args.plant or getattr(plant, 'source', '')}", args.mapping)


def sim_inputs(args: argparse.Namespace, plant: Any = None,
               controller_params: dict[str, Any] | None = None) -> RunInputs:
    """`sim`'s options → what its run needs (:func:`bus_inputs` against the emulator's
    target); ``plant`` and ``controller_params`` as in :func:`simulate_inputs`."""
    plant = plant if plant is not None else _load_scenario(args.plant)
    return bus_inputs(args, _sim_target(args, plant), plant, controller_params)


def cmd_sim(args: argparse.Namespace) -> int:
    """`hil-gateway sim`: the same loop against the emulator started in this process."""
    plant = _load_scenario(args.plant)
    return _gateway_session(args, _sim_target(args, plant), plant)


# ---------------------------------------------------------------------------- profile


def cmd_profile_check(args: argparse.Namespace) -> int:
    """`hil-gateway profile check FILE`: validate and show the set points and demands; a
    drive profile (a TOML with [drive]) is checked off line against its EDS and DBC
    (:mod:`gateway.profilecheck`: exit 1 when a signal does not fit its object).

    What cannot run (a value beyond the PDO signals' range or the emulated drive's
    over-speed limit) is refused by the loader, as for every command that loads a profile:
    exit status 2 with the file, the key and the limit. Merely high demands are warnings."""
    from gateway.profilecheck import check_drive_profile, is_drive_profile, render
    from gateway.reference import demand, reference_limits

    if is_drive_profile(args.file):  # a drive profile ([drive]): checked off line
        report = check_drive_profile(args.file)
        print(render(report, parse_period(args.period, "--period")))
        return 0 if report.ok else 1
    profile = _load_profile(args.file)
    motor = _load_motor(args.motor)
    print(f"{args.file}: profile {profile.name!r} is valid, duration {profile.duration:g} s")
    for line in profile.set_points():
        print(f"  {line}")
    ranges = {name: (max(lim.lo for lim in lims), min(lim.hi for lim in lims))
              for name, lims in reference_limits().items()}
    (_, w_hi), (_, psi_hi), (tl_lo, tl_hi) = (ranges[k] for k in ("speed", "flux", "load"))
    print(f"within the limits (beyond them a profile is refused): |ω*| ≤ {w_hi:g} rad/s, "
          f"ψ* ≤ {psi_hi:g} Wb, T_L {tl_lo:g} to {tl_hi:g} N·m")
    d = demand(profile, motor)
    from gateway.sim import emulator_limits

    i_trip, u_lim = emulator_limits()
    print("demand on the motor under perfect tracking (open-loop references (9)-(11)):")
    print(f"  peak current |i_s|   {d.i_s_peak:8.3g} A    at {d.t_i_s_peak:.3g} s "
          f"(i_sd up to {d.i_sd_peak:.3g} A, i_sq up to {d.i_sq_peak:.3g} A)")
    print(f"  peak voltage |u_s|   {d.u_s_peak:8.3g} V    at {d.t_u_s_peak:.3g} s")
    print(f"  peak torque  |T_e|   {d.T_e_peak:8.3g} N·m  at {d.t_T_e_peak:.3g} s")
    print(f"  peak speed   |ω*|    {d.w_peak:8.4g} rad/s, frame speed |ω0| up to "
          f"{d.w_0_peak:.4g} rad/s")
    if d.i_s_peak > i_trip:
        print(f"  warning: beyond the default drive's over-current trip ({i_trip:g} A)")
    if d.u_s_peak > u_lim:
        print(f"  warning: beyond the default drive's voltage limit ({u_lim:.0f} V = "
              f"u_dc/√3): expect the limit to act")
    return 0


#: What `profile plot -o` can write (matplotlib picks the format from the suffix).
PLOT_SUFFIXES = (".png", ".svg", ".pdf")


def cmd_profile_plot(args: argparse.Namespace) -> int:
    """`hil-gateway profile plot FILE`: references and their derivatives, in real units."""
    if args.output:
        out = Path(args.output)
        if out.suffix.lower() not in PLOT_SUFFIXES:
            raise UserError(f"-o {args.output!r}: a plot is written as "
                            f"{', '.join(PLOT_SUFFIXES)} (by the suffix); e.g. -o "
                            f"{out.with_suffix('.png')}")
    else:
        out = Path("runs") / f"profile-{Path(args.file).stem}.png"
    profile = _load_profile(args.file)
    try:
        import matplotlib

        matplotlib.use("Agg")
        import matplotlib.pyplot as plt
    except ImportError as exc:
        raise UserError("profile plot needs matplotlib: pip install 'can-drive-hil[plot]'") from exc
    from gateway.reference import sample_times

    t = sample_times(profile, max_points=4000)
    s = profile.sample(t)
    fig, ax = plt.subplots(3, 2, sharex=True, figsize=(10, 7), layout="constrained")
    rows = (("w_ref", "dw_ref", "speed ω*", "rad/s", "C0"),
            ("psi_ref", "dpsi_ref", "rotor flux ψ*", "Wb", "C1"),
            ("T_L", "dT_L", "load torque T_L", "N·m", "C3"))
    for j, (key, dkey, name, unit, color) in enumerate(rows):
        ax[j, 0].plot(t, s[key], color=color)
        ax[j, 0].set_ylabel(f"{name} [{unit}]")
        ax[j, 1].plot(t, s[dkey], color=color, lw=0.9)
        dunit = {"rad/s": "rad/s²"}.get(unit, f"{unit}/s")
        ax[j, 1].set_ylabel(f"d/dt {name.split()[-1]} [{dunit}]")
        for a in ax[j]:
            a.grid(True, alpha=0.3)
    ax[0, 0].set_title("references")
    ax[0, 1].set_title("first derivatives (what the laws use)")
    for a in ax[2]:
        a.set_xlabel("time [s]")
    fig.suptitle(f"reference profile {profile.name!r} ({args.file}), {profile.duration:g} s")
    try:
        out.parent.mkdir(parents=True, exist_ok=True)
        fig.savefig(out, dpi=110)
    except (OSError, ValueError) as exc:
        raise UserError(f"cannot write {str(out)!r}: {getattr(exc, 'strerror', None) or exc}; "
                        "choose another file with -o") from exc
    finally:
        plt.close(fig)
    print(f"wrote {out}")
    return 0


# ---------------------------------------------------------------------------- compare


def cmd_compare(args: argparse.Namespace) -> int:
    """`hil-gateway compare RUN_DIR…`: errors side by side, configuration differences, and
    a figure of the speed and flux errors of every run overlaid; with ``--baseline`` the
    regression gate instead (:func:`cmd_gate`)."""
    from gateway import report

    if args.baseline is not None:
        return cmd_gate(args)
    for given, name in ((args.tolerance, "--tolerance"), (args.junit, "--junit")):
        if given:
            raise UserError(f"{name} belongs to the regression gate: give --baseline RUN_DIR "
                            "too (the run the others are measured against)")
    out = _figure_path(args)
    runs = [report.load_run(Path(d)) for d in args.runs]
    print(report.compare_table(runs))
    _write_figure(out, runs)
    return 0


def _figure_path(args: argparse.Namespace) -> Path:
    """`compare`'s figure: -o FILE (.png, .svg, .pdf), else compare.png in the current
    directory (a run directory stays as its run left it)."""
    out = Path(args.output) if args.output else Path("compare.png")
    if out.suffix.lower() not in PLOT_SUFFIXES:
        raise UserError(f"-o {args.output!r}: the figure is written as "
                        f"{', '.join(PLOT_SUFFIXES)} (by the suffix)")
    return out


def _write_figure(out: Path, runs: list[Any]) -> None:
    """The runs' speed and flux errors overlaid, into ``out``."""
    from gateway import report

    try:
        written = report.plot_compare(runs, out)
    except OSError as exc:
        raise UserError(f"cannot write {str(out)!r}: {exc.strerror or exc}; choose another "
                        "file with -o") from exc
    print(f"wrote {written}" if written else "(install matplotlib for the figure)")


def cmd_gate(args: argparse.Namespace) -> int:
    """`hil-gateway compare --baseline RUN_DIR RUN_DIR… --tolerance FILE.toml [--junit
    FILE.xml]`: each run's metrics against the baseline's within the tolerance file's
    limits; the table of checks, the JUnit XML; exit 0 passed, 1 a metric beyond its
    limit, 2 a metric that cannot be compared or bad input."""
    from gateway import gate, report
    from gateway.atomicfile import write_text_atomic
    from gateway.junit import junit_xml
    from gateway.rundir import run_labels
    from gateway.tolerance import load_tolerances

    if not args.tolerance:
        raise UserError("--baseline needs --tolerance FILE.toml: the limits of each metric, "
                        "by the dotted key of summary.json (e.g. examples/tolerance.toml)")
    figure = _figure_path(args) if args.output else None
    limits = load_tolerances(Path(args.tolerance))
    baseline = report.load_summary(Path(args.baseline))
    paths = [Path(d) for d in args.runs]
    runs = list(zip(run_labels(paths), [report.load_summary(p) for p in paths], strict=True))
    checks = gate.evaluate(baseline, runs, limits)
    print(f"regression gate: baseline {args.baseline}, limits {args.tolerance}")
    print(gate.table(checks))
    if args.junit:
        xml = junit_xml(checks, [("baseline", str(args.baseline)),
                                 ("tolerance", str(args.tolerance))])
        try:
            write_text_atomic(Path(args.junit), xml)
        except OSError as exc:
            raise UserError(f"--junit {args.junit!r}: cannot write it "
                            f"({exc.strerror or exc}); choose a writable place") from exc
        print(f"wrote {args.junit}")
    if figure is not None:  # only when asked for: the gate's output is the table
        _write_figure(figure, [report.load_run(Path(args.baseline)),
                               *(report.load_run(p) for p in paths)])
    problems = gate.errors(checks)
    if problems:
        raise UserError(f"{len(problems)} metric(s) cannot be compared: "
                        + "; ".join(problems))
    return gate.exit_status(checks)


# ----------------------------------------------------------------------------- report


def cmd_report(args: argparse.Namespace) -> int:
    """`hil-gateway report RUN_DIR…`: one self-contained HTML page of a run (report.html in
    its directory), or of several runs side by side (-o FILE, default ./compare.html)."""
    from gateway import htmlreport
    from gateway.rundir import REPORT_FILE

    if args.output:  # checked before anything is read or drawn
        htmlreport.check_output(Path(args.output))
    from gateway.campaign.table import is_campaign

    if any(is_campaign(Path(d)) for d in args.runs):
        return _report_campaign(args)
    runs = [htmlreport.load(Path(d)) for d in args.runs]
    if args.output:
        out = Path(args.output)
    elif len(runs) == 1:
        out = runs[0].path / REPORT_FILE
    else:
        out = Path(htmlreport.COMPARISON_NAME)
    written = htmlreport.write_report(runs, out)
    print(f"wrote {written}")
    return 0


def _report_campaign(args: argparse.Namespace) -> int:
    """`hil-gateway report CAMPAIGN_DIR`: the campaign's table as one HTML page
    (CAMPAIGN_DIR/report.html, or -o FILE)."""
    from gateway import htmlreport
    from gateway.atomicfile import write_text_atomic
    from gateway.campaign.htmlpage import render
    from gateway.campaign.table import open_table
    from gateway.rundir import REPORT_FILE

    if len(args.runs) != 1:
        raise UserError(f"report {' '.join(args.runs)}: a campaign's page is of one campaign; "
                        "give its directory alone (runs are compared with several run "
                        "directories)")
    table, meta, where = open_table(args.runs[0])
    out = Path(args.output) if args.output else where / REPORT_FILE
    text = render(table.to_pylist(), meta, where)
    try:
        written = write_text_atomic(htmlreport.check_output(out), text)
    except OSError as exc:
        raise UserError(f"cannot write the report to {str(out)!r}: {exc.strerror or exc}; "
                        "choose a writable place with -o FILE.html") from exc
    print(f"wrote {written}")
    return 0


# ------------------------------------------------------------------------------- main


class _Parser(argparse.ArgumentParser):
    """argparse with a one-paragraph error: what is wrong and where the help is, not the
    whole usage (subcommand parsers are of this class too)."""

    def error(self, message: str) -> NoReturn:
        self.exit(2, f"{self.prog}: error: {message} (see {self.prog} --help)\n")


#: A negative number with or without a unit (``-1ms``, ``-0.5s``): a value, not an option.
_NEGATIVE = re.compile(r"^-\.?\d")


def _values_not_options(argv: Sequence[str]) -> list[str]:
    """``--period -1ms`` → ``--period=-1ms``: argparse would take a negative value with a
    unit for an option and say only "expected one argument"; as a value it reaches its
    parser, which says what is wrong with it."""
    out: list[str] = []
    for a in argv:
        if (out and _NEGATIVE.match(a) and out[-1].startswith("--") and "=" not in out[-1]):
            out[-1] = f"{out[-1]}={a}"
        else:
            out.append(a)
    return out


def build_parser(command: str | None = None) -> argparse.ArgumentParser:
    """The argument parser of `hil-gateway`: all subcommands, or only ``command`` when it
    is one of this module's (:data:`LOCAL_COMMANDS`): a `simulate` does not wait for the
    imports of the others (`sim`, `run`, `log`, `scan`, `check` and `bridge` import
    python-can and python-canopen)."""
    parser = _Parser(
        prog=PROG,
        description="CANopen hardware-in-the-loop gateway: the sensorless speed and flux "
                    "controller of Marino, Tomei & Verrelli (2002) against a CiA 402 drive, "
                    "real or emulated, or simulated without CAN.",
        epilog=EPILOG, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--debug", action="store_true",
                        help="show tracebacks and debug logging")
    sub = parser.add_subparsers(dest="command", metavar="COMMAND")
    if command in LOCAL_COMMANDS:
        LOCAL_COMMANDS[command](sub)
    else:
        _add_simulate(sub)
        _add_sim(sub)
        _add_run(sub)
        from gateway import bridgecmd, buslog, check, scan

        buslog.add_parser(sub)
        scan.add_parser(sub)
        check.add_parser(sub)
        bridgecmd.add_parser(sub)
        _add_compare(sub)
        _add_report(sub)
        _add_scope(sub)
        _add_reference(sub)
        from gateway import identifycmd

        identifycmd.add_parser(sub)
        from gateway.campaign import command as campaign

        campaign.add_parser(sub)
    _debug_everywhere(parser)
    return parser


def _command_of(argv: Sequence[str]) -> str | None:
    """The subcommand ``argv`` names (its first word that is not an option), or None."""
    return next((a for a in argv if not a.startswith("-")), None)


def _add_simulate(sub: Any) -> None:
    """`simulate`: the closed loop without CAN."""
    p = sub.add_parser(
        "simulate", help="the closed loop without CAN (continuous or sampled); no bus at all",
        description="Run the closed loop without CAN: continuous time with scipy, or sampled "
                    "exactly as over the bus (zero-order hold, optional one-period SYNC delay, "
                    "INT16 PDO quantisation). Writes summary.json, signals.csv and the figures. "
                    "A loop that leaves the divergence envelope of the bus loop (speed, "
                    "current, flux, voltage or speed error beyond the profile's demand + "
                    "margin, or field orientation lost, 3 cycles in a row) is stopped there. "
                    "A sampled run injects the bus faults of a --plant scenario "
                    "([[bus.fault]]) on its PDO frames, with the bus loop's reactions (as "
                    "`sim` in lockstep). Exit status: 0 at the profile's end, 1 diverged or "
                    "stopped by a bus fault, 130 interrupted, 2 bad input.")
    _add_control_options(p)
    from dbc.modes import DriveMode, SetpointFrame

    p.add_argument("--drive-mode", "--drive", dest="drive_mode", type=DriveMode,
                   choices=list(DriveMode),
                   help="the emulated drive's mode: ideal current source, PI current loop at "
                        "10 kHz, voltage-fed, or a standard drive's torque (CST) or velocity "
                        "(CSV) mode with its own field orientation (default: ideal for "
                        "current-fed, voltage for full-order, torque for speed-pi, velocity "
                        "for stream); --drive is the old spelling")
    p.add_argument("--period", default="1ms",
                   help="sampling period with its unit, 100us … 100ms in whole µs (1ms, "
                        "250us, ...), or 'continuous' (default 1ms)")
    p.add_argument("--setpoint-frame", type=SetpointFrame, choices=list(SetpointFrame),
                   default=SetpointFrame.DQ,
                   help="dq: the drive turns the frame itself (docs/paper.md §E9); ab: setpoints "
                        "held in the fixed frame over the period")
    p.add_argument("--delay", type=int, choices=(0, 1), default=1,
                   help="periods between a sample and its setpoints acting (1 = CANopen SYNC)")
    _add_plant_option(p)
    p.add_argument("--no-quantize", action="store_true",
                   help="skip the INT16 quantisation of the PDO signals")
    p.add_argument("--duration", help="simulate this long instead of the profile's duration "
                   "(10s, 500ms; a bare number is seconds)")
    _add_output_options(p, "runs/<time>-simulate-<law>")
    p.set_defaults(func=cmd_simulate)


def _add_sim(sub: Any) -> None:
    """`sim`: the loop over CANopen against the emulator in this process."""
    p = sub.add_parser(
        "sim", help="the loop over CANopen against the emulated drive, in one process",
        description="Run the sensorless loop over CANopen against the emulated CiA 402 drive "
                    "started in the same process (in-process channel by default, or "
                    "python-can's virtual bus): no hardware, no setup. It is `run` with the "
                    "emulator built in; `simulate` is the same loop without CAN. Writes the "
                    "run directory like `run`.")
    _add_run_options(p)
    from gateway.transport import TRANSPORTS

    p.add_argument("--transport", choices=TRANSPORTS, default="inprocess",
                   help="inprocess (default): a python-can bus that hands each receiver the "
                        "same frame; virtual: python-can's virtual interface, which deep-copies "
                        "every frame per receiver (about half the cycles per second)")
    _add_plant_option(p)
    p.set_defaults(func=cmd_sim)


def _add_run(sub: Any) -> None:
    """`run`: the loop against a drive on a CAN bus."""
    from dbc.bus import add_bus_options

    p = sub.add_parser(
        "run", help="the loop against a drive on a CAN bus (real, or `hil-plant run`)",
        description="Bring the drive up (NMT, SDO configuration, CiA 402 enable), run the "
                    "sensorless loop over PDOs for the profile, bring it down safely, and write "
                    "the run directory: raw bus log, signals.csv, summary.json, figures.")
    add_bus_options(p)
    _add_run_options(p)
    p.add_argument("--drive", metavar="PROFILE", help="drive profile (TOML); default: the "
                   "emulator (gateway/drives/emulator.toml)")
    p.set_defaults(func=cmd_run)


def cmd_scope(args: argparse.Namespace) -> int:
    """`hil-gateway scope RUN_DIR`: a finished run in the live scope's page."""
    import time

    from gateway import report
    from gateway.scope import ScopeFeed, ScopeServer, parse_address

    run = report.load_run(Path(args.run))
    host, port = parse_address(args.scope)
    if not run.signals:
        raise UserError(f"{args.run}: no signals.csv to show (the run wrote none)")
    feed = ScopeFeed(f"{run.name} (finished)")
    feed.load(run.signals)
    feed.finish(run.summary)
    server = ScopeServer(feed, host, port)
    until = f"for {args.hold:g} s" if args.hold else "until Ctrl-C"
    print(f"scope: {server.url} shows {args.run} ({len(run.signals['t'])} rows); serving "
          f"{until}", flush=True)
    try:
        time.sleep(args.hold) if args.hold else _wait_forever()
    except KeyboardInterrupt:
        pass
    finally:
        server.close()
    return 0


def _wait_forever() -> None:
    import threading

    threading.Event().wait()


def _add_scope(sub: Any) -> None:
    p = sub.add_parser(
        "scope", help="open a finished run in the live scope's web page",
        description="Serve a run directory's signals.csv in the live scope's page (the page "
                    "that --scope serves while a run happens): choose signals, pause, zoom, "
                    "time base, trigger. Serves until Ctrl-C (or --hold seconds).")
    p.add_argument("run", metavar="RUN_DIR", help="a run directory (with signals.csv)")
    p.add_argument("--scope", metavar="[HOST:]PORT", default="127.0.0.1:8765",
                   help="where to serve the page (default 127.0.0.1:8765; PORT 0: any free "
                        "port, printed)")
    p.add_argument("--hold", type=float, default=0.0, metavar="S",
                   help="serve for this many seconds, then exit (default: until Ctrl-C)")
    p.set_defaults(func=cmd_scope)


def _add_compare(sub: Any) -> None:
    """`compare`: runs side by side."""
    p = sub.add_parser(
        "compare", help="compare runs: errors side by side, configuration differences, "
                        "figure; or gate them against a baseline (--baseline)",
        description="Compare run directories (of simulate, sim or run): print the errors of "
                    "each side by side with the configuration keys that differ, and write a "
                    "figure with every run's speed and flux errors overlaid (compare.png in "
                    "the current directory, or -o FILE; the run directories are left as "
                    "their runs wrote them). With --baseline, the regression gate instead: "
                    "each RUN_DIR's metrics against the baseline run's, within the limits "
                    "of --tolerance FILE.toml (by the dotted key of summary.json, e.g. "
                    "\"speed_error.rms\" = { rel = 0.2, abs = 1e-4 }: a run fails when the "
                    "metric grew by more than abs + rel·|baseline|; direction = \"down\" or "
                    "\"both\" for a decrease or either way); prints a table of every check "
                    "and writes JUnit XML with --junit; exit status 0 all within, 1 a "
                    "metric beyond its limit, 2 a metric that cannot be compared (missing, "
                    "not a number) or a bad tolerance file. See docs/outputs.md.")
    p.add_argument("runs", nargs="+", metavar="RUN_DIR")
    p.add_argument("-o", "--output", metavar="FILE",
                   help="figure file, .png, .svg or .pdf (default ./compare.png; with "
                        "--baseline only when given)")
    p.add_argument("--baseline", metavar="RUN_DIR",
                   help="the run the others are measured against: the regression gate")
    p.add_argument("--tolerance", metavar="FILE.toml",
                   help="the limits of the regression gate, per metric (template: "
                        "examples/tolerance.toml)")
    p.add_argument("--junit", metavar="FILE.xml",
                   help="write the gate's checks as JUnit XML (a test suite per run, a test "
                        "case per metric), complete or not at all")
    p.set_defaults(func=cmd_compare)


def _add_report(sub: Any) -> None:
    """`report`: a run as one HTML page."""
    p = sub.add_parser(
        "report", help="one self-contained HTML page of a run, or of several side by side",
        description="Write one HTML file that opens offline (figures embedded, no other "
                    "file): the run's configuration, outcome (stop, reason, exit status, "
                    "shutdown), identification, metrics overall and per window, figures, "
                    "bus timing and counters, faults, and every other section of its "
                    "summary.json. One RUN_DIR: RUN_DIR/report.html (replaced when written "
                    "again). Several: one comparison page (outcomes and metrics side by "
                    "side, configuration differences, errors overlaid, each run below), "
                    "./compare.html or -o FILE. A run that did not finish (only running.json) "
                    "is reported as such. A campaign's directory: its page (the statuses, "
                    "the pass criteria, the worst points with the command that reproduces "
                    "each, the figures, the points worst first) as DIR/report.html. "
                    "Exit status 0 when the page is written (whatever "
                    "the runs' own), 2 for a directory that is not a run or a file that "
                    "cannot be written. See docs/outputs.md.")
    p.add_argument("runs", nargs="+", metavar="RUN_DIR",
                   help="run directories written by simulate, sim or run; or one campaign's "
                        "directory (its --out DIR) or results.parquet")
    p.add_argument("-o", "--output", metavar="FILE.html",
                   help="the page to write (default: RUN_DIR/report.html for one run, "
                        "./compare.html for several); written completely or not at all")
    p.set_defaults(func=cmd_report)


def _add_reference(sub: Any) -> None:
    """`reference` (alias `profile`): check, plot, new-drive, dbc."""
    p = sub.add_parser("reference", aliases=["profile"],
                       help="check or plot a reference profile (alias: profile)",
                       description="Validate or plot a reference profile ω*(t), ψ*(t), T_L(t) "
                                   "(TOML). (A drive profile, --drive, describes a drive.)")
    psub = p.add_subparsers(dest="profile_command", metavar="ACTION")
    pc = psub.add_parser("check", help="validate; print the set points and peak demands (a "
                                       "drive profile: its signals against its EDS)",
                         description="Validate a reference profile, print its set points and "
                                     "the peak current and voltage it demands from the motor. "
                                     "Given a drive profile (a TOML with [drive]), check it "
                                     "off line: every PDO signal against the EDS object it "
                                     "maps (exists, PDO-mappable, size, access) and which "
                                     "drive modes it can run, and the bus time of its cycle "
                                     "and the bus load at --period; exit 1 if a signal does "
                                     "not fit.")
    pc.add_argument("file", metavar="FILE")
    pc.add_argument("--motor", metavar="FILE", help="motor parameters (TOML)")
    pc.add_argument("--period", default="1ms", help="a drive profile: the cycle period its "
                    "bus load is given for (default 1ms)")
    pc.set_defaults(func=cmd_profile_check)
    pp = psub.add_parser("plot", help="plot the references and their derivatives",
                         description="Plot ω*, ψ*, T_L and their time derivatives (each on "
                                     "its own axis, in real units) of a profile.")
    pp.add_argument("file", metavar="FILE")
    pp.add_argument("-o", "--output", metavar="FILE",
                    help="output file, .png, .svg or .pdf (default runs/profile-<FILE's "
                         "stem>.png; an existing file is replaced)")
    pp.set_defaults(func=cmd_profile_plot)
    from gateway import dbcfile, newdrive  # new-drive: a skeleton; dbc: the bus's DBC

    newdrive.add_action(psub)
    dbcfile.add_action(psub)
    p.set_defaults(func=lambda a: _usage(p))


#: The subcommands defined in this module, by name, and what registers each (the others live
#: in their own modules: gateway.buslog, scan, check, bridgecmd).
LOCAL_COMMANDS: dict[str, Callable[[Any], None]] = {
    "simulate": _add_simulate, "sim": _add_sim, "run": _add_run, "compare": _add_compare,
    "scope": _add_scope, "reference": _add_reference, "profile": _add_reference,
    "report": _add_report,
}


def _debug_everywhere(parser: argparse.ArgumentParser) -> None:
    """--debug also after the subcommand (``hil-gateway sim --debug``), as in hil-plant:
    every subparser gets it with default SUPPRESS, so the top-level value stands unless
    given there."""
    for action in parser._actions:
        if isinstance(action, argparse._SubParsersAction):
            for sub in {id(p): p for p in action.choices.values()}.values():
                if "--debug" not in sub._option_string_actions:
                    sub.add_argument("--debug", action="store_true", default=argparse.SUPPRESS,
                                     help="show tracebacks and debug logging")
                _debug_everywhere(sub)


def _usage(p: argparse.ArgumentParser) -> int:
    p.print_help(sys.stderr)
    return 2


def main(argv: Sequence[str] | None = None) -> int:
    """Entry point of `hil-gateway`; returns the exit status."""
    # numpy's OpenBLAS starts a thread per core that spins on import (0.1 s of CPU taken
    # from the figure worker); nothing here multiplies matrices large enough to need them
    os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")
    argv = list(sys.argv[1:] if argv is None else argv)
    if _command_of(argv) == "campaign":  # `campaign show` is one word for argparse
        from gateway.campaign.command import rewrite

        argv = rewrite(argv)
    argv = _values_not_options(argv)
    parser = build_parser(_command_of(argv))
    if _command_of(argv) == "identify":  # the other options are those of the command it runs
        args, args.options = parser.parse_known_args(argv)
    else:
        args = parser.parse_args(argv)
    logging.basicConfig(level=logging.DEBUG if args.debug else logging.WARNING,
                        format="%(levelname)s %(name)s: %(message)s")
    if not args.debug:
        # python-canopen logs an ERROR for each SDO transfer it aborts (an unanswered read:
        # "Transfer aborted by client with code 0x05040000"); every SDO failure reaches the
        # user as the gateway's own message (what, where, what to do), so not twice
        logging.getLogger("canopen.sdo.client").setLevel(logging.CRITICAL)
    func: Callable[[argparse.Namespace], int] | None = getattr(args, "func", None)
    if func is None:
        parser.print_help(sys.stderr)
        return 2
    try:
        return func(args)
    except UserError as exc:
        if args.debug:
            raise
        print(f"{PROG}: error: {exc}", file=sys.stderr)
        return exc.exit_code
    except KeyboardInterrupt:
        print(f"{PROG}: interrupted", file=sys.stderr)
        return 130
    except BrokenPipeError:  # `hil-gateway sim | head`: the reader left; the files are written
        devnull = os.open(os.devnull, os.O_WRONLY)
        os.dup2(devnull, sys.stdout.fileno())  # no second error when Python flushes stdout
        return 1


if __name__ == "__main__":  # pragma: no cover
    sys.exit(main())
