"""The cyclic control loop over PDOs: SYNC → TPDOs → one controller step → RPDOs.

Everything cyclic happens in the bus's receive thread (python-can's notifier, shared with
python-canopen), driven by frames:

* the gateway's own SYNC, received back from the bus (``receive_own_messages``; on
  interfaces without it the sender reports it directly) opens cycle k and timestamps it;
* the drive's TPDOs are stored raw; when the last expected one arrives the cycle is
  complete: decode → :class:`gateway.cycle.ControlCycle` → encode → send, the same cycle
  :func:`gateway.simulate.run_sampled` runs, so lockstep over the bus equals `simulate`;
* ``lockstep``: the next SYNC is sent right after the RPDOs. ``realtime``: SYNC comes from
  a periodic sender (the kernel's broadcast manager on SocketCAN, a sleep-then-spin thread
  elsewhere); a cycle whose TPDOs are incomplete when the next SYNC appears is *missed*:
  the controller coasts (:meth:`Controller.coast`) and after ``max_missed`` consecutive
  misses the loop stops. A cycle whose setpoints are ready only after the next SYNC was
  due is *late*: its RPDOs are withheld (:meth:`Controller.withhold`), because the drive
  would latch them a period late with a frame angle a period old; it holds its setpoints.
  A SYNC thread held up for more than a period (a loaded host) does not send the SYNCs it
  could not send on time: it skips their slots, and the SYNC counter (0x1019) skips with
  them, so the drive and the controller both know how much time passed. Each skipped slot
  is a cycle without a sample: the controller coasts through it (counted as missed, and as
  ``skipped_syncs``; not as a sign of a lost drive).

Per cycle the loop records the signals and its timing: SYNC period, SYNC → last TPDO, and
the gateway's reaction time from the last TPDO's arrival to the RPDOs sent.

Faults stop the loop within the cycle they appear in, before any setpoint is sent for it
(:class:`gateway.stop.StopReason` names each): a fault reported by the master (EMCY, lost
heartbeat, boot-up, NMT change), a statusword that is not "Operation enabled", a TPDO of
the wrong length, a SYNC the gateway did not send, an implausible measurement
(:class:`gateway.guard.Plausibility`), a loop outside the profile's envelope
(:class:`gateway.guard.Envelope`), too many missed cycles in a row or within any 100 ms.
The last frames before the stop are kept for the summary (:attr:`CycleLoop.recent`).
"""

from __future__ import annotations

import gc
import logging
import math
import sys
import threading
import time
from collections import Counter, deque
from collections.abc import Callable
from dataclasses import dataclass, field
from typing import Any

import can

from dbc.cia301 import SYNC_ID, SYNC_OVERFLOW, NmtState, sync_counter, sync_periods
from dbc.cia402 import SW_FAULT, State
from dbc.timing import LOCKSTEP_BACKSTOP_S, Sampling, Timing
from gateway.control.controller import PAPER_SIGNALS
from gateway.control.interface import DriveController
from gateway.cycle import BUS_COLUMNS, ControlCycle, ReferenceProfile, row_type
from gateway.guard import DivergenceWatch, Envelope, Plausibility
from gateway.process_data import Pdo, ProcessData
from gateway.report import Record
from gateway.stop import StopReason

log = logging.getLogger(__name__)


def catch_up(k: int, t0: float, T: float, now: float) -> int:
    """The slot of the next SYNC on the schedule t0 + (k − 1)·T: ``k``, or, when ``now`` is
    more than a period past it (the sender was held up), the latest slot whose time has
    come — the slots in between are skipped, never sent late in a burst."""
    late = now - (t0 + (k - 1) * T)
    return k + int(late / T) if late > T else k


#: The missed-cycle rate limit looks at windows of this length, s.
MISS_WINDOW = 0.1
#: Real time without a SYNC counter: SYNCs received beyond those the producer can have sent
#: before the gateway calls them foreign (the kernel's timer and the echo's timestamp may
#: disagree by a period either way).
FOREIGN_SYNC_SLACK = 2


def kernel_syncs_sent(start: float, T: float) -> int:
    """The most SYNCs the kernel's broadcast manager, started at ``start`` (time.time())
    with period ``T``, can have sent by now: one per period, plus
    :data:`FOREIGN_SYNC_SLACK`."""
    return math.floor((time.time() - start) / T) + 1 + FOREIGN_SYNC_SLACK
#: Frames kept for the summary of a stop.
RECENT_FRAMES = 24
#: Error frames the loop tolerates within any :data:`MISS_WINDOW` before it stops: a few
#: are a disturbance the bus recovers from; a stream of them is a damaged bus.
MAX_ERROR_FRAMES = 50

#: Real-time SYNC thread: how long before a deadline it stops sleeping and spins, s. On the
#: project's VM, time.sleep overshoots by 107 µs median, 217 µs p99 (2.9 ms p99.9).
SPIN_MARGIN = 0.0003


class ErrorFrames(can.Listener):
    """Calls ``on_error`` for every error frame the bus delivers (python-canopen's
    listeners ignore them)."""

    def __init__(self, on_error: Callable[[], None]) -> None:
        self.on_error = on_error

    def on_message_received(self, msg: can.Message) -> None:
        if msg.is_error_frame:
            self.on_error()


def loop_row_type(signals: tuple[str, ...]) -> type[Any]:
    """A bus cycle's row for a controller that logs ``signals``."""
    return row_type(signals, BUS_COLUMNS)


#: The bus row of the paper's controllers.
LoopRow = loop_row_type(PAPER_SIGNALS)


@dataclass(frozen=True)
class LoopConfig:
    """sampling: period, delay (1 for synchronous RPDOs: the drive applies them at the next
    SYNC; 0 for "on receipt") and setpoint frame; n_cycles: cycles to run; max_missed:
    consecutive missed cycles that stop the loop; max_miss_rate: the fraction of cycles
    that may be missed within any :data:`MISS_WINDOW` (at least 5 cycles); tpdo_timeout: in
    lockstep, how long to wait for a cycle's TPDOs, s; sync_counter: SYNC carries the
    counter (0x1019); plausibility, envelope: the guards (None: not checked); the
    envelope stops the loop when crossed in ``envelope_cycles`` cycles in a row (one
    coasting cycle's current step is not a loss of control). heartbeat_cob_id,
    heartbeat_every: in lockstep the gateway's heartbeat also goes out before every n-th
    SYNC, so that a drive supervising it in simulated time (the emulator's SYNC time base)
    sees it at the same cycles whatever the host's load (0: not sent by the loop)."""

    n_cycles: int
    sampling: Sampling = field(default_factory=Sampling)
    timing: Timing = Timing.LOCKSTEP
    max_missed: int = 5
    max_miss_rate: float = 0.2
    tpdo_timeout: float = LOCKSTEP_BACKSTOP_S
    sync_counter: bool = True
    plausibility: Plausibility | None = None
    envelope: Envelope | None = None
    envelope_cycles: int = 3
    heartbeat_cob_id: int = 0
    heartbeat_every: int = 0

    def __post_init__(self) -> None:
        object.__setattr__(self, "timing", Timing(self.timing))


@dataclass
class LoopStats:
    """What happened, for the summary: the stop's cause and its message."""

    cycles: int = 0
    missed: int = 0
    late_rpdo: int = 0  #: cycles whose RPDOs were withheld: ready after the next SYNC
    #: cycles whose RPDOs went out in time by the clock but reached the bus after the next
    #: SYNC (seen in the bus's own echo: the host held the gateway between two frames)
    rpdo_after_sync: int = 0
    stop: StopReason | None = None
    stop_reason: str = ""
    stop_cycle: int = 0  #: the cycle open when the loop stopped (0: before the first)
    #: TPDOs not used, with why: '<PDO> late', 'early', 'stale', 'wrong length',
    #: 'duplicate' (a second frame of it in one cycle: the first is used)
    tpdo_events: Counter[str] = field(default_factory=Counter)
    max_consecutive_missed: int = 0  #: the longest run of missed cycles (the worst gap)
    #: SYNC slots the real-time SYNC thread skipped, held up past them (each also missed)
    skipped_syncs: int = 0
    error_frames: int = 0  #: error frames received
    #: lockstep: TPDOs that came before the echo of the SYNC they answer (held for its cycle)
    tpdo_before_echo: int = 0
    last_good_cycle: int = 0  #: the last cycle completed and sent
    wall_time: float = 0.0


class CycleLoop:
    """One run of the cyclic loop on an open bus (see the module docstring)."""

    def __init__(
        self,
        bus: can.BusABC,
        subscribe: Callable[[int, Callable[[int, bytearray, float], None]], None],
        pd: ProcessData,
        controller: DriveController,
        profile: ReferenceProfile,
        cfg: LoopConfig,
        own_echo: bool = True,
        fault: threading.Event | None = None,
        fault_cause: Callable[[], tuple[StopReason, str] | None] | None = None,
        fault_marks: Callable[[int], int] | None = None,
    ) -> None:
        self.bus = bus
        #: the bus faults injected in a cycle (bits of dbc.busfaults.FaultKind.bit), if any
        self._marks = fault_marks or (lambda k: 0)
        self.pd = pd
        self.ctl = controller
        self.cycle = ControlCycle(controller, profile, cfg.sampling, pd.modulator_dc_link)
        self.cfg = cfg
        self.own_echo = own_echo
        self.fault = fault or threading.Event()
        self._fault_cause = fault_cause
        self._row = loop_row_type(controller.signals)
        self.record = Record(self._row)
        #: the last frames seen and sent: (time.time(), 'rx'/'tx', COB-ID, data hex)
        self.recent: deque[tuple[float, str, int, str]] = deque(maxlen=RECENT_FRAMES)
        self._misses: deque[int] = deque()  # cycles missed within the last window
        #: cycles missed or with their setpoints withheld within the last window
        self._lost: deque[int] = deque()
        self._miss_window = max(5, round(MISS_WINDOW / cfg.sampling.period))
        self._syncs_sent = 0
        #: the slots of the SYNCs the SYNC thread sent, not yet seen on the bus (own echo)
        self._slots: deque[int] = deque()
        self._watch = (DivergenceWatch(cfg.envelope.for_controller(controller),
                                       cfg.envelope_cycles)
                       if cfg.envelope is not None else None)
        self.stats = LoopStats()
        self._lock = threading.Lock()
        #: real time: the SYNC thread's send against a cycle's deadline check and RPDOs
        self._send_lock = threading.Lock()
        self._done = threading.Event()
        self._stop = threading.Event()
        self._error: BaseException | None = None
        self._T = cfg.sampling.period
        # the drive's TPDOs: all of them make a cycle's measurement, in any order
        self._expected = {p.name: p for p in pd.tpdos}
        self._ids = {p.cob_id: p for p in pd.tpdos}
        self._echo = pd.pdo("sync_counter") if "sync_counter" in pd.roles else None
        self._stale = False
        self._frames: dict[str, bytes] = {}
        self._missed_names: set[str] = set()  # the TPDOs a missed cycle lacked
        self._late_names: set[str] = set()  # those of the previous cycle, if it was missed
        self._echo_seen = False  # this cycle's counter echo has arrived
        self._suspects: set[str] = set()  # frames that may be the previous cycle's
        #: TPDOs received while the SYNC sent was not yet echoed (see _on_tpdo)
        self._early: list[tuple[Pdo, bytes, float]] = []
        self._tpdo_time = 0.0
        self._k = 0  # cycles opened (SYNCs seen)
        self._k_done = 0  # cycles completed
        self._k_sent = 0  # the last cycle whose setpoints were sent (not withheld)
        self._consecutive_missed = 0  # cycles in a row without a sample (the gap)
        self._consecutive_lost = 0  # of them, those the drive's TPDOs did not come for
        self._sync_time = math.nan
        self._sync_prev = math.nan
        self._progress_at = time.monotonic()
        if pd.setpoint_frame is not cfg.sampling.setpoint_frame:
            raise ValueError(f"the drive's setpoints are in the {pd.setpoint_frame} frame, "
                             f"not {cfg.sampling.setpoint_frame}")
        self._sync_task: Any = None
        self._heartbeat = can.Message(arbitration_id=cfg.heartbeat_cob_id,
                                      data=[NmtState.OPERATIONAL.heartbeat],
                                      is_extended_id=False)
        self._producer_start = time.time()  # real time: when the SYNC producer started
        self._sync_thread: threading.Thread | None = None
        #: the RPDO frames sent whose echo has not come back yet, by COB-ID (oldest first)
        self._rpdo_sent: dict[int, deque[bytes]] = {p.cob_id: deque(maxlen=64)
                                                    for p in pd.rpdos}
        self._errors: deque[int] = deque()  # the cycles of recent error frames
        for cob_id in self._ids:
            subscribe(cob_id, self._on_tpdo)
        subscribe(SYNC_ID, self._on_own_sync if own_echo else self._on_foreign_sync)
        self._unechoed: set[int] = set()  # RPDOs of the last cycle sent, not yet echoed
        for p in pd.rpdos:  # the echo of ours (own_echo), and anyone else's on our COB-IDs
            subscribe(p.cob_id, self._on_own_rpdo)

    # ------------------------------------------------------------------- frames in

    def _sync_message(self, k: int) -> can.Message:
        data = [sync_counter(k)] if self.cfg.sync_counter else []
        return can.Message(arbitration_id=SYNC_ID, data=data, is_extended_id=False)

    def _on_own_sync(self, can_id: int, data: bytearray, timestamp: float) -> None:
        """A SYNC on the bus: ours (the echo of what we sent), or another producer's."""
        with self._lock:
            self.recent.append((time.time(), "rx", can_id, bytes(data).hex()))
            if self._done.is_set():
                return
            k = self._slots.popleft() if self._slots else self._kernel_cycle(bytes(data))
            why = self._foreign_sync(k, bytes(data))
            if why:
                self._finish(StopReason.FOREIGN_SYNC,
                             f"a SYNC the gateway did not send (data {bytes(data).hex() or '-'}"
                             f", expected the SYNC of cycle {k}; {why}): another SYNC "
                             "producer on the bus; there must be one")
                return
            self._open_locked(timestamp, k)
            early, self._early = self._early, []
            for pdo, raw, t_frame in early:  # they answer this SYNC: its cycle's now
                if self._done.is_set():
                    break
                self._tpdo_locked(pdo, raw, t_frame, time.perf_counter())

    def _kernel_cycle(self, data: bytes) -> int:
        """The cycle a SYNC opens where no SYNC thread keeps the slots (lock held): the
        next one, except with the kernel's broadcast manager and a counter. The manager
        sends one SYNC per period, in order, but one can fail to reach the gateway (its
        receive queue full while the host held the process) or be skipped with the host's
        timer: the counter tells how many periods passed since the last SYNC seen, as it
        tells the drive (:func:`dbc.cia301.sync_periods`), and the cycles between are
        skipped slots (:meth:`_skip`). A counter equal to the last one, or one further
        ahead than the manager can have sent by now (one per period since it started, plus
        :data:`FOREIGN_SYNC_SLACK`), is not taken: the next cycle, which the foreign-SYNC
        rule then judges by the counter."""
        k = self._k + 1
        if self._sync_task is None or not self.cfg.sync_counter or len(data) != 1:
            return k
        last = sync_counter(self._k)
        if data[0] == last:
            return k
        ahead = self._k + sync_periods(last, data[0])
        return ahead if ahead <= kernel_syncs_sent(self._producer_start, self._T) else k

    def _foreign_sync(self, k: int, data: bytes) -> str:
        """Why the SYNC received as the ``k``-th is not the gateway's, or '' when it is ours.

        With a counter (0x1019), by the counter. Without one, by count, never by the time
        between two SYNCs (a loaded host delays one and sends the next on time): in lockstep
        the gateway has sent k SYNCs by then; in real time the producer has sent at most
        one per period since it started (the kernel's schedule, or the SYNC thread's own
        count), so a k beyond that, by more than :data:`FOREIGN_SYNC_SLACK`, is another
        producer's."""
        if self.cfg.sync_counter:
            want = sync_counter(k)
            if len(data) == 1 and data[0] == want:
                return ""
            return f"by the SYNC counter: ours would carry {want:02x} (hex, as the data)"
        if data:
            return "by its data: the gateway's SYNC carries no counter"
        if self.cfg.timing is Timing.LOCKSTEP:
            sent = self._syncs_sent
        elif self._sync_thread is not None:
            sent = self._syncs_sent + FOREIGN_SYNC_SLACK
        else:  # the kernel's broadcast manager
            sent = kernel_syncs_sent(self._producer_start, self._T)
        if k <= sent:
            return ""
        return (f"by count: {k} SYNCs received where the gateway sent at most {sent} "
                f"in {time.time() - self._producer_start:.3f} s")

    def _on_own_rpdo(self, can_id: int, data: bytearray, timestamp: float) -> None:
        """A frame on an RPDO's COB-ID: the bus's echo of one the gateway sent (it is on
        the bus now), or, beyond the frames sent, another node writing on it."""
        with self._lock:
            self._unechoed.discard(can_id)
            pending = self._rpdo_sent[can_id]
            if self.own_echo and bytes(data) in pending:  # the echo of one we sent
                while pending.popleft() != bytes(data):
                    pass  # older ones whose echo was lost
                return
            if self._done.is_set():
                return
            self.recent.append((time.time(), "rx", can_id, bytes(data).hex()))
            self._finish(StopReason.FOREIGN_WRITER,
                         f"a frame on COB-ID 0x{can_id:03X} (the gateway's "
                         f"{self._rpdo_name(can_id)}) that the gateway did not send (data "
                         f"{bytes(data).hex() or '-'}): another node writes the drive's "
                         "setpoints; find it (`hil-gateway scan`, candump) and take it off")

    def _rpdo_name(self, can_id: int) -> str:
        return next((p.name for p in self.pd.rpdos if p.cob_id == can_id), "RPDO")

    def on_error_frame(self) -> None:
        """An error frame on the bus (the notifier's listener): counted; beyond
        :data:`MAX_ERROR_FRAMES` within any :data:`MISS_WINDOW` the loop stops."""
        with self._lock:
            self.stats.error_frames += 1
            k = self._k
            errors = self._in_window(self._errors, k)
            if errors > MAX_ERROR_FRAMES and not self._done.is_set():
                self._finish(StopReason.BUS_ERRORS,
                             f"{errors} error frames within {self._miss_window} cycles "
                             f"({self.stats.error_frames} in all): the bus is damaged "
                             "(cabling, termination, bitrate, a faulty node)")

    def _on_foreign_sync(self, can_id: int, data: bytearray, timestamp: float) -> None:
        """Without own echo the gateway never receives its SYNC: any SYNC is another's."""
        with self._lock:
            self.recent.append((time.time(), "rx", can_id, bytes(data).hex()))
            self._finish(StopReason.FOREIGN_SYNC, "a SYNC the gateway did not send: another "
                         "SYNC producer on the bus; there must be one")

    def _open_cycle(self, timestamp: float, k: int | None = None) -> None:
        with self._lock:
            self._open_locked(timestamp, k)

    def _open_locked(self, timestamp: float, k: int | None = None) -> None:
        """A SYNC went out: cycle ``k`` (default: the next) begins; the previous one, if
        incomplete, is missed (unless the master saw a fault, which is then the cause), and
        so is every slot between them the SYNC thread skipped."""
        if self._drive_faulted():
            return
        skipped = 0 if k is None else k - self._k - 1
        if self._unechoed:
            # The last cycle's RPDOs were sent before this SYNC was due, but some reached the
            # bus after it: the drive latched the others alone, and latches these at the
            # next SYNC. Its setpoints over the coming interval are mostly the ones it held:
            # the controller's model is told so (no step since that cycle's).
            self._unechoed.clear()
            self.stats.rpdo_after_sync += 1
            if self._k_done == self._k:
                self.ctl.withhold()
                self._k_sent = 0
        if self._k > self._k_done and self._k_done < self.cfg.n_cycles:
            self._miss()
        late, self._missed_names = self._missed_names, set()
        if skipped > 0 and not self._done.is_set():
            self._skip(skipped)
            if self._done.is_set():
                return
        self._k += 1
        self._sync_prev, self._sync_time = self._sync_time, timestamp
        self._frames.clear()
        self._stale = False
        # The missed cycle's TPDOs that did not come may still come, first in this window:
        # until the counter echo of this cycle arrives, such a frame is suspect (see
        # _on_tpdo). Without an echo there is nothing to tell them by.
        self._late_names = late if self._echo is not None else set()
        self._echo_seen = False
        self._suspects.clear()

    def _skip(self, n: int) -> None:
        """The SYNC producer skipped ``n`` slots after cycle self._k (the SYNC thread held
        up past them, or the kernel's SYNCs that the counter says did not reach the
        gateway): each is a cycle without a sample, which the controller coasts through
        (lock held).

        With synchronous RPDOs the drive latches nothing without a SYNC: it holds the
        setpoints it had through the skipped slots and latches cycle self._k's, sent for
        the slot after it, at the SYNC after them, as sent (their frame angle ``n``
        periods old). A controller with ``delayed(n)`` is told so; others coast as if
        those setpoints had come on time."""
        self.stats.skipped_syncs += n
        delayed = getattr(self.ctl, "delayed", None)
        told = (self._k_sent == self._k == self._k_done and delayed is not None
                and self.cfg.sampling.delay == 1)
        if told:
            delayed(n)
        for _ in range(n):
            if self._k >= self.cfg.n_cycles:
                self._finish(StopReason.END_OF_PROFILE, "end of the profile")
                return
            self._k += 1
            self._miss(skipped=True, coasted=told)
            if self._done.is_set():
                return

    def _miss(self, skipped: bool = False, coasted: bool = False) -> None:
        """Cycle self._k had no complete TPDO set (``skipped``: no SYNC, the SYNC thread was
        held up past its slot): coast (``coasted``: the controller did already) and count
        (lock held)."""
        k = self._k
        self.stats.missed += 1
        self._consecutive_missed += 1
        self.stats.max_consecutive_missed = max(self.stats.max_consecutive_missed,
                                                self._consecutive_missed)
        if not skipped:
            self._consecutive_lost += 1
        self._missed_names = (set() if skipped
                              else set(self._expected) - set(self._frames))
        self._k_done = k
        if not coasted:
            self.ctl.coast()
        window = self._miss_window
        misses = self._in_window(self._misses, k)
        self._in_window(self._lost, k)
        missing = (["no SYNC (the gateway was held up past its slot)"] if skipped
                   else sorted(self._missed_names | self._suspects) or ["none (late)"])
        if self._consecutive_lost >= self.cfg.max_missed:
            self._finish(StopReason.DRIVE_LOST,
                         f"{self._consecutive_lost} consecutive cycles without the drive's "
                         f"TPDOs (missing in cycle {k}: {', '.join(missing)}; drive lost or "
                         "bus overloaded)")
        elif misses > self.cfg.max_miss_rate * window and self.cfg.max_miss_rate < 1:
            self._finish(StopReason.DRIVE_LOST,
                         f"{misses} of the last {window} cycles missed (more than "
                         f"{self.cfg.max_miss_rate:.0%} within {window * self._T * 1e3:g} ms; "
                         f"last missing: {', '.join(missing)}): the loop cannot keep its rate")
        elif k >= self.cfg.n_cycles:  # the last cycle was missed: no cycle n + 1
            self._finish(StopReason.END_OF_PROFILE, "end of the profile")

    def _on_tpdo(self, can_id: int, data: bytearray, timestamp: float) -> None:
        """A TPDO of the drive: it belongs to the cycle open since the last SYNC; the cycle
        is complete when every TPDO is in, in any order."""
        t_arrival = time.perf_counter()
        pdo = self._ids.get(can_id)
        if pdo is None or self._done.is_set():
            return
        raw = bytes(data)
        with self._lock:
            self.recent.append((time.time(), "rx", can_id, raw.hex()))
            if (self._k <= self._k_done and self._sync_in_flight()
                    and len(raw) == pdo.length):
                # Lockstep: the cycle open is complete, the next SYNC is sent, its echo has
                # not come back, and a TPDO is here. On an in-process bus that hands a frame
                # to each receiver in turn (python-can's virtual) the drive can answer before
                # the sender's own copy is queued; on a real bus the echo comes first. Held,
                # and taken when the echo opens the cycle, as if after it (dropped as late,
                # the cycle waited for the 2 s backstop and was missed). A frame of another
                # cycle is told there as after the echo (counter echo, late, duplicate).
                self._early.append((pdo, raw, timestamp))
                self.stats.tpdo_before_echo += 1
                return
            self._tpdo_locked(pdo, raw, timestamp, t_arrival)

    def _sync_in_flight(self) -> bool:
        """Lockstep: the gateway's SYNC is sent and its echo not yet received (lock held).

        Only in lockstep, where the SYNC goes out once the cycle before is complete or
        missed. In real time a frame before the echo is the open cycle's by the bus's
        order, and the answers of an in-process drive there come late rather than early
        (measured at 5 ms: 10–55 stale answers to earlier SYNCs in a run, none that
        overtook its SYNC's echo)."""
        return (self.own_echo and self.cfg.timing is Timing.LOCKSTEP
                and self._syncs_sent > self._k)

    def _tpdo_locked(self, pdo: Pdo, data: bytes, timestamp: float,
                     t_arrival: float) -> None:
        """A TPDO in the cycle open now (lock held): :meth:`_on_tpdo`."""
        if len(data) != pdo.length:
            self.stats.tpdo_events[f"{pdo.name} wrong length"] += 1
            self._finish(StopReason.BAD_FRAME,
                         f"{pdo.name} (COB-ID 0x{pdo.cob_id:03X}) of {len(data)} bytes, "
                         f"expected {pdo.length}: not decoded (a wrong PDO mapping on the "
                         "drive, or another node on this COB-ID)")
            return
        if self._k <= self._k_done:
            # after its cycle (late) or before the first SYNC (early)
            self.stats.tpdo_events[f"{pdo.name} {'late' if self._k else 'early'}"] += 1
            return
        if pdo is self._echo and self.cfg.sync_counter:
            counter = pdo.codec.decode(data)["sync_counter"]
            self._stale = counter != sync_counter(self._k)
        if self._stale:
            # the answer to an earlier SYNC, arriving in this cycle: not ours
            self.stats.tpdo_events[f"{pdo.name} stale"] += 1
            return
        name = pdo.name
        if pdo is self._echo:
            self._echo_seen = True
        elif name in self._late_names and not self._echo_seen:
            # A TPDO the missed cycle lacked, before this cycle's echo: the drive answers
            # SYNCs in order, so it is the missed cycle's if this cycle's comes after
            # it. The cycle waits for a second one, or for one after the echo, and
            # never mixes the samples of two SYNCs (a voltage of the interval before
            # with the currents of this one threw the flux estimate off, at 10 ms).
            if name in self._suspects:
                self._suspects.discard(name)  # the second: the first was late
                self.stats.tpdo_events[f"{name} late"] += 1
            elif name not in self._frames:
                self._suspects.add(name)
        else:
            if name in self._suspects:
                self.stats.tpdo_events[f"{name} late"] += 1
            elif name in self._frames:
                self.stats.tpdo_events[f"{name} duplicate"] += 1
                return  # the first one counts
            self._suspects.discard(name)
        self._frames[name] = data
        if len(self._frames) < len(self._expected) or self._suspects:
            return
        self._tpdo_time = timestamp
        try:
            self._cycle(t_arrival)
        except Exception as exc:  # the receive thread must not die silently
            self._error = exc
            log.exception("error in control cycle %d", self._k)
            self._finish(StopReason.CONTROL_ERROR, f"error in the control cycle: {exc!r}")

    # ------------------------------------------------------------------ the cycle

    def _in_window(self, cycles: deque[int], k: int) -> int:
        """Cycle ``k`` added to ``cycles`` (those of some event, oldest first), and those
        before the miss window that ends at ``k`` dropped; how many are left."""
        cycles.append(k)
        while cycles[0] <= k - self._miss_window:
            cycles.popleft()
        return len(cycles)

    #: the share of the last miss window's cycles lost beyond which a divergence names them
    LOST_NOTE = 0.2

    def _lost_note(self, k: int) -> str:
        """What a divergence stop in cycle ``k`` adds when the loop had lost its rate just
        before: the drive held old setpoints through those cycles (a host that stalled, a
        lossy bus), which the controller's model follows but no law is designed for."""
        window = self._miss_window
        n = sum(1 for j in self._lost if j > k - window)
        if n < self.LOST_NOTE * window:
            return ""
        return (f"; {n} of the {window} cycles before it ({window * self._T * 1e3:g} ms) gave "
                f"the drive no new setpoints (missed: {self.stats.missed} in the run, withheld "
                f"as late: {self.stats.late_rpdo}): the loop lost its rate (a loaded or "
                "stalled host in real time, a lossy bus), and the drive held older setpoints "
                "meanwhile; signals.csv's columns missed and withheld show when")

    def _cycle(self, t_arrival: float) -> None:
        """Check, decode, step, guard, encode, send (lock held)."""
        k = self._k
        cfg = self.cfg
        fr = self._frames
        if self._drive_faulted():
            return
        measured: dict[str, float] = {}
        for name, pdo in self._expected.items():
            measured.update(pdo.codec.decode(fr[name]))
        sw = int(measured["statusword"])
        state = State.from_statusword(sw)
        if state is not State.OPERATION_ENABLED:
            stop = StopReason.DRIVE_FAULT if sw & SW_FAULT else StopReason.DRIVE_STATE
            shown = state.name if state is not None else "no CiA 402 state"
            self._finish(stop, f"statusword 0x{sw:04X} ({shown}) in cycle {k}: the drive left "
                               "Operation enabled")
            return
        if cfg.plausibility is not None:
            why = cfg.plausibility.check(measured)
            if why:
                self._finish(StopReason.IMPLAUSIBLE, f"cycle {k}: {why}")
                return
        setpoints, row = self.cycle.step(k, measured)
        if self._watch is not None and self._watch.check(row, k):
            self._finish(StopReason.DIVERGED, (self._watch.reason or "") + self._lost_note(k))
            return
        with self._send_lock:
            # Real time: the SYNC thread sends under the same lock, so the next SYNC goes
            # out either before this check (it has: withheld) or after all of this cycle's
            # RPDOs, on every receiver's queue alike (python-can's virtual bus puts a frame
            # in each queue in turn: two threads sending at once could reach the drive in
            # one order and the gateway's echo in the other).
            withheld = cfg.timing is Timing.REALTIME and (
                time.time() > self._sync_time + self._T
                or (self._sync_thread is not None and self._syncs_sent > k))
            if withheld:
                # Ready after the next SYNC was due (or sent: a SYNC thread held up sends the
                # next slot's on its schedule, less than a period after a late one): sent
                # now, the RPDOs would act one period late (from the SYNC after next) with
                # a frame angle one period old, or not at all. Withheld instead: the drive
                # holds its setpoints, and the controller's model of what the drive applies
                # says so.
                self.ctl.withhold()
                self.stats.late_rpdo += 1
                self._in_window(self._lost, k)  # for _lost_note
            else:
                send = self.bus.send
                frames = self.pd.encode(setpoints)
                if self.own_echo and cfg.timing is Timing.REALTIME:
                    self._unechoed = {cob_id for cob_id, _, _ in frames}
                for cob_id, _name, data in frames:
                    self._rpdo_sent[cob_id].append(bytes(data))
                    if not self._send(send, can.Message(arbitration_id=cob_id, data=data,
                                                        is_extended_id=False)):
                        return
                    self.recent.append((time.time(), "tx", cob_id, data.hex()))
                self._k_sent = k
        t_sent = time.perf_counter()
        self._k_done = k
        self.stats.last_good_cycle = k
        self._consecutive_missed = self._consecutive_lost = 0
        self.stats.cycles += 1
        self.record.append(self._row(
            *row, float(sw), float(measured.get("sync_counter", 0)),
            self._sync_time - self._sync_prev, self._tpdo_time - self._sync_time,
            t_sent - t_arrival, float(self.stats.missed), float(withheld),
            float(self._marks(k)),
        ))
        self._progress_at = time.monotonic()
        if k >= cfg.n_cycles:
            self._finish(StopReason.END_OF_PROFILE, "end of the profile")
        elif cfg.timing is Timing.LOCKSTEP and not self._stop.is_set():
            self._send_sync(k + 1)

    def _drive_faulted(self) -> bool:
        """The master saw a fault (EMCY, heartbeat, NMT): stop with its cause (lock held)."""
        if not self.fault.is_set():
            return False
        cause = self._fault_cause() if self._fault_cause is not None else None
        stop, message = cause or (StopReason.DRIVE_FAULT, "drive fault")
        self._finish(stop, message)
        return True

    def _send_sync(self, k: int) -> None:
        """Lockstep: send SYNC k (lock held)."""
        if self._drive_faulted():
            return
        msg = self._sync_message(k)
        every = self.cfg.heartbeat_every
        if every and (k - 1) % every == 0 and not self._send(self.bus.send, self._heartbeat):
            return
        self._syncs_sent = k
        if not self.own_echo:
            self._open_locked(time.time())
        if self._send(self.bus.send, msg):
            self.recent.append((time.time(), "tx", SYNC_ID, bytes(msg.data).hex()))

    def _send(self, send: Callable[[can.Message], None], msg: can.Message) -> bool:
        """Send a frame; a bus that refuses it (bus-off, a full queue, an adapter gone)
        stops the loop with that cause, not as an error of the control cycle (lock held)."""
        try:
            send(msg)
        except can.CanError as exc:
            self._finish(StopReason.BUS_OFF,
                         f"the gateway could not send 0x{msg.arbitration_id:03X} in cycle "
                         f"{self._k}: {exc} (bus-off, or the adapter's queue full or gone)")
            return False
        return True

    def _finish(self, stop: StopReason, message: str) -> None:
        if self.stats.stop is None:
            self.stats.stop, self.stats.stop_reason = stop, message
            self.stats.stop_cycle = self._k
            if stop is not StopReason.END_OF_PROFILE:
                log.warning("loop stopped in cycle %d: %s", self._k, message)
        self._stop.set()
        self._done.set()

    # ------------------------------------------------------------------- running

    def request_stop(self, reason: str, stop: StopReason = StopReason.INTERRUPTED) -> None:
        """Stop after the cycle in progress (Ctrl-C, SIGTERM, a fault); ``reason`` is the
        message."""
        self._stop.set()
        self._finish(stop, reason)

    def run(self, progress: Callable[[float], None] | None = None) -> LoopStats:
        """Run until the profile ends, a stop is requested, the drive faults or is lost."""
        t0 = time.perf_counter()
        self._progress_at = time.monotonic()
        # No cyclic-garbage collector pauses inside the loop (a full collection over the
        # growing record costs tens of ms): everything alive now is frozen out of the
        # collector's sight, and collection resumes after the run. Not collected first:
        # that took 25–130 ms of the run's start (13 % of a 2.5 s lockstep run) in a
        # process that had imported and drawn more; what is garbage now is collected after
        # the run, when the frozen objects are handed back to the collector.
        gc_was_enabled = gc.isenabled()
        gc.freeze()
        gc.disable()
        switch_interval = sys.getswitchinterval()
        try:
            if self.cfg.timing is Timing.LOCKSTEP:
                self.start_lockstep()
            else:
                self._start_sync_producer()
            last_wake = time.monotonic()
            while not self._done.wait(0.05):
                now = time.monotonic()
                if now - last_wake > 0.5 * self.cfg.tpdo_timeout:
                    # this process was held up (a loaded host): the drive's answers may wait
                    # in the receive queue; the stall is not the drive's
                    self._progress_at = max(self._progress_at, now)
                last_wake = now
                if self.fault.is_set():  # no cycle running to notice it (e.g. no TPDOs)
                    self.stop_on_fault()
                    break
                if progress is not None:
                    progress(self._k_done / self.cfg.n_cycles)
                if self.cfg.timing is Timing.LOCKSTEP:
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
        return self.stats

    def start_lockstep(self) -> None:
        """Lockstep: send SYNC 1 (:meth:`run` does; a caller that delivers the frames itself,
        `simulate`'s PDO link, :mod:`gateway.faultlink`, too)."""
        with self._lock:
            self._send_sync(1)

    @property
    def done(self) -> bool:
        """The loop has stopped (:attr:`stats` says why)."""
        return self._done.is_set()

    def _lockstep_watchdog(self) -> None:
        """No progress for tpdo_timeout: the backstop."""
        with self._lock:
            if self._done.is_set() or (time.monotonic() - self._progress_at
                                       < self.cfg.tpdo_timeout):
                return
            self._backstop_locked()

    def stop_on_fault(self) -> None:
        """The master saw a fault and no cycle is running to notice it: stop with its
        cause."""
        with self._lock:
            self._drive_faulted()

    def backstop(self) -> None:
        """Lockstep: the cycle open will get no more TPDOs: count it as missed (the
        controller coasts) and send the next SYNC. The watchdog does so after tpdo_timeout
        of wall time; `simulate`'s PDO link, which knows no frame is coming, at once."""
        with self._lock:
            if not self._done.is_set():
                self._backstop_locked()

    def _backstop_locked(self) -> None:
        for pdo, _, _ in self._early:  # held for a SYNC whose echo never came: late
            self.stats.tpdo_events[f"{pdo.name} late"] += 1
        self._early.clear()
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
            self._producer_start = time.time()
            self._sync_task = self.bus.send_periodic(msgs, T)
            log.info("SYNC every %g s by the kernel's broadcast manager", T)
            return
        # The SYNC thread must get the interpreter lock within ~0.1 ms of its deadline, not
        # after the default 5 ms switch interval. (Only here: with the kernel's broadcast
        # manager no Python thread keeps time, and a short interval only adds switching —
        # measured under User-Mode Linux it made the loop miss most cycles.)
        sys.setswitchinterval(1e-4)
        self._producer_start = time.time()
        self._sync_thread = threading.Thread(target=self._sync_thread_main, name="sync",
                                             daemon=True)
        self._sync_thread.start()

    def _sync_thread_main(self) -> None:
        """SYNC on an absolute schedule: sleep until SPIN_MARGIN before, then spin. A thread
        held up for more than a period (the host stalled) skips the slots it missed
        (:func:`catch_up`): the SYNCs it could not send are not sent later in a burst, which
        the drive could not follow, and the next one carries its own slot's counter, which
        tells the drive (and the loop) how many periods passed.

        The spin yields the interpreter lock every turn (``sleep(0)``): a plain busy loop
        would hold it for the whole switch interval and starve the receive threads.
        """
        T = self._T
        t0 = time.perf_counter() + 0.01
        k = 0
        while not self._stop.is_set():
            k = catch_up(k + 1, t0, T, time.perf_counter())
            target = t0 + (k - 1) * T
            remaining = target - time.perf_counter()
            if remaining > SPIN_MARGIN:
                time.sleep(remaining - SPIN_MARGIN)
            while time.perf_counter() < target:
                time.sleep(0)
            if self._stop.is_set():
                break
            if not self.own_echo:
                self._open_cycle(time.time(), k)
            try:
                with self._send_lock:  # never between a cycle's check and its RPDOs
                    self._syncs_sent = k
                    if self.own_echo:
                        self._slots.append(k)
                    self.bus.send(self._sync_message(k))
            except can.CanError as exc:
                with self._lock:
                    self._finish(StopReason.BUS_OFF, f"the gateway could not send SYNC {k}: "
                                 f"{exc} (bus-off, or the adapter's queue full or gone)")
                break

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
