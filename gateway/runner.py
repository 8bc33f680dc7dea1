"""The loop on a bus: bring the drive up, loop, bring it down safely.

Used by :func:`gateway.session.run` for `hil-gateway run` (any python-can bus) and
`hil-gateway sim` (the emulator in the same process on an in-process bus), which then
writes the run's results. The order is fixed and every exit path —
end of profile, Ctrl-C, SIGTERM, a drive fault or loss, an error — goes through the same
shutdown: no more SYNC, controlword "disable voltage", NMT PRE-OPERATIONAL, heartbeat off,
bus log flushed and closed; the caller shuts the bus down.
"""

from __future__ import annotations

import logging
import math
import time
from collections.abc import Callable
from dataclasses import asdict, dataclass, replace
from pathlib import Path
from typing import Any

import can
import numpy as np

from dbc.cia301 import HEARTBEAT_BASE, SYNC_OVERFLOW
from dbc.modes import DriveMode, SetpointFrame
from dbc.motor import MotorParams
from dbc.signals import SETPOINTS
from dbc.timing import TimeBase, Timing, internal_rate
from gateway import report
from gateway.buslog import BusRecorder
from gateway.control.controller import FluxSource, LoadSource
from gateway.control.interface import ControllerContext, summary_of
from gateway.drive_profile import DriveProfile
from gateway.errors import UserError
from gateway.guard import Envelope, Plausibility, profile_envelope
from gateway.loop import CycleLoop, ErrorFrames, LoopConfig
from gateway.master import DriveMaster
from gateway.process_data import ProcessData, process_data
from gateway.reference import Profile
from gateway.reference.demand import sample_times
from gateway.results import TruthColumns
from gateway.rundir import RUNNING_MARKER
from gateway.spec import RunSpec
from gateway.stop import StopReason, StopSignals

log = logging.getLogger(__name__)


def _eds_default(master: DriveMaster, name: str) -> float:
    """The default value the drive's EDS gives an object (the emulator's own objects)."""
    var = master.find_object(name)
    if var is None or var.default is None:
        raise UserError(f"the drive's EDS ({master.profile.eds}) has no default for {name!r}, "
                        "which the emulator's drive profile needs")
    return float(var.default)


def required_roles(spec: RunSpec, pd: ProcessData, requires: tuple[str, ...] = ()
                   ) -> tuple[str, ...]:
    """The roles a run needs of the drive: the statusword (the controlword too for a standard
    drive), the measured currents and applied voltages (and the DC link where the profile's
    modulator does not compensate it), the frame for (d, q) setpoints, the setpoints the
    drive mode uses, the true flux only for ``--flux true``, and what the controller
    ``requires`` (its optional attribute, e.g. ``("w_m",)``: a speed sensor). A standard
    drive (CST, CSV): the CiA 402 words, its target, and what the controller requires."""
    if spec.drive_mode.standard:  # the drive's own control: its target, its statusword
        assert spec.drive_mode.target is not None
        roles = ["controlword", "statusword", spec.drive_mode.target]
        return tuple(roles + [r for r in requires if r not in roles])
    frame = pd.setpoint_frame
    i1, i2, u1, u2 = SETPOINTS[frame]
    # the controlword may be left to SDO, written when it changes (enable, shutdown) and
    # held by the drive between: a lean mapping (gateway/drives/emulator-lean.toml)
    roles = ["statusword", "i_sa", "i_sb", "u_sa", "u_sb"]
    if pd.modulator_dc_link is not None:  # no DC-link compensation: u_dc scales them
        roles.append("u_dc")
    if frame is SetpointFrame.DQ:
        roles += ["eps_0", "w_0"]
    roles += [u1, u2] if spec.drive_mode is DriveMode.VOLTAGE else [i1, i2]
    if spec.flux is FluxSource.TRUE and spec.controller.is_paper:
        roles += ["psi_ra", "psi_rb"]
    roles += [r for r in requires if r not in roles]
    return tuple(roles)


def guards(drive: DriveProfile, profile: Profile, motor: MotorParams, spec: RunSpec
           ) -> tuple[Plausibility, Envelope]:
    """The plausibility limits of the drive (its profile's [limits]; without them 1.5 × the
    controller's current limit) and the divergence envelope of the reference profile."""
    plaus = Plausibility(
        i_peak=drive.current_peak_a or 1.5 * spec.gains.i_max,
        u_dc_min=drive.dc_link_v[0] if drive.dc_link_v else None,
        u_dc_max=drive.dc_link_v[1] if drive.dc_link_v else None)
    return plaus, profile_envelope(profile, motor, spec.gains.i_max)


def _load_note(spec: RunSpec, pd: Any, profile: Any, duration: float) -> str:
    """The note for a run on a drive that cannot apply the profile's load torque (no T_L role
    in its process data: no dynamometer the gateway commands) while the profile has one, or
    "". By default such a run does not tell the laws that load (``untold``); told
    anyway (``--load known``), the laws feed forward a torque the shaft may not carry."""
    if spec.load is LoadSource.OBSERVED or "T_L" in pd.roles:
        return ""
    t = sample_times(profile)  # every transition resolved, bounded for long profiles
    peak = float(np.max(np.abs(profile.sample(np.append(t[t < duration], duration))["T_L"])))
    if peak == 0.0:
        return ""
    if spec.load is LoadSource.UNTOLD:
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


@dataclass(frozen=True)
class BusTarget:
    """The drive of a bus run and how to reach it.

    drive: its profile (:class:`DriveProfile`); open: opens the bus for a spec, the
    controller's motor and the drive's node id, and returns (the gateway's bus, its label
    such as 'socketcan:vcan0', the function that closes whatever it opened: for `sim` also
    the emulated drive); node, gateway_node: the node ids (None: the drive profile's);
    command: the command's name in the summary (``run``, ``sim``); truth: the emulator's
    full-resolution state by cycle (`sim`, :class:`gateway.sim.TruthRecorder`)."""

    drive: DriveProfile
    open: Callable[[Any, MotorParams, int], tuple[can.BusABC, str, Callable[[], None]]]
    node: int | None = None
    gateway_node: int | None = None
    command: str = "run"
    truth: TruthColumns | None = None

    @property
    def node_id(self) -> int:
        return self.node if self.node is not None else self.drive.node


@dataclass
class BusRun:
    """What the loop on a bus leaves: the record's columns (None: no cycle ran) and the
    summary of the run (its cause of stopping, the timing, the faults, the shutdown), which
    :func:`gateway.session.run` completes with the metrics and writes."""

    sig: dict[str, np.ndarray] | None
    summary: dict[str, Any]


@dataclass(frozen=True)
class _Plan:
    """What a run is checked and set up with before the bus is touched: its target,
    profile, motor and spec, the drive's process data, the loop's configuration, and the
    note on a load the drive cannot apply."""

    target: BusTarget
    profile: Profile
    motor: MotorParams
    spec: RunSpec
    pd: ProcessData
    loop: LoopConfig
    load_note: str


def _plan(target: BusTarget, profile: Profile, motor: MotorParams, spec: RunSpec) -> _Plan:
    drive = target.drive
    pd = process_data(drive, target.node_id)
    if spec.sampling is None:
        raise UserError("a bus run is sampled: choose a --period such as 1ms")
    if spec.sampling.setpoint_frame != pd.setpoint_frame:
        raise UserError(f"the run's setpoint frame {spec.sampling.setpoint_frame} is not the "
                        f"drive profile's ({pd.setpoint_frame}, {drive.source})")
    duration = spec.duration or profile.duration
    load_note = _load_note(spec, pd, profile, duration)
    if load_note:
        log.warning("%s", load_note)
    plausibility, envelope = guards(drive, profile, motor, spec)
    loop = LoopConfig(n_cycles=round(duration / spec.period), sampling=spec.sampling,
                      timing=spec.timing, max_missed=spec.max_missed,
                      max_miss_rate=spec.max_miss_rate, plausibility=plausibility,
                      envelope=envelope)
    return _Plan(target, profile, motor, spec, pd, loop, load_note)


#: Interfaces that deliver this process's own frames back when asked (receive_own_messages).
OWN_ECHO_INTERFACES = ("socketcan", "virtual", "inprocess")


def run_gateway(target: BusTarget, profile: Profile, motor: MotorParams, spec: RunSpec,
                out: Path, progress: Callable[[float], None] | None = None,
                signals: StopSignals | None = None,
                on_record: Callable[[report.Record], None] | None = None) -> BusRun:
    """Open the target's bus and run the loop against its drive; every exit path goes
    through the same shutdown (the module's docstring), then the bus is closed. The raw bus
    log is written (flushed every second) and :data:`RUNNING_MARKER` before the loop
    starts; the results are written by the caller (:func:`gateway.session.run`), once.
    ``on_record``: called with the loop's record before its first cycle (a live scope)."""
    plan = _plan(target, profile, motor, spec)
    bus, label, close = target.open(spec, motor, target.node_id)
    try:
        return _run_on(bus, label, plan, out, progress, signals or StopSignals(), on_record)
    finally:
        close()


def _run_on(bus: can.BusABC, label: str, plan: _Plan, out: Path,
            progress: Callable[[float], None] | None, signals: StopSignals,
            on_record: Callable[[report.Record], None] | None = None) -> BusRun:
    target, profile, spec = plan.target, plan.profile, plan.spec
    node_id = target.node_id
    configuration = _configuration(spec, target, profile, node_id, label)
    recorder = BusRecorder(out / spec.bus_log)
    master = DriveMaster(bus, target.drive, node_id, target.gateway_node)
    if plan.load_note:
        master.notes.append(plan.load_note)
    loop: CycleLoop | None = None
    stats = None
    error: BaseException | None = None
    t_start = time.time()
    try:
        master.connect(listeners=[recorder])
        loop = _bring_up(bus, master, plan, own_echo=label.split(":")[0] in OWN_ECHO_INTERFACES)
        report.write_summary(out / RUNNING_MARKER, {
            "run": {"status": "running", "started": t_start}, "configuration": configuration})
        signals.on_stop = loop.request_stop
        master.network.notifier.add_listener(ErrorFrames(loop.on_error_frame))
        if on_record is not None:
            on_record(loop.record)
        if signals.requested.is_set():
            loop.request_stop(signals.reason)
        stats = loop.run(progress)
        if stats.stop is StopReason.DRIVE_LOST:
            # TPDOs stop before the heartbeat tells why (a reset, NMT pre-operational): give
            # the drive one heartbeat to name the cause
            master.fault.wait(1.5 * target.drive.heartbeat_ms / 1e3)
    except KeyboardInterrupt:
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
    return _summarise(loop, stats, master, recorder, spec, configuration, signals.reason,
                      t_start)


def _bring_up(bus: can.BusABC, master: DriveMaster, plan: _Plan, own_echo: bool) -> CycleLoop:
    """Identify and configure the drive, make the controller, start SYNC and the watches,
    enable the drive; returns the loop, ready to run."""
    drive, profile, motor, spec = plan.target.drive, plan.profile, plan.motor, plan.spec
    # the exact design models what the drive applies: for the emulator's PI current loop
    # its response time (1/bandwidth, from its EDS); a real drive is taken as ideal
    lag = (1.0 / _eds_default(master, "current_loop_bw")
           if drive.emulator and spec.drive_mode is DriveMode.CURRENT_LOOP else 0.0)
    assert spec.sampling is not None
    ctl = spec.controller.make(ControllerContext(
        motor=motor, sampling=spec.sampling, refs_at=profile.at, drive_mode=spec.drive_mode,
        current_lag=lag, paper=spec.controller_config(lag), correction=spec.correction))
    who = f"the {spec.law} law" if spec.controller.is_paper else spec.who
    plan.pd.require(required_roles(spec, plan.pd, getattr(ctl, "requires", ())),
                    f"{who} with a {spec.drive_mode} drive",
                    master.node.object_dictionary.indices)
    counter = master.configure(spec.period, plan.pd, drive.remap, drive.mode_of(spec.drive_mode),
                               _emulator_settings(master, drive, spec),
                               sync_overflow=SYNC_OVERFLOW)
    lockstep = spec.timing is Timing.LOCKSTEP
    loop_cfg = replace(plan.loop, sync_counter=counter)
    if lockstep:  # the gateway's heartbeat in the loop's time too (LoopConfig)
        loop_cfg = replace(loop_cfg, heartbeat_cob_id=HEARTBEAT_BASE + master.gateway_node,
                           heartbeat_every=max(1, math.floor(
                               master.heartbeat_period / spec.period + 1e-9)))
    master.start(lockstep=lockstep,
                 alive_ids=[p.cob_id for p in plan.pd.tpdos] if lockstep else ())
    master.enable()

    def fault_cause() -> tuple[StopReason, str] | None:
        f = master.first_fault
        return None if f is None else (f.reason, f.describe())

    schedule = getattr(bus, "schedule", None)  # a FaultyBus: the faults it injects
    return CycleLoop(bus, master.network.subscribe, plan.pd, ctl, profile, loop_cfg,
                     own_echo=own_echo, fault=master.fault, fault_cause=fault_cause,
                     fault_marks=None if schedule is None else schedule.marks)


def _emulator_settings(master: DriveMaster, drive: DriveProfile, spec: RunSpec
                       ) -> dict[str, int | float]:
    """The emulator's own objects for this run (model, RPDO apply, time base, internal
    rate); nothing for any other drive, which takes RPDOs at the next SYNC only."""
    assert spec.sampling is not None
    if not drive.emulator:
        if spec.sampling.delay != 1:
            raise UserError("--delay 0 (RPDOs applied on receipt) is an emulator option; a "
                            "CiA 402 drive applies synchronous RPDOs at the next SYNC "
                            "(--delay 1)")
        return {}
    # lockstep: the emulator supervises the gateway's heartbeat in simulated time
    time_base = TimeBase.SYNC if spec.timing is Timing.LOCKSTEP else TimeBase.WALL
    return {"Emulator model": spec.drive_mode.emulator_model,
            "RPDO apply": int(spec.sampling.apply),
            "Time base": int(time_base),
            "f_pwm": round(internal_rate(_eds_default(master, "f_pwm"), spec.period))}


def _configuration(spec: RunSpec, target: BusTarget, profile: Profile, node_id: int,
                   label: str) -> dict[str, Any]:
    return {"command": target.command, "bus": label, "node": node_id,
            "drive_profile": target.drive.source, "profile": profile.source,
            **spec.describe()}


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


def run_account(stats: Any, stop: StopReason, message: str, exit_status: int,
                 t_start: float) -> dict[str, Any]:
    """summary["run"]: the cause of stopping and the loop's account of its cycles."""
    return {
        "status": "finished", "stop": stop.name, "stop_reason": message,
        "exit_status": exit_status,
        "cycles": stats.cycles if stats else 0,
        "missed_cycles": stats.missed if stats else 0,
        "late_rpdo": stats.late_rpdo if stats else 0,
        "rpdo_after_sync": stats.rpdo_after_sync if stats else 0,
        "last_good_cycle": stats.last_good_cycle if stats else 0,
        "tpdo_events": dict(stats.tpdo_events) if stats else {},
        "max_consecutive_missed": stats.max_consecutive_missed if stats else 0,
        "skipped_syncs": stats.skipped_syncs if stats else 0,
        "tpdo_before_echo": stats.tpdo_before_echo if stats else 0,
        "error_frames": stats.error_frames if stats else 0,
        "stop_cycle": stats.stop_cycle if stats else 0,
        "wall_time_s": stats.wall_time if stats else time.time() - t_start,
    }


def _summarise(loop: CycleLoop | None, stats: Any, master: DriveMaster,
               recorder: BusRecorder, spec: RunSpec, configuration: dict[str, Any],
               interrupt_reason: str, t_start: float) -> BusRun:
    """The record's columns and the summary of what happened on the bus."""
    summary: dict[str, Any] = {}
    sig = None
    if loop is not None and len(loop.record):
        sig = loop.record.arrays()
        summary["timing"] = timing_stats(sig, spec.period, spec.timing is Timing.REALTIME)
    stop, message = _final_stop(stats, master, interrupt_reason)
    shutdown = master.shutdown_report
    exit_status = stop.exit_status
    if shutdown is not None and not shutdown.safe:
        exit_status = 1
        if stop in (StopReason.END_OF_PROFILE, StopReason.INTERRUPTED):
            stop, message = StopReason.UNSAFE, f"{message}; then {StopReason.UNSAFE.value}"
    summary["run"] = {**run_account(stats, stop, message, exit_status, t_start),
                      **recorder.account(),
                      "heartbeat_refused": master.state.heartbeat_send_errors}
    if loop is not None and stop not in (StopReason.END_OF_PROFILE, StopReason.INTERRUPTED):
        summary["run"]["frames_before_stop"] = [
            {"time": t, "dir": d, "cob_id": f"0x{c:03X}", "data": data}
            for t, d, c, data in loop.recent]
    summary["shutdown"] = None if shutdown is None else asdict(shutdown)
    summary["configuration_notes"] = list(master.notes)
    summary["faults"] = [{"time": f.time, "kind": f.kind, "code": f.code, "text": f.text,
                          "reason": f.reason.name} for f in master.state.faults]
    summary["configuration"] = configuration
    schedule = getattr(master.bus, "schedule", None)  # a FaultyBus
    if schedule is not None:
        summary["bus_faults"] = schedule.account()
    found = summary_of(loop.ctl) if loop is not None else None
    if found is not None:
        summary["identification"] = found
    if recorder.error:
        summary["write_errors"] = [recorder.error + f" ({recorder.dropped} frames not logged)"]
    return BusRun(sig, summary)


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
