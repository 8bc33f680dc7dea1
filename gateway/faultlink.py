"""`simulate`'s PDO link with a plant scenario's bus faults: the bus loop's cycle
(:class:`gateway.loop.CycleLoop`, lockstep) and the sampled drive exchange CAN frames in
this process, with no bus and no thread, and the faults act on those frames
(:class:`dbc.busfaults.FrameFaults`, the same actions as on a bus, :mod:`gateway.faultbus`).

Every reaction is the bus loop's own: a cycle whose TPDOs do not all come is missed (the
controller coasts), a TPDO of the wrong length stops the run (BAD_FRAME), error frames are
counted against the same limit, a SYNC or a setpoint frame the gateway did not send stops it
(FOREIGN_SYNC, FOREIGN_WRITER), a frame the bus refuses stops it (BUS_OFF). The frames move
in the order a lockstep bus gives them: what the gateway sends goes on after the frames
already on their way; in cycle k the other nodes' frames come first, then the frames delayed
to k, then SYNC k; the drive answers SYNC k with its TPDOs of the cycle.

Where the bus counts wall time, the link counts cycles:

* a cycle whose TPDOs will not come is missed at once (the bus loop waits its backstop,
  :data:`dbc.timing.LOCKSTEP_BACKSTOP_S`, first: no frame can come meanwhile);
* a late or jittered SYNC changes nothing but its mark (in lockstep it does not on a bus
  either);
* a bus-off refuses every frame from the first the gateway sends in its window: the run
  stops there, as on a bus, before its recovery;
* the drive's heartbeat goes out every ``heartbeat_every`` of its cycles (on a bus, on the
  drive's wall clock): a ``heartbeat-stop`` of the drive acts on those; in lockstep the
  gateway takes the drive's TPDOs as its signs of life, so nothing follows, as on a bus.
"""

from __future__ import annotations

import threading
import time
from collections import deque
from collections.abc import Callable
from dataclasses import dataclass
from typing import Any, Protocol

import can

from dbc.busfaults import BusFault, FaultKind, FaultSchedule, Frame, FrameFaults, FrameIds, Lane
from dbc.cia301 import HEARTBEAT_BASE, SYNC_ID, NmtState
from gateway.errors import UserError
from gateway.loop import CycleLoop, LoopStats
from gateway.process_data import ProcessData
from gateway.report import Record
from gateway.results import TruthColumns
from gateway.stop import StopReason

__all__ = ["LinkAccount", "LinkedDrive", "check_link_faults", "run_link"]

#: Kinds the link cannot carry, and why (the drive's heartbeat watch of the gateway runs
#: on a bus only).
_NOT_ON_THE_LINK = {
    (FaultKind.HEARTBEAT_STOP, "gateway"): (
        "the gateway's heartbeat is supervised by the emulated device, which `simulate` "
        "does not run"),
}


class LinkedDrive(Protocol):
    """The drive's side of the link."""

    #: its drive cycles between two heartbeats (0: none)
    heartbeat_every: int

    def sync(self, counter: int) -> list[Frame]:
        """One SYNC (``counter``: its data, 0 without): latch, advance a period, sample;
        its TPDO frames of the cycle, in the order it sends them."""
        ...

    def rpdo(self, frame: Frame) -> str:
        """A frame on one of its RPDO COB-IDs: taken (''), or why it faults."""
        ...


@dataclass
class LinkAccount:
    """What a run over the link adds to its summary: the loop's account (``stats``), how
    often each fault acted (``bus_faults``), the last frames before a stop (``recent``), and
    the drive's state at full resolution by its cycle (``truth``)."""

    stats: LoopStats
    bus_faults: list[dict[str, Any]]
    recent: list[tuple[float, str, int, str]]
    truth: TruthColumns


def check_link_faults(faults: tuple[BusFault, ...], source: str) -> None:
    """A :class:`UserError` naming a fault the link cannot carry, and the command that
    runs it over a bus."""
    for f in faults:
        why = _NOT_ON_THE_LINK.get((f.kind, f.message or ""))
        if why:
            raise UserError(f"--plant {source}: bus fault {f.describe()}: {why}; run it "
                            f"over the bus with `hil-gateway sim --plant {source}`")


class _Link:
    """The frames between the loop and the drive, cycle by cycle (module docstring). It is
    the loop's bus: what the loop sends meets the faults as it is sent (its marks are in
    the cycle's row, as on a bus) and is queued for the drive, with the gateway's own SYNC
    back to it (the echo that opens the cycle; an RPDO's echo would only confirm it)."""

    channel_info = "simulate's PDO link"

    def __init__(self, faults: FrameFaults, ids: FrameIds, drive: LinkedDrive) -> None:
        self.faults, self.ids, self.drive = faults, ids, drive
        self.loop: CycleLoop | None = None
        self.handlers: dict[int, Callable[[int, bytearray, float], None]] = {}
        self.k = 0  # SYNCs the gateway sent (the cycle)
        self.off = False  # bus-off: the run stops at the first frame refused
        self.to_gateway: deque[Frame] = deque()
        self.to_drive: deque[Frame] = deque()
        self._tx, self._rx = Lane(), Lane()
        self._drive_cycles = 0
        self._heartbeat = bytes([NmtState.OPERATIONAL.heartbeat])
        #: the drive faulted (the master's fault event on a bus: the loop stops at its next
        #: check, with :meth:`fault_cause`)
        self.fault = threading.Event()
        self._cause: tuple[StopReason, str] | None = None

    def fault_cause(self) -> tuple[StopReason, str] | None:
        return self._cause

    def subscribe(self, can_id: int, handler: Callable[[int, bytearray, float], None]
                  ) -> None:
        self.handlers[can_id] = handler

    def send(self, msg: can.Message, timeout: float | None = None) -> None:
        if self.off or self.faults.bus_off(self.k) is not None:
            self.off = True
            raise can.CanOperationError("bus-off (injected): the controller left the bus")
        f = Frame(msg.arbitration_id, bytes(msg.data), timestamp=time.time())
        if f.can_id != SYNC_ID:
            self.to_drive.extend(self._tx.pass_on(self.faults.on_frame(f, self.k), self.k))
            return
        self.k += 1
        k = self.k
        _, missing = self.faults.sync(k)  # a late SYNC: in lockstep nothing but its mark
        others = self.faults.others(k)
        for o in others:
            self._to_gateway(o)
        self.to_drive.extend(o for o in others if not o.error)
        self.to_drive.extend(self._tx.release(k))
        self.to_gateway.append(f)
        self.to_gateway.extend(self._rx.release(k))
        if not missing:
            self.to_drive.append(f)

    def move(self) -> bool:
        """Deliver every frame on its way once (the gateway's first); whether any moved.
        Once the loop has stopped, the gateway still receives what was on its way (as the
        bus delivers it until closed: error frames are counted), the drive nothing."""
        loop = self.loop
        assert loop is not None
        moved = False
        while self.to_gateway:
            self._deliver(self.to_gateway.popleft())
            moved = True
        while self.to_drive and not loop.done and not self.to_gateway:
            self._at_drive(self.to_drive.popleft())
            moved = True
        return moved

    def _deliver(self, f: Frame) -> None:
        """A frame the gateway receives."""
        assert self.loop is not None
        if f.error:
            self.loop.on_error_frame()
            return
        handler = self.handlers.get(f.can_id)
        if handler is not None:
            handler(f.can_id, bytearray(f.data), f.timestamp or time.time())

    def _to_gateway(self, f: Frame) -> None:
        """A frame on its way to the gateway, through the faults (its own frames and error
        frames untouched)."""
        if f.error or self.ids.from_gateway(f.can_id):
            self.to_gateway.append(f)
        elif not (f.can_id == HEARTBEAT_BASE + self.ids.node
                  and self.faults.heartbeat_stopped("drive", self.k)):
            self.to_gateway.extend(self._rx.pass_on(self.faults.on_frame(f, self.k), self.k))

    def _at_drive(self, f: Frame) -> None:
        """A frame the drive receives: a SYNC runs its cycle, an RPDO is taken."""
        if f.can_id == SYNC_ID:
            if len(f.data) > 1:
                return  # not a SYNC (CiA 301: 0 or 1 data bytes)
            for t in self.drive.sync(f.data[0] if f.data else 0):
                self._to_gateway(t)
            self._drive_cycles += 1
            every = self.drive.heartbeat_every
            if every and self._drive_cycles % every == 0:
                self._to_gateway(Frame(HEARTBEAT_BASE + self.ids.node, self._heartbeat))
            return
        if f.can_id in self.ids.rpdos:
            why = self.drive.rpdo(f)
            if why and not self.fault.is_set():
                self._cause = (StopReason.DRIVE_FAULT, why)
                self.fault.set()


def run_link(loop_factory: Callable[[_Link], CycleLoop], pd: ProcessData,
             schedule: FaultSchedule, drive: LinkedDrive, node: int, gateway_node: int,
             truth: TruthColumns,
             progress: Callable[[float], None] | None = None,
             stop: threading.Event | None = None,
             on_record: Callable[[Record], None] | None = None
             ) -> tuple[CycleLoop, LinkAccount]:
    """Run the lockstep loop against ``drive`` over the link with ``schedule``'s faults.

    ``loop_factory(link)``: the loop on the link (its bus: ``subscribe``, ``fault``,
    ``fault_cause`` as a master gives them); ``node``,
    ``gateway_node``: the drive's and the gateway's (their COB-IDs); ``on_record``: called
    with its record before the first cycle. Returns the loop (its record) and the account
    of the run."""
    ids = FrameIds.of(pd, node, gateway_node)
    link = _Link(FrameFaults(schedule, ids.messages), ids, drive)
    loop = link.loop = loop_factory(link)
    if on_record is not None:
        on_record(loop.record)
    n = loop.cfg.n_cycles
    step = max(1, n // 100)
    t0 = time.perf_counter()
    loop.start_lockstep()
    shown = 0
    while not loop.done:
        if not link.move():  # nothing more comes in this cycle
            if link.fault.is_set():
                loop.stop_on_fault()  # as the bus loop's watch does, before its backstop
            else:
                loop.backstop()  # the cycle's TPDOs will not come
        if stop is not None and stop.is_set() and not loop.done:
            loop.request_stop("stopped by a signal")
        if progress is not None and link.k >= shown + step:
            shown = link.k
            progress(min(1.0, shown / n))
    link.move()  # what was on its way to the gateway when it stopped
    loop.stats.wall_time = time.perf_counter() - t0
    return loop, LinkAccount(loop.stats, schedule.account(), list(loop.recent), truth)
