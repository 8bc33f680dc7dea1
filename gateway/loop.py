"""The cyclic control loop over PDOs: SYNC → TPDOs → one controller step → RPDOs.

Everything cyclic happens in the bus's receive thread (python-can's notifier, shared with
python-canopen), driven by frames:

* the gateway's own SYNC, received back from the bus (``receive_own_messages``; on
  interfaces without it the sender reports it directly) opens cycle k and timestamps it;
* the drive's TPDOs are stored raw; when the last expected one arrives the cycle is
  complete: decode → :func:`gateway.cycle.sample_from_tpdos` → controller step →
  :func:`gateway.cycle.rpdos_from_command` → encode → send, exactly as
  :func:`gateway.simulate.run_sampled` does, so lockstep over the bus equals `simulate`;
* ``lockstep``: the next SYNC is sent right after the RPDOs. ``realtime``: SYNC comes from
  a periodic sender (the kernel's broadcast manager on SocketCAN, a sleep-then-spin thread
  elsewhere); a cycle whose TPDOs are incomplete when the next SYNC appears is *missed*:
  the controller coasts (:meth:`Controller.coast`) and after ``max_missed`` consecutive
  misses the loop stops.

Per cycle the loop records the signals and its timing: SYNC period, SYNC → last TPDO, and
the gateway's reaction time from the last TPDO's arrival to the RPDOs sent.
"""

from __future__ import annotations

import gc
import logging
import math
import sys
import threading
import time
from collections.abc import Callable
from dataclasses import dataclass
from typing import Any, Literal

import can

from gateway.control.controller import Controller
from gateway.control.profiles import Profile
from gateway.cycle import (
    SYNC_OVERFLOW,
    rpdo2_name,
    rpdos_from_command,
    sample_from_tpdos,
    sync_counter,
)
from gateway.report import BASE_COLUMNS, Record

log = logging.getLogger(__name__)

Timing = Literal["lockstep", "realtime"]
SYNC_ID = 0x080

#: Real-time SYNC thread: how long before a deadline it stops sleeping and spins, s. On the
#: project's VM, time.sleep overshoots by 107 µs median, 217 µs p99 (2.9 ms p99.9).
SPIN_MARGIN = 0.0003

LOOP_COLUMNS: tuple[str, ...] = (
    *BASE_COLUMNS, "psi_rd_hat", "psi_rq_hat", "T_e", "i_limited", "u_limit_active",
    "statusword", "sync_counter", "sync_period", "sync_to_tpdo", "reaction", "missed",
)


@dataclass(frozen=True)
class LoopConfig:
    """period: s; n_cycles: cycles to run; delay: 1 for synchronous RPDOs (the drive applies
    them at the next SYNC), 0 for "on receipt"; max_missed: consecutive missed cycles that
    stop the loop; tpdo_timeout: in lockstep, how long to wait for a cycle's TPDOs."""

    period: float
    n_cycles: int
    timing: Timing = "lockstep"
    delay: int = 1
    setpoint_frame: str = "dq"
    max_missed: int = 5
    tpdo_timeout: float = 1.0
    sync_counter: bool = True


@dataclass
class LoopStats:
    """What happened, for the summary."""

    cycles: int = 0
    missed: int = 0
    late_rpdo: int = 0
    stop_reason: str = ""
    wall_time: float = 0.0


class PdoNames:
    """The DBC message names the loop uses (from the drive profile)."""

    def __init__(self, currents: str, voltages: str, truth: str | None, control: str,
                 setpoints: str, load: str | None) -> None:
        self.currents, self.voltages, self.truth = currents, voltages, truth
        self.control, self.setpoints, self.load = control, setpoints, load


class CycleLoop:
    """One run of the cyclic loop on an open bus (see the module docstring)."""

    def __init__(
        self,
        bus: can.BusABC,
        subscribe: Callable[[int, Callable[[int, bytearray, float], None]], None],
        codec: Any,
        names: PdoNames,
        controller: Controller,
        profile: Profile,
        cfg: LoopConfig,
        own_echo: bool = True,
        fault: threading.Event | None = None,
    ) -> None:
        self.bus = bus
        self.codec = codec
        self.names = names
        self.ctl = controller
        self.profile = profile
        self.cfg = cfg
        self.own_echo = own_echo
        self.fault = fault or threading.Event()
        self.record = Record(LOOP_COLUMNS)
        self.stats = LoopStats()
        self._lock = threading.Lock()
        self._done = threading.Event()
        self._stop = threading.Event()
        self._error: BaseException | None = None
        T = cfg.period
        self._T = T
        # the frames the controller needs, in the order the drive sends them
        self._expected = [names.currents, names.voltages] + ([names.truth] if names.truth else [])
        self._ids = {codec.frame_id(n): n for n in self._expected}
        self._first_name = self._expected[0]
        self._last_name = self._expected[-1]
        self._stale = False
        self._frames: dict[str, bytes] = {}
        self._tpdo_time = 0.0
        self._k = 0  # cycles opened (SYNCs seen)
        self._k_done = 0  # cycles completed
        self._consecutive_missed = 0
        self._sync_time = math.nan
        self._sync_prev = math.nan
        self._progress_at = time.monotonic()
        rpdo2_expected = rpdo2_name(cfg.setpoint_frame)  # type: ignore[arg-type]
        # (COB-ID, DBC message, key of rpdos_from_command's result)
        self._rpdo: list[tuple[int, str, str]] = [
            (codec.frame_id(names.control), names.control, "RPDO1"),
            (codec.frame_id(names.setpoints), names.setpoints, rpdo2_expected),
        ]
        if names.load:
            self._rpdo.append((codec.frame_id(names.load), names.load, "RPDO3"))
        if names.setpoints != rpdo2_expected:
            raise ValueError(f"setpoint message {names.setpoints} does not carry the "
                             f"{cfg.setpoint_frame} frame ({rpdo2_expected})")
        self._sync_task: Any = None
        self._sync_thread: threading.Thread | None = None
        for cob_id in self._ids:
            subscribe(cob_id, self._on_tpdo)
        if own_echo:
            subscribe(SYNC_ID, self._on_own_sync)

    # ------------------------------------------------------------------- frames in

    def _sync_message(self, k: int) -> can.Message:
        data = [sync_counter(k)] if self.cfg.sync_counter else []
        return can.Message(arbitration_id=SYNC_ID, data=data, is_extended_id=False)

    def _on_own_sync(self, can_id: int, data: bytearray, timestamp: float) -> None:
        self._open_cycle(timestamp)

    def _open_cycle(self, timestamp: float) -> None:
        with self._lock:
            self._open_locked(timestamp)

    def _open_locked(self, timestamp: float) -> None:
        """A SYNC went out: cycle k begins; the previous one, if incomplete, is missed."""
        if self._k > self._k_done and self._k_done < self.cfg.n_cycles:
            self._miss()
        self._k += 1
        self._sync_prev, self._sync_time = self._sync_time, timestamp
        self._frames.clear()
        self._stale = False

    def _miss(self) -> None:
        """Cycle self._k had no complete TPDO set: coast and count (lock held)."""
        self.stats.missed += 1
        self._consecutive_missed += 1
        self._k_done = self._k
        self.ctl.coast()
        if self._consecutive_missed >= self.cfg.max_missed:
            self._finish(f"{self._consecutive_missed} consecutive cycles without the drive's "
                         "TPDOs (drive lost or bus overloaded)")
        elif self._k >= self.cfg.n_cycles:  # the last cycle was missed: no cycle n + 1
            self._finish("end of the profile")

    def _on_tpdo(self, can_id: int, data: bytearray, timestamp: float) -> None:
        t_arrival = time.perf_counter()
        name = self._ids.get(can_id)
        if name is None or self._done.is_set():
            return
        with self._lock:
            if self._k <= self._k_done:
                return  # a TPDO outside an open cycle (late, or before the first SYNC)
            if name == self._first_name and self.cfg.sync_counter:
                counter = self.codec.decode(name, data).get("sync_counter")
                self._stale = counter is not None and counter != sync_counter(self._k)
            if self._stale:
                return  # the answer to an earlier SYNC, arriving in this cycle: not ours
            self._frames[name] = bytes(data)
            if name != self._last_name or len(self._frames) < len(self._expected):
                return
            self._tpdo_time = timestamp
            try:
                self._cycle(t_arrival)
            except Exception as exc:  # the receive thread must not die silently
                self._error = exc
                self._finish(f"error in the control cycle: {exc!r}")

    # ------------------------------------------------------------------ the cycle

    def _cycle(self, t_arrival: float) -> None:
        """Decode, step, encode, send (lock held)."""
        k = self._k
        T = self._T
        cfg = self.cfg
        codec = self.codec
        names = self.names
        fr = self._frames
        tp1 = codec.decode(names.currents, fr[names.currents])
        tp2 = codec.decode(names.voltages, fr[names.voltages])
        tp3 = codec.decode(names.truth, fr[names.truth]) if names.truth else None
        sample = sample_from_tpdos(tp1, tp2, tp3)
        t = k * T
        refs = self.profile.at(t)
        cmd = self.ctl.step(refs, sample)
        T_L_cmd = self.profile.at(t + cfg.delay * T).T_L if cfg.delay else refs.T_L
        msgs = rpdos_from_command(cmd, T_L_cmd, cfg.setpoint_frame)  # type: ignore[arg-type]
        send = self.bus.send
        for cob_id, name, key in self._rpdo:
            send(can.Message(arbitration_id=cob_id, data=codec.encode(name, msgs[key]),
                             is_extended_id=False))
        t_sent = time.perf_counter()
        self._k_done = k
        self._consecutive_missed = 0
        self.stats.cycles += 1
        if cfg.timing == "realtime" and time.time() > self._sync_time + T:
            self.stats.late_rpdo += 1  # the next SYNC was due before the RPDOs went out
        psi = cmd.psi_r_dq
        if tp3 is not None:
            w_m, psi_mod, T_e = tp3["w_m"], abs(complex(tp3["psi_ra"], tp3["psi_rb"])), tp3["T_e"]
        else:
            w_m = psi_mod = T_e = math.nan
        status = int(tp1["statusword"])
        self.record.append((
            t, refs.w_ref, refs.psi_ref, refs.T_L, w_m, psi_mod, cmd.w_hat, abs(psi),
            sample.i_s_ab.real, sample.i_s_ab.imag, sample.u_s_ab.real, sample.u_s_ab.imag,
            cmd.i_s_dq_ref.real, cmd.i_s_dq_ref.imag, cmd.u_s_dq_ref.real, cmd.u_s_dq_ref.imag,
            cmd.eps_0, cmd.w_0, psi.real, psi.imag, T_e, float(cmd.i_limited),
            float(bool(status & 0x0800)), float(status), float(tp1.get("sync_counter", 0)),
            self._sync_time - self._sync_prev, self._tpdo_time - self._sync_time,
            t_sent - t_arrival, float(self.stats.missed),
        ))
        self._progress_at = time.monotonic()
        if k >= cfg.n_cycles:
            self._finish("end of the profile")
        elif cfg.timing == "lockstep" and not self._stop.is_set():
            self._send_sync(k + 1)

    def _send_sync(self, k: int) -> None:
        """Lockstep: send SYNC k (lock held)."""
        msg = self._sync_message(k)
        if not self.own_echo:
            self._open_locked(time.time())
        self.bus.send(msg)

    def _finish(self, reason: str) -> None:
        if not self.stats.stop_reason:
            self.stats.stop_reason = reason
        self._done.set()

    # ------------------------------------------------------------------- running

    def request_stop(self, reason: str) -> None:
        """Stop after the cycle in progress (Ctrl-C, SIGTERM, a fault)."""
        self._stop.set()
        self._finish(reason)

    def run(self, progress: Callable[[float], None] | None = None) -> LoopStats:
        """Run until the profile ends, a stop is requested, the drive faults or is lost."""
        t0 = time.perf_counter()
        self._progress_at = time.monotonic()
        # No cyclic-garbage collector pauses inside the loop (a full collection over the
        # growing record costs tens of ms): everything alive now is frozen out of the
        # collector's sight, and collection resumes after the run.
        gc_was_enabled = gc.isenabled()
        gc.collect()
        gc.freeze()
        gc.disable()
        switch_interval = sys.getswitchinterval()
        try:
            if self.cfg.timing == "lockstep":
                with self._lock:
                    self._send_sync(1)
            else:
                self._start_sync_producer()
            while not self._done.wait(0.05):
                if self.fault.is_set():
                    self.request_stop("drive fault")
                    break
                if progress is not None:
                    progress(self._k_done / self.cfg.n_cycles)
                if self.cfg.timing == "lockstep":
                    self._lockstep_watchdog()
        finally:
            self._stop.set()
            self._stop_sync_producer()
            self.stats.wall_time = time.perf_counter() - t0
            sys.setswitchinterval(switch_interval)
            gc.unfreeze()
            if gc_was_enabled:
                gc.enable()
        if progress is not None:
            progress(self._k_done / self.cfg.n_cycles)
        if self._error is not None:
            raise self._error
        return self.stats

    def _lockstep_watchdog(self) -> None:
        """No progress for tpdo_timeout: count the cycle as missed and send the next SYNC."""
        if time.monotonic() - self._progress_at < self.cfg.tpdo_timeout:
            return
        with self._lock:
            if self._done.is_set():
                return
            self._miss()
            self._progress_at = time.monotonic()
            if not self._done.is_set():
                self._send_sync(self._k + 1)

    # ---------------------------------------------------------- realtime SYNC producer

    def _start_sync_producer(self) -> None:
        T = self._T
        if self.bus.channel_info.lower().startswith("socketcan") or type(self.bus).__name__ == \
                "SocketcanBus":
            msgs = [self._sync_message(k) for k in range(1, SYNC_OVERFLOW + 1)]
            if not self.cfg.sync_counter:
                msgs = msgs[:1]
            self._sync_task = self.bus.send_periodic(msgs, T)
            log.info("SYNC every %g s by the kernel's broadcast manager", T)
            return
        # The SYNC thread must get the interpreter lock within ~0.1 ms of its deadline, not
        # after the default 5 ms switch interval. (Only here: with the kernel's broadcast
        # manager no Python thread keeps time, and a short interval only adds switching —
        # measured under User-Mode Linux it made the loop miss most cycles.)
        sys.setswitchinterval(1e-4)
        self._sync_thread = threading.Thread(target=self._sync_thread_main, name="sync",
                                             daemon=True)
        self._sync_thread.start()

    def _sync_thread_main(self) -> None:
        """SYNC on an absolute schedule: sleep until SPIN_MARGIN before, then spin.

        The spin yields the interpreter lock every turn (``sleep(0)``): a plain busy loop
        would hold it for the whole switch interval and starve the receive threads.
        """
        T = self._T
        t0 = time.perf_counter() + 0.01
        k = 0
        while not self._stop.is_set():
            k += 1
            target = t0 + (k - 1) * T
            remaining = target - time.perf_counter()
            if remaining > SPIN_MARGIN:
                time.sleep(remaining - SPIN_MARGIN)
            while time.perf_counter() < target:
                time.sleep(0)
            if self._stop.is_set():
                break
            if not self.own_echo:
                self._open_cycle(time.time())
            try:
                self.bus.send(self._sync_message(k))
            except can.CanError as exc:
                log.warning("SYNC send failed: %s", exc)

    def _stop_sync_producer(self) -> None:
        if self._sync_task is not None:
            try:
                self._sync_task.stop()
            except Exception as exc:
                log.warning("stopping the SYNC task failed: %s", exc)
            self._sync_task = None
        if self._sync_thread is not None:
            self._sync_thread.join(1.0)
            self._sync_thread = None
