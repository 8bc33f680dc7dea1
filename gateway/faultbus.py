"""A python-can bus that injects a scenario's bus faults between the gateway and the drive
(:mod:`dbc.busfaults`): the gateway's bus wrapped, so that neither side is modified. What a
fault does to a frame is :class:`dbc.busfaults.FrameFaults`' (`simulate`'s PDO link,
:mod:`gateway.faultlink`, uses the same); this bus carries the frames, their echoes and the
wall-clock parts.

Direction is told by COB-ID: the gateway's frames (SYNC, its RPDOs, NMT, SDO requests, its
heartbeat) are acted on when the gateway sends them; every other frame (the drive's TPDOs,
heartbeat, EMCY, SDO answers) when the gateway receives it. The gateway's own frames that
the bus echoes back pass untouched.

Clock: cycle k begins when the gateway sends its k-th SYNC; a frame delayed by n cycles is
handed on after the k + n-th SYNC (received: after that SYNC's echo). ``bus-off`` alone
runs on the wall clock: the controller is off the bus for ``duration`` seconds from the
first send in its window, since no cycle runs while it is off. Other nodes (a babbling
node, a second master, error frames) send from ``other``, a bus of their own on the same
medium.
"""

from __future__ import annotations

import contextlib
import threading
import time
from collections import deque

import can

from dbc.busfaults import (
    PER_MESSAGE,
    BusFault,
    FaultSchedule,
    Frame,
    FrameFaults,
    FrameIds,
    Lane,
)
from dbc.cia301 import HEARTBEAT_BASE, SYNC_ID

__all__ = ["FaultyBus", "check_faults", "inject"]

class FaultyBus(can.BusABC):
    """``inner`` (the gateway's bus) with the faults of ``schedule`` injected (module
    docstring): what each does to a frame is :class:`dbc.busfaults.FrameFaults`'; this bus
    carries the frames and keeps the wall-clock parts (a late SYNC's delay, a bus-off's
    time to recovery, the echoes). :attr:`schedule` holds what acted, cycle by cycle."""

    def __init__(self, inner: can.BusABC, schedule: FaultSchedule, ids: FrameIds,
                 other: can.BusABC | None = None, bridge: bool = False) -> None:
        self.inner, self.schedule, self.ids, self.other = inner, schedule, ids, other
        #: a bridge between two buses (:func:`run_bridge`): ``inner`` is the drive's side,
        #: which echoes nothing; the gateway gets its own echoes from its own bus
        self.bridge = bridge
        self.faults = FrameFaults(schedule, ids.messages)
        self._lock = threading.Lock()
        self.k = 0  #: SYNCs the gateway sent (the current cycle)
        self._echoes = 0  # SYNC echoes received
        self._rx_ready: deque[can.Message] = deque()
        self._tx, self._rx = Lane(), Lane()
        self._off_until: float | None = None  # bus-off: wall-clock end
        self._off_done = False
        self._timers: list[threading.Timer] = []
        #: frames of the gateway's duplicated by the bus: the gateway's controller sees
        #: its own frame once, so one echo of each is swallowed
        self._swallow: dict[tuple[int, bytes], int] = {}
        super().__init__(channel=getattr(inner, "channel_info", "faulty"))
        self.channel_info = f"fault-injecting {getattr(inner, 'channel_info', '')}"

    # ---------------------------------------------------------------- sending

    def send(self, msg: can.Message, timeout: float | None = None) -> None:
        with self._lock:
            self._bus_off_check()
            out = self._outgoing(msg)
        for m, delay in out:
            if delay > 0:
                t = threading.Timer(delay, self._send_quietly, (m,))
                t.daemon = True
                self._timers.append(t)
                t.start()
            else:
                self.inner.send(m, timeout)

    def _send_quietly(self, m: can.Message) -> None:
        with contextlib.suppress(can.CanError):  # the bus closed meanwhile
            self.inner.send(m)

    def _bus_off_check(self) -> None:
        """Raise while the controller is off the bus (bus-off)."""
        now = time.monotonic()
        if self._off_until is None and not self._off_done:
            f = self.faults.bus_off(self.k)
            if f is not None:
                self._off_until = now + (f.duration or 0.0)
        if self._off_until is not None:
            if now < self._off_until:
                raise can.CanOperationError("bus-off (injected): the controller left the bus")
            self._off_until, self._off_done = None, True

    def _outgoing(self, msg: can.Message) -> list[tuple[can.Message, float]]:
        """What goes on the bus for a frame the gateway sends: (frame, wall delay s)."""
        out: list[tuple[can.Message, float]] = []
        if msg.arbitration_id == SYNC_ID and not msg.is_error_frame:
            self.k += 1
            k = self.k
            out += [(_message(f), 0.0) for f in self._tx.release(k)]
            if self.bridge:  # no echo on the drive's side: received frames go by SYNCs sent
                self._rx_ready.extend(_message(f) for f in self._rx.release(k))
            return out + self._sync(msg, k)
        if msg.arbitration_id == HEARTBEAT_BASE + self.ids.gateway_node and \
                self.faults.heartbeat_stopped("gateway", self.k):
            return out
        frames = [_message(f) for f in
                  self._tx.pass_on(self.faults.on_frame(_frame(msg), self.k), self.k)]
        for f in frames[1:]:
            if f.arbitration_id == msg.arbitration_id and bytes(f.data) == bytes(msg.data):
                key = (f.arbitration_id, bytes(f.data))
                self._swallow[key] = self._swallow.get(key, 0) + 1
        if not self.bridge:
            for f in frames:
                if f.arbitration_id == msg.arbitration_id and bytes(f.data) != bytes(msg.data):
                    # changed on the wire (corrupt, dlc): the drive gets it so, while the
                    # gateway's controller reports the frame it sent
                    key = (f.arbitration_id, bytes(f.data))
                    self._swallow[key] = self._swallow.get(key, 0) + 1
                    self._rx_ready.append(_copy(msg))
        return out + [(f, 0.0) for f in frames]

    def _sync(self, msg: can.Message, k: int) -> list[tuple[can.Message, float]]:
        """SYNC ``k``: late, jittered or missing; the other nodes' frames of the cycle."""
        delay, missing = self.faults.sync(k)
        others = self.faults.others(k)
        if self.other is not None:
            for f in others:
                self.other.send(_message(f))
        if missing:  # the drive does not see it; the gateway's own echo it still gets
            if not self.bridge:
                self._rx_ready.append(_copy(msg))
            return []
        return [(msg, delay)]

    # ---------------------------------------------------------------- receiving

    def _recv_internal(self, timeout: float | None) -> tuple[can.Message | None, bool]:
        deadline = None if timeout is None else time.monotonic() + timeout
        while True:
            with self._lock:
                if self._rx_ready:
                    return self._rx_ready.popleft(), False
            wait = None if deadline is None else max(0.0, deadline - time.monotonic())
            msg = self.inner.recv(wait if wait is None else min(wait, 0.05))
            if msg is not None:
                with self._lock:
                    self._rx_ready.extend(self._incoming(msg))
                continue
            if deadline is not None and time.monotonic() >= deadline:
                return None, False

    def _incoming(self, msg: can.Message) -> list[can.Message]:
        """What the gateway receives for a frame from the bus."""
        can_id = msg.arbitration_id
        key = (can_id, bytes(msg.data))
        if self._swallow.get(key):  # the second echo of a frame the bus duplicated
            self._swallow[key] -= 1
            return []
        if msg.is_error_frame or self.ids.from_gateway(can_id):
            if can_id == SYNC_ID and not msg.is_error_frame:
                self._echoes += 1
                return [msg, *(_message(f) for f in self._rx.release(self._echoes))]
            return [msg]
        if self._off_until is not None and time.monotonic() < self._off_until:
            return []  # off the bus: it hears nothing
        if can_id == HEARTBEAT_BASE + self.ids.node and \
                self.faults.heartbeat_stopped("drive", self.k):
            return []
        base = self.k if self.bridge else self._echoes
        return [_message(f) for f in
                self._rx.pass_on(self.faults.on_frame(_frame(msg), self.k), base)]

    def shutdown(self) -> None:
        """Cancel the delayed frames; the buses it wraps are closed with it, except a
        bridge's (its caller's)."""
        for t in self._timers:
            t.cancel()
        if not self.bridge:
            self.inner.shutdown()
            if self.other is not None:
                self.other.shutdown()
        super().shutdown()


def _frame(m: can.Message) -> Frame:
    return Frame(m.arbitration_id, bytes(m.data), m.is_error_frame, m.timestamp)


def _message(f: Frame) -> can.Message:
    """The frame as python-can's message."""
    return can.Message(timestamp=f.timestamp or time.time(), arbitration_id=f.can_id,
                       is_extended_id=False, is_error_frame=f.error, dlc=len(f.data),
                       data=f.data, check=False)


def _copy(m: can.Message) -> can.Message:
    """A new frame like ``m``."""
    return _message(_frame(m))


def check_faults(faults: tuple[BusFault, ...], pd: object, source: str = "") -> None:
    """Every message a fault names is one of the drive's PDOs (or SYNC); a
    :class:`gateway.errors.UserError` naming it otherwise."""
    from gateway.errors import UserError

    names = [p.name for p in getattr(pd, "pdos", ())]
    for f in faults:
        if f.kind in PER_MESSAGE and f.message not in (*names, "SYNC"):
            raise UserError(f"{source}: bus fault {f.describe()}: {f.message!r} is not a "
                            f"message of the drive's DBC; its messages are "
                            f"{', '.join(names)} (and SYNC)")


def inject(bus: can.BusABC, faults: tuple[BusFault, ...], period: float, pd: object,
           node: int, gateway_node: int, other: can.BusABC | None) -> can.BusABC:
    """``bus`` with ``faults`` injected (a :class:`FaultyBus`), or ``bus`` itself when there
    are none. ``pd``: the drive's :class:`gateway.process_data.ProcessData` (its messages'
    COB-IDs); ``other``: a bus of another node on the same medium (closed with it)."""
    if not faults:
        if other is not None:
            other.shutdown()
        return bus
    return FaultyBus(bus, FaultSchedule(faults, period), FrameIds.of(pd, node, gateway_node),
                     other)


class _BothSides:
    """Another node on a bridged bus: what it sends, both sides see."""

    def __init__(self, *buses: can.BusABC) -> None:
        self.buses = buses

    def send(self, msg: can.Message, timeout: float | None = None) -> None:
        for b in self.buses:
            b.send(msg, timeout)

    def shutdown(self) -> None:
        """The buses are the bridge's; it shuts them down."""


def run_bridge(gateway_side: can.BusABC, drive_side: can.BusABC,
               faults: tuple[BusFault, ...], period: float, pd: object, node: int,
               gateway_node: int, stop: threading.Event) -> FaultyBus:
    """Forward every frame between two buses (the gateway's and the drive's), injecting
    ``faults`` on the way, until ``stop`` is set; returns the bus that holds the account.
    Neither side is modified: each sees the other through the bridge."""
    faulty = FaultyBus(drive_side, FaultSchedule(faults, period),
                       FrameIds.of(pd, node, gateway_node),
                       _BothSides(gateway_side, drive_side), bridge=True)  # type: ignore[arg-type]

    def to_drive() -> None:
        while not stop.is_set():
            msg = gateway_side.recv(0.05)
            if msg is None:
                continue
            with contextlib.suppress(can.CanError):  # bus-off: the gateway's frame is lost
                faulty.send(msg)

    thread = threading.Thread(target=to_drive, name="bridge-to-drive", daemon=True)
    thread.start()
    try:
        while not stop.is_set():
            msg = faulty.recv(0.05)
            if msg is not None:
                gateway_side.send(msg)
    finally:
        stop.set()
        thread.join(1.0)
        faulty.shutdown()
    return faulty
