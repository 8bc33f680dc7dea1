"""A whole gateway run: bring the drive up, loop, bring it down safely, write the run directory.

Used by `hil-gateway run` (any python-can bus) and `hil-gateway sim` (the emulator in the
same process on python-can's virtual bus). The order is fixed and every exit path —
end of profile, Ctrl-C, SIGTERM, a drive fault or loss, an error — goes through the same
shutdown: no more SYNC, controlword "disable voltage", NMT PRE-OPERATIONAL, heartbeat off,
bus log flushed and closed; the caller shuts the bus down.
"""

from __future__ import annotations

import collections
import logging
import signal
import threading
import time
from collections.abc import Callable, Iterator
from contextlib import contextmanager
from dataclasses import asdict, dataclass, field
from pathlib import Path
from typing import Any

import can
import numpy as np

from dbc import load_codec
from gateway import report
from gateway.buslog import write_frame
from gateway.control.controller import Controller, ControllerConfig
from gateway.control.laws import Gains
from gateway.control.profiles import Profile
from gateway.drive_profile import DriveProfile
from gateway.errors import UserError
from gateway.loop import SYNC_OVERFLOW, CycleLoop, LoopConfig, PdoNames
from gateway.master import DriveMaster
from gateway.simulate import DRIVES, _load_tuning, drive_params_for_period
from plant.params import DriveParams, MotorParams

log = logging.getLogger(__name__)

LOG_SUFFIXES = (".blf", ".asc", ".csv", ".log", ".trc")


@dataclass(frozen=True)
class RunConfig:
    """One gateway run.

    drive_mode: what the drive is asked to be: "ideal" or "current-loop" (CiA 402 current
        vector mode; on the emulator also its model of the current loop) or "voltage"
        (voltage vector mode). delay: 1 = synchronous RPDOs (CiA 301 default), 0 = the
        emulator applies RPDOs on receipt. bus_log: file name of the raw bus log in the run
        directory; its suffix picks the python-can writer. plant_scenario: the resolved
        plant scenario of `sim` (issue 14), None when the plant is not ours to know (`run`).
    """

    law: str = "current-fed"
    flux: str = "estimated"
    estimator: str = "open-loop"
    drive_mode: str = "ideal"
    period: float = 1e-3
    timing: str = "lockstep"
    delay: int = 1
    gains: Gains = field(default_factory=Gains)
    bus_log: str = "bus.blf"
    max_missed: int = 5
    duration: float | None = None
    plant_scenario: dict[str, Any] | None = None
    load: str = "known"

    def __post_init__(self) -> None:
        if self.drive_mode not in DRIVES:
            raise UserError(f"unknown drive mode {self.drive_mode!r}: use {', '.join(DRIVES)}")
        if Path(self.bus_log).suffix.lower() not in LOG_SUFFIXES:
            raise UserError(f"bus log {self.bus_log!r}: the file name must end in one of "
                            f"{', '.join(LOG_SUFFIXES)} (it selects python-can's writer)")

    def controller_config(self) -> ControllerConfig:
        return ControllerConfig(law=self.law, flux=self.flux, estimator=self.estimator,  # type: ignore[arg-type]
                                period=self.period, delay=self.delay, gains=self.gains,
                                load=self.load, **_load_tuning(self.load, self.drive_mode))


class BusRecorder(can.Listener):
    """The raw bus log: frames queued in the receive thread, written by a writer thread.

    Queuing costs the control cycle a deque append; :meth:`stop` drains everything and
    closes the file, so nothing received is lost on any exit path.
    """

    def __init__(self, path: Path) -> None:
        try:
            self._writer = can.Logger(str(path))
        except (OSError, ValueError) as exc:
            raise UserError(f"cannot write the bus log {str(path)!r}: {exc}") from exc
        self.path = path
        self.count = 0
        self._queue: collections.deque[can.Message] = collections.deque()
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._drain_loop, name="bus-log", daemon=True)
        self._thread.start()

    def on_message_received(self, msg: can.Message) -> None:
        self._queue.append(msg)

    def _drain(self) -> None:
        q = self._queue
        writer = self._writer
        while q:
            write_frame(writer, q.popleft())
            self.count += 1

    def _drain_loop(self) -> None:
        while not self._stop.wait(0.05):
            self._drain()

    def stop(self) -> None:
        """Write what is queued, flush and close (idempotent)."""
        if self._stop.is_set():
            return
        self._stop.set()
        self._thread.join(2.0)
        self._drain()
        self._writer.stop()


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


def pdo_layout(
    master: DriveMaster, codec: Any, names: list[str]
) -> dict[str, list[tuple[int, int, int]]]:
    """Each PDO's mapping entries from its DBC signals and the EDS objects of the same name."""
    from dbc import signal_specs

    specs = signal_specs()
    od = master.node.object_dictionary
    layout: dict[str, list[tuple[int, int, int]]] = {}
    for name in names:
        entries = []
        for sig in codec.messages[name].names:
            if sig == "controlword":
                obj = od[0x6040]
            elif sig == "statusword":
                obj = od[0x6041]
            else:
                try:
                    obj = od[sig]
                except KeyError as exc:
                    raise UserError(
                        f"the drive's EDS ({master.profile.eds}) has no object named {sig!r} "
                        f"for signal {sig} of {name}: name the object like the DBC signal, or "
                        "set remap = false in the drive profile and configure the mapping on "
                        "the drive") from exc
            entries.append((obj.index, obj.subindex, specs[sig].bits))
        layout[name] = entries
    return layout


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
) -> dict[str, Any]:
    """Run the loop against the drive on ``bus``; returns the summary (also written to out/)."""
    node_id = node or drive.node
    codec = load_codec(node_id)
    frame = drive.setpoint_frame
    names = PdoNames(currents=drive.currents, voltages=drive.voltages, truth=drive.truth,
                     control=drive.control, setpoints=drive.setpoints, load=drive.load)
    duration = cfg.duration or profile.duration
    n_cycles = round(duration / cfg.period)
    loop_cfg = LoopConfig(period=cfg.period, n_cycles=n_cycles, timing=cfg.timing,  # type: ignore[arg-type]
                          delay=cfg.delay, setpoint_frame=frame, max_missed=cfg.max_missed)
    signals = signals or StopSignals()
    recorder = BusRecorder(out / cfg.bus_log)
    master = DriveMaster(bus, drive, node_id)
    loop: CycleLoop | None = None
    stats = None
    error: BaseException | None = None
    t_start = time.time()
    try:
        master.connect(listeners=[recorder])
        pdos = [names.control, names.setpoints, names.currents, names.voltages]
        pdos += [n for n in (names.load, names.truth) if n]
        mode = drive.mode_voltage if cfg.drive_mode == "voltage" else drive.mode_current
        emulator: dict[str, int | float] = {}
        if drive.emulator:
            f_pwm = drive_params_for_period(DriveParams(), cfg.period, cfg.drive_mode).f_pwm
            emulator = {"Emulator model": 0 if cfg.drive_mode == "ideal" else 1,
                        "RPDO apply": 0 if cfg.delay == 1 else 1,
                        "f_pwm": round(f_pwm)}
        elif cfg.delay != 1:
            raise UserError("--delay 0 (RPDOs applied on receipt) is an emulator option; a "
                            "CiA 402 drive applies synchronous RPDOs at the next SYNC (--delay 1)")
        layout = pdo_layout(master, codec, pdos) if drive.remap else {}
        master.configure(cfg.period, layout, {n: codec.frame_id(n) for n in pdos}, mode,
                         emulator, sync_overflow=SYNC_OVERFLOW)
        master.start()
        master.enable()
        ctl = Controller(motor, cfg.controller_config())
        loop = CycleLoop(bus, master.network.subscribe, codec, names, ctl, profile, loop_cfg,
                         own_echo=own_echo, fault=master.fault)
        signals.on_stop = loop.request_stop
        if signals.requested.is_set():
            loop.request_stop(signals.reason)
        stats = loop.run(progress)
    except KeyboardInterrupt:
        error = None
        signals.reason = signals.reason or "interrupted"
    except BaseException as exc:
        error = exc
    finally:
        signals.shutting_down = True
        signals.on_stop = None
        master.shutdown()
        recorder.stop()
    if error is not None:
        raise error
    return _summarise(loop, stats, master, recorder, cfg, drive, profile, out, node_id,
                      bus_label, signals.reason, t_start)


def _summarise(loop, stats, master, recorder, cfg, drive, profile, out, node_id, bus_label,
               interrupt_reason, t_start) -> dict[str, Any]:
    summary: dict[str, Any] = {}
    if loop is not None and len(loop.record):
        sig = loop.record.arrays()
        loop.record.write_csv(out / "signals.csv")
        if drive.truth:  # tracking errors need the emulator's truth (TPDO3)
            summary.update(report.metrics(sig))
            report.plot_figures(sig, out, f"(over CAN, {cfg.timing})")
        summary["timing"] = timing_stats(sig, cfg.period, cfg.timing == "realtime")
    stop_reason = (stats.stop_reason if stats else "") or interrupt_reason or "start-up stopped"
    summary["run"] = {
        "cycles": stats.cycles if stats else 0,
        "missed_cycles": stats.missed if stats else 0,
        "late_rpdo": stats.late_rpdo if stats else 0,
        "stop_reason": stop_reason,
        "wall_time_s": stats.wall_time if stats else time.time() - t_start,
        "bus_frames_logged": recorder.count,
        "bus_log": recorder.path.name,
    }
    summary["faults"] = [{"time": f.time, "kind": f.kind, "code": f.code, "text": f.text}
                         for f in master.state.faults]
    summary["configuration"] = {
        "command": "run", "bus": bus_label, "node": node_id, "drive_profile": drive.source,
        "profile": profile.source, **{k: v for k, v in asdict(cfg).items() if k != "gains"},
        "gains": asdict(cfg.gains), "setpoint_frame": drive.setpoint_frame,
    }
    report.write_summary(out / "summary.json", summary)
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
    lines = [f"cycles {run['cycles']}, missed {run['missed_cycles']}, late RPDO "
             f"{run['late_rpdo']}, stopped: {run['stop_reason']}, wall time "
             f"{run['wall_time_s']:.2f} s"]
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
