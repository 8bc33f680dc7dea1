"""A whole gateway run: bring the drive up, loop, bring it down safely, write the run directory.

Used by `hil-gateway run` (any python-can bus) and `hil-gateway sim` (the emulator in the
same process on python-can's virtual bus). The order is fixed and every exit path —
end of profile, Ctrl-C, SIGTERM, a drive fault or loss, an error — goes through the same
shutdown: no more SYNC, controlword "disable voltage", NMT PRE-OPERATIONAL, heartbeat off,
bus log flushed and closed; the caller shuts the bus down.
"""

from __future__ import annotations

import logging
import math
import signal
import threading
import time
from collections.abc import Callable, Iterator
from contextlib import contextmanager
from dataclasses import asdict, dataclass, field, replace
from pathlib import Path
from typing import Any

import can
import numpy as np

from dbc.cia301 import HEARTBEAT_BASE, SYNC_OVERFLOW
from dbc.modes import DriveMode, SetpointFrame
from dbc.motor import MotorParams
from dbc.signals import SETPOINTS
from dbc.timing import Sampling, TimeBase, internal_rate
from gateway import report
from gateway.buslog import LOG_SUFFIXES, BusRecorder
from gateway.control.controller import (
    ControllerConfig,
    Discretisation,
    EstimatorKind,
    FluxSource,
    Law,
    LoadSource,
    as_enum,
    euler_only,
)
from gateway.control.interface import ControllerChoice, ControllerContext, summary_of
from gateway.control.laws import Gains
from gateway.control.load_observer import load_config
from gateway.drive_profile import DriveProfile
from gateway.errors import UserError
from gateway.guard import Envelope, Plausibility, profile_envelope
from gateway.loop import CycleLoop, LoopConfig, Timing
from gateway.master import DriveMaster
from gateway.process_data import ProcessData, process_data
from gateway.reference import Profile
from gateway.reference.demand import sample_times
from gateway.results import Reporting, merge_truth, write_results, write_summary_noting
from gateway.stop import StopReason

log = logging.getLogger(__name__)


@dataclass(frozen=True)
class RunConfig:
    """One gateway run.

    drive_mode: what the drive is asked to be (:class:`DriveMode`): IDEAL or CURRENT_LOOP
        (CiA 402 current vector mode; on the emulator also its model of the current loop)
        or VOLTAGE (voltage vector mode). sampling: period, delay (1 = synchronous RPDOs,
        CiA 301 default; 0 = the emulator applies RPDOs on receipt) and the setpoint frame
        (the drive profile's). bus_log: file name of the raw bus log in the run directory;
        its suffix picks the python-can writer. discretisation: EXACT (the sampled-data
        design, docs/sampled-control.md) or EULER.
        plant_scenario: the resolved plant scenario of `sim` (docs/robustness.md), None
        when the plant is not ours to know (`run`). load: :class:`LoadSource`. Strings are
        accepted for the enums.
    """

    law: Law = Law.CURRENT_FED
    flux: FluxSource = FluxSource.ESTIMATED
    estimator: EstimatorKind = EstimatorKind.OPEN_LOOP
    drive_mode: DriveMode = DriveMode.IDEAL
    sampling: Sampling = field(default_factory=Sampling)
    timing: Timing = Timing.LOCKSTEP
    gains: Gains = field(default_factory=Gains)
    bus_log: str = "bus.blf"
    max_missed: int = 5
    max_miss_rate: float = 0.2
    duration: float | None = None
    discretisation: Discretisation = Discretisation.EXACT
    plant_scenario: dict[str, Any] | None = None
    load: LoadSource = LoadSource.KNOWN
    identify: bool = False
    controller: ControllerChoice = field(default_factory=ControllerChoice)

    def __post_init__(self) -> None:
        try:
            for name, enum, what in (("law", Law, "law"), ("flux", FluxSource, "flux source"),
                                     ("estimator", EstimatorKind, "estimator"),
                                     ("drive_mode", DriveMode, "drive mode"),
                                     ("timing", Timing, "timing"),
                                     ("discretisation", Discretisation, "discretisation"),
                                     ("load", LoadSource, "load mode")):
                object.__setattr__(self, name, as_enum(enum, getattr(self, name), what))
            euler_only(self.discretisation, self.load)
            load_config(self.load, self.drive_mode)
        except ValueError as exc:
            raise UserError(str(exc)) from None
        if Path(self.bus_log).suffix.lower() not in LOG_SUFFIXES:
            raise UserError(f"bus log {self.bus_log!r}: the file name must end in one of "
                            f"{', '.join(LOG_SUFFIXES)} (it selects python-can's writer)")

    @property
    def period(self) -> float:
        """The cycle period T, s (from :attr:`sampling`)."""
        return self.sampling.period

    def controller_config(self, current_lag: float = 0.0) -> ControllerConfig:
        """The controller's part; ``current_lag``: the drive's current response time, s."""
        return ControllerConfig(law=self.law, flux=self.flux, estimator=self.estimator,
                                sampling=self.sampling, gains=self.gains,
                                discretisation=self.discretisation, current_lag=current_lag,
                                load=self.load, **load_config(self.load, self.drive_mode),
                                identify=self.identify)


class StopSignals:
    """SIGINT/SIGTERM → a stop request; a second signal during shutdown is refused politely.

    The drive is brought down by the normal shutdown path; a second Ctrl-C cannot skip it
    and leave the drive enabled.
    """

    def __init__(self) -> None:
        self.requested = threading.Event()
        self.reason = ""
        self.on_stop: Callable[[str], None] | None = None
        self.shutting_down = False
        self._old: dict[int, Any] = {}

    def _handler(self, signum: int, frame: Any) -> None:
        name = signal.Signals(signum).name
        if self.requested.is_set():
            print(f"\n{name} again: shutting the drive down safely, please wait", flush=True)
            return
        self.reason = f"{name} received"
        self.requested.set()
        if self.on_stop is not None:
            self.on_stop(self.reason)
        elif not self.shutting_down:
            raise KeyboardInterrupt  # start-up: abort into the shutdown path

    @contextmanager
    def installed(self) -> Iterator[StopSignals]:
        if threading.current_thread() is not threading.main_thread():
            yield self
            return
        for sig in (signal.SIGINT, signal.SIGTERM):
            self._old[sig] = signal.signal(sig, self._handler)
        try:
            yield self
        finally:
            for sig, old in self._old.items():
                signal.signal(sig, old)


def _eds_default(master: DriveMaster, name: str) -> float:
    """The default value the drive's EDS gives an object (the emulator's own objects)."""
    var = master.find_object(name)
    if var is None or var.default is None:
        raise UserError(f"the drive's EDS ({master.profile.eds}) has no default for {name!r}, "
                        "which the emulator's drive profile needs")
    return float(var.default)


def required_roles(cfg: RunConfig, pd: ProcessData, requires: tuple[str, ...] = ()
                   ) -> tuple[str, ...]:
    """The roles a run needs of the drive: CiA 402 words, the measured currents and applied
    voltages, the frame for (d, q) setpoints, the setpoints the drive mode uses, the true
    flux only for ``--flux true``, and what the controller ``requires`` (its optional
    attribute, e.g. ``("w_m",)``: a speed sensor)."""
    frame = pd.setpoint_frame
    i1, i2, u1, u2 = SETPOINTS[frame]
    roles = ["controlword", "statusword", "i_sa", "i_sb", "u_sa", "u_sb"]
    if frame is SetpointFrame.DQ:
        roles += ["eps_0", "w_0"]
    roles += [u1, u2] if cfg.drive_mode is DriveMode.VOLTAGE else [i1, i2]
    if cfg.flux is FluxSource.TRUE and cfg.controller.is_paper:
        roles += ["psi_ra", "psi_rb"]
    roles += [r for r in requires if r not in roles]
    return tuple(roles)


def guards(drive: DriveProfile, profile: Profile, motor: MotorParams, cfg: RunConfig
           ) -> tuple[Plausibility, Envelope]:
    """The plausibility limits of the drive (its profile's [limits]; without them 1.5 × the
    controller's current limit) and the divergence envelope of the reference profile."""
    plaus = Plausibility(
        i_peak=drive.current_peak_a or 1.5 * cfg.gains.i_max,
        u_dc_min=drive.dc_link_v[0] if drive.dc_link_v else None,
        u_dc_max=drive.dc_link_v[1] if drive.dc_link_v else None)
    return plaus, profile_envelope(profile, motor, cfg.gains.i_max)


def _load_note(cfg: RunConfig, pd: Any, profile: Any, duration: float) -> str:
    """The note for a run on a drive that cannot apply the profile's load torque (no T_L role
    in its process data: no dynamometer the gateway commands) while the profile has one, or
    "". By default such a run does not tell the laws that load (``untold``); told
    anyway (``--load known``), the laws feed forward a torque the shaft may not carry."""
    if cfg.load is LoadSource.OBSERVED or "T_L" in pd.roles:
        return ""
    t = sample_times(profile)  # every transition resolved, bounded for long profiles
    peak = float(np.max(np.abs(profile.sample(np.append(t[t < duration], duration))["T_L"])))
    if peak == 0.0:
        return ""
    if cfg.load is LoadSource.UNTOLD:
        return (f"the profile's load torque (up to {peak:g} N·m) is not told to the "
                "controller: this drive cannot apply it (its process data has no T_L), so the "
                "laws assume no load (--load untold, the default here). If the shaft carries "
                "that load some other way, use --load known; a larger load than the laws "
                "tolerate untold is stopped by the orientation guard (docs/robustness.md §2)")
    return (f"the controller is told the profile's load torque (up to {peak:g} N·m), which "
            "this drive cannot apply (its process data has no T_L): the shaft must carry "
            "that load, else the laws feed forward a torque that is not there. Use a profile "
            "whose [load] is what the shaft carries, --load untold (the default for this "
            "drive), or --load observed (estimated; its limits are in docs/robustness.md)")


def run_gateway(
    bus: can.BusABC,
    drive: DriveProfile,
    profile: Profile,
    motor: MotorParams,
    cfg: RunConfig,
    out: Path,
    node: int | None = None,
    own_echo: bool = True,
    progress: Callable[[float], None] | None = None,
    signals: StopSignals | None = None,
    bus_label: str = "",
    gateway_node: int | None = None,
    reporting: Reporting | None = None,
) -> dict[str, Any]:
    """Run the loop against the drive on ``bus``; returns the summary (also written to out/).

    summary.json is written before the loop starts (``run.status = "running"``) and
    replaced atomically at the end, so a crash leaves the configuration and the status; the
    bus log is flushed every second. The results are written once, at the end
    (:func:`gateway.results.write_results`), as ``reporting`` says.
    """
    reporting = reporting or Reporting()
    node_id = node or drive.node
    pd = process_data(drive, node_id)
    if cfg.sampling.setpoint_frame != pd.setpoint_frame:
        raise UserError(f"the run's setpoint frame {cfg.sampling.setpoint_frame} is not the "
                        f"drive profile's ({pd.setpoint_frame}, {drive.source})")
    duration = cfg.duration or profile.duration
    n_cycles = round(duration / cfg.period)
    load_note = _load_note(cfg, pd, profile, duration)
    if load_note:
        log.warning("%s", load_note)
    plausibility, envelope = guards(drive, profile, motor, cfg)
    loop_cfg = LoopConfig(n_cycles=n_cycles, sampling=cfg.sampling, timing=cfg.timing,
                          max_missed=cfg.max_missed, max_miss_rate=cfg.max_miss_rate,
                          plausibility=plausibility,
                          envelope=envelope)
    signals = signals or StopSignals()
    configuration = _configuration(cfg, drive, profile, node_id, bus_label,
                                   reporting.command)
    recorder = BusRecorder(out / cfg.bus_log)
    master = DriveMaster(bus, drive, node_id, gateway_node)
    if load_note:
        master.notes.append(load_note)
    loop: CycleLoop | None = None
    stats = None
    error: BaseException | None = None
    t_start = time.time()
    try:
        master.connect(listeners=[recorder])
        # the exact design models what the drive applies: for the emulator's PI current loop
        # its response time (1/bandwidth, from its EDS); a real drive is taken as ideal
        lag = (1.0 / _eds_default(master, "current_loop_bw")
               if drive.emulator and cfg.drive_mode is DriveMode.CURRENT_LOOP else 0.0)
        paper = cfg.controller_config(lag)
        ctl = cfg.controller.make(ControllerContext(
            motor=motor, sampling=cfg.sampling, refs_at=profile.at, drive_mode=cfg.drive_mode,
            current_lag=lag, paper=paper))
        who = (f"the {cfg.law} law" if cfg.controller.is_paper
               else f"controller {cfg.controller.name}")
        pd.require(required_roles(cfg, pd, getattr(ctl, "requires", ())),
                   f"{who} with a {cfg.drive_mode} drive", master.node.object_dictionary.indices)
        mode = (drive.mode_voltage if cfg.drive_mode is DriveMode.VOLTAGE
                else drive.mode_current)
        emulator: dict[str, int | float] = {}
        if drive.emulator:
            # lockstep: the emulator supervises the gateway's heartbeat in simulated time
            time_base = TimeBase.SYNC if cfg.timing is Timing.LOCKSTEP else TimeBase.WALL
            emulator = {"Emulator model": cfg.drive_mode.emulator_model,
                        "RPDO apply": int(cfg.sampling.apply),
                        "Time base": int(time_base),
                        "f_pwm": round(internal_rate(_eds_default(master, "f_pwm"), cfg.period))}
        elif cfg.sampling.delay != 1:
            raise UserError("--delay 0 (RPDOs applied on receipt) is an emulator option; a "
                            "CiA 402 drive applies synchronous RPDOs at the next SYNC (--delay 1)")
        counter = master.configure(cfg.period, pd, drive.remap, mode, emulator,
                                   sync_overflow=SYNC_OVERFLOW)
        lockstep = cfg.timing is Timing.LOCKSTEP
        loop_cfg = replace(loop_cfg, sync_counter=counter)
        if lockstep:  # the gateway's heartbeat in the loop's time too (LoopConfig)
            loop_cfg = replace(loop_cfg, heartbeat_cob_id=HEARTBEAT_BASE + master.gateway_node,
                               heartbeat_every=max(1, math.floor(
                                   master.heartbeat_period / cfg.period + 1e-9)))
        master.start(lockstep=lockstep, alive_ids=[p.cob_id for p in pd.tpdos] if lockstep
                     else ())
        master.enable()

        def fault_cause() -> tuple[StopReason, str] | None:
            f = master.first_fault
            return None if f is None else (f.reason, f.describe())

        loop = CycleLoop(bus, master.network.subscribe, pd, ctl, profile, loop_cfg,
                         own_echo=own_echo, fault=master.fault, fault_cause=fault_cause)
        write_summary_noting(out, {"run": {"status": "running", "started": t_start},
                                    "configuration": configuration}, [])
        signals.on_stop = loop.request_stop
        if signals.requested.is_set():
            loop.request_stop(signals.reason)
        stats = loop.run(progress)
        if stats.stop is StopReason.DRIVE_LOST:
            # TPDOs stop before the heartbeat tells why (a reset, NMT pre-operational): give
            # the drive one heartbeat to name the cause
            master.fault.wait(1.5 * drive.heartbeat_ms / 1e3)
    except KeyboardInterrupt:
        error = None
        signals.reason = signals.reason or "interrupted during start-up"
    except BaseException as exc:
        error = exc
    finally:
        signals.shutting_down = True
        signals.on_stop = None
        master.shutdown()
        recorder.stop()
    if error is not None:
        raise error
    return _summarise(loop, stats, master, recorder, cfg, drive, out, configuration,
                      signals.reason, t_start, reporting)


def _configuration(cfg: RunConfig, drive: DriveProfile, profile: Profile, node_id: int,
                   bus_label: str, command: str = "run") -> dict[str, Any]:
    return {
        "command": command, "bus": bus_label, "node": node_id, "drive_profile": drive.source,
        "profile": profile.source,
        **{k: v for k, v in asdict(cfg).items() if k not in ("gains", "sampling")},
        "period": cfg.period, "delay": cfg.sampling.delay,
        "gains": asdict(cfg.gains), "setpoint_frame": cfg.sampling.setpoint_frame,
    }


def _final_stop(stats: Any, master: DriveMaster, interrupt_reason: str
                ) -> tuple[StopReason, str]:
    """The run's cause of stopping: the loop's; a drive fault seen after the last cycle
    (an EMCY near the end) turns an ended profile into a failure."""
    if stats is not None and stats.stop is not None:
        stop, message = stats.stop, stats.stop_reason
    else:
        stop, message = StopReason.INTERRUPTED, interrupt_reason or "start-up stopped"
    fault = master.first_fault
    if stop is StopReason.END_OF_PROFILE and fault is not None:
        stop, message = fault.reason, f"{fault.describe()} (after the last cycle)"
    elif stop is StopReason.DRIVE_LOST and fault is not None:
        stop, message = fault.reason, f"{fault.describe()} ({message})"
    return stop, message


def _summarise(loop, stats, master, recorder, cfg, drive, out, configuration,
               interrupt_reason, t_start, reporting: Reporting) -> dict[str, Any]:
    """The summary, then the results written once (:func:`gateway.results.write_results`):
    signals.csv with the emulator's full-resolution truth merged where `sim` has it, the
    metrics over the profile's windows, the figures, summary.json; what cannot be written
    is named in ``summary["write_errors"]`` (and the exit status is then 1)."""
    summary: dict[str, Any] = {}
    write_errors: list[str] = []
    sig = None
    summary["quantisation"] = report.quantisation(True, drive.setpoints)
    if loop is not None and len(loop.record):
        sig = loop.record.arrays()
        if drive.truth:  # tracking errors need the emulator's truth (TPDO3)
            lsb = summary["quantisation"]["signals"]["w_m"]["lsb"]
            summary["truth"] = merge_truth(sig, reporting.truth, cfg.period, lsb)
            summary.update(report.metrics(sig, reporting.windows))
        summary["timing"] = timing_stats(sig, cfg.period, cfg.timing is Timing.REALTIME)
    stop, message = _final_stop(stats, master, interrupt_reason)
    shutdown = master.shutdown_report
    exit_status = stop.exit_status
    if shutdown is not None and not shutdown.safe:
        exit_status = 1
        if stop in (StopReason.END_OF_PROFILE, StopReason.INTERRUPTED):
            stop, message = StopReason.UNSAFE, f"{message}; then {StopReason.UNSAFE.value}"
    summary["run"] = {
        "status": "finished",
        "stop": stop.name,
        "stop_reason": message,
        "exit_status": exit_status,
        "cycles": stats.cycles if stats else 0,
        "missed_cycles": stats.missed if stats else 0,
        "late_rpdo": stats.late_rpdo if stats else 0,
        "rpdo_after_sync": stats.rpdo_after_sync if stats else 0,
        "last_good_cycle": stats.last_good_cycle if stats else 0,
        "tpdo_events": dict(stats.tpdo_events) if stats else {},
        "stop_cycle": stats.stop_cycle if stats else 0,
        "wall_time_s": stats.wall_time if stats else time.time() - t_start,
        **recorder.account(),
    }
    if loop is not None and stop not in (StopReason.END_OF_PROFILE, StopReason.INTERRUPTED):
        summary["run"]["frames_before_stop"] = [
            {"time": t, "dir": d, "cob_id": f"0x{c:03X}", "data": data}
            for t, d, c, data in loop.recent]
    summary["shutdown"] = None if shutdown is None else asdict(shutdown)
    summary["configuration_notes"] = list(master.notes)
    summary["faults"] = [{"time": f.time, "kind": f.kind, "code": f.code, "text": f.text,
                          "reason": f.reason.name} for f in master.state.faults]
    summary["configuration"] = configuration
    found = summary_of(loop.ctl) if loop is not None else None
    if found is not None:
        summary["identification"] = found
    if recorder.error:
        write_errors.append(recorder.error + f" ({recorder.dropped} frames not logged)")
    write_results(out, sig, summary, figures=bool(drive.truth), limits=reporting.limits,
                  delay_s=cfg.sampling.delay * cfg.period, errors=write_errors)
    return summary


def timing_stats(sig: dict[str, np.ndarray], period: float, realtime: bool) -> dict[str, Any]:
    """Medians, p99 and maxima of the per-cycle timing columns, in seconds; the SYNC jitter
    (|SYNC period − T|) only for real-time timing, where SYNC has a schedule."""
    out: dict[str, Any] = {}
    for key in ("sync_period", "sync_to_tpdo", "reaction"):
        x = sig[key]
        x = x[np.isfinite(x)]
        if not x.size:
            continue
        out[key] = {"median": float(np.median(x)), "p99": float(np.percentile(x, 99)),
                    "max": float(np.max(x)), "min": float(np.min(x))}
    if realtime and "sync_period" in out:
        jitter = np.abs(sig["sync_period"][np.isfinite(sig["sync_period"])] - period)
        out["sync_jitter"] = {"median": float(np.median(jitter)),
                              "p99": float(np.percentile(jitter, 99)),
                              "max": float(np.max(jitter))}
    return out


def timing_table(summary: dict[str, Any]) -> str:
    """A few lines on the run's timing and outcome."""
    run = summary["run"]
    split = run.get("rpdo_after_sync", 0)
    lines = [f"cycles {run['cycles']}, missed {run['missed_cycles']}, late RPDO "
             f"{run['late_rpdo']}{f' (+{split} after the SYNC)' if split else ''}, stopped: "
             f"{run['stop_reason']}, wall time {run['wall_time_s']:.2f} s"]
    t = summary.get("timing", {})
    for key, label in (("sync_period", "SYNC period"), ("sync_jitter", "SYNC jitter"),
                       ("sync_to_tpdo", "SYNC → TPDO"), ("reaction", "TPDO → RPDO")):
        if key in t:
            v = t[key]
            lines.append(f"{label:12s} median {1e6 * v['median']:8.1f} us   p99 "
                         f"{1e6 * v['p99']:8.1f} us   max {1e6 * v['max']:8.1f} us")
    for f in summary.get("faults", []):
        code = "" if f["code"] is None else f" 0x{f['code']:04X}"
        lines.append(f"fault: {f['kind']}{code} {f['text']}")
    return "\n".join(lines)
