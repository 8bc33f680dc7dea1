"""A python-can bus that injects a scenario's bus faults between the gateway and the drive
(:mod:`dbc.busfaults`): the gateway's bus wrapped, so that neither side is modified.

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
import math
import threading
import time
from collections import deque
from dataclasses import dataclass

import can

from dbc.busfaults import BusFault, FaultKind, FaultSchedule
from dbc.cia301 import HEARTBEAT_BASE, NMT_ID, SYNC_ID

__all__ = ["FaultyBus", "FrameIds", "check_faults", "inject"]

_SDO_RX = 0x600  #: SDO requests to the drive (client → server)
_FRAME_KINDS = frozenset({FaultKind.DROP, FaultKind.DELAY, FaultKind.DUPLICATE,
                          FaultKind.REORDER, FaultKind.CORRUPT, FaultKind.DLC})


@dataclass(frozen=True)
class FrameIds:
    """The COB-IDs of the run: message name → COB-ID (the drive profile's PDOs), the
    drive's node, the gateway's node."""

    messages: dict[str, int]
    node: int
    gateway_node: int
    rpdos: frozenset[int]

    @classmethod
    def of(cls, pd: object, node: int, gateway_node: int) -> FrameIds:
        """The COB-IDs of a drive's process data (:class:`gateway.process_data.ProcessData`)."""
        pdos = getattr(pd, "pdos", ())
        return cls({p.name: p.cob_id for p in pdos}, node, gateway_node,
                   frozenset(p.cob_id for p in pdos if not p.tx))

    def from_gateway(self, can_id: int) -> bool:
        """A frame the gateway sends (SYNC, RPDOs, NMT, SDO requests, its heartbeat)."""
        return (can_id in (SYNC_ID, NMT_ID, _SDO_RX + self.node,
                           HEARTBEAT_BASE + self.gateway_node) or can_id in self.rpdos)


class FaultyBus(can.BusABC):
    """``inner`` (the gateway's bus) with the faults of ``schedule`` injected (module
    docstring). :attr:`schedule` holds what acted, cycle by cycle."""

    def __init__(self, inner: can.BusABC, schedule: FaultSchedule, ids: FrameIds,
                 other: can.BusABC | None = None, bridge: bool = False) -> None:
        self.inner, self.schedule, self.ids, self.other = inner, schedule, ids, other
        #: a bridge between two buses (:func:`run_bridge`): ``inner`` is the drive's side,
        #: which echoes nothing; the gateway gets its own echoes from its own bus
        self.bridge = bridge
        self._lock = threading.Lock()
        self.k = 0  #: SYNCs the gateway sent (the current cycle)
        self._echoes = 0  # SYNC echoes received
        self._rx_ready: deque[can.Message] = deque()
        self._held_tx: list[tuple[int, can.Message]] = []
        self._held_rx: list[tuple[int, can.Message]] = []
        self._reorder_tx: can.Message | None = None
        self._reorder_rx: can.Message | None = None
        self._carry: dict[int, float] = {}  # fractional frames per cycle (rates)
        self._off_until: float | None = None  # bus-off: wall-clock end
        self._off_done = False
        self._timers: list[threading.Timer] = []
        #: frames of the gateway's duplicated by the bus: the gateway's controller sees
        #: its own frame once, so one echo of each is swallowed
        self._swallow: dict[tuple[int, bytes], int] = {}
        super().__init__(channel=getattr(inner, "channel_info", "faulty"))
        self.channel_info = f"fault-injecting {getattr(inner, 'channel_info', '')}"
        self._by_id: dict[int, list[int]] = {}
        for i, f in enumerate(schedule.faults):
            if f.kind in _FRAME_KINDS and f.message is not None:
                cob = SYNC_ID if f.message == "SYNC" else ids.messages.get(f.message)
                if cob is None:
                    raise ValueError(f"bus fault {f.describe()}: {f.message!r} is not a "
                                     f"message of the drive's DBC ({', '.join(ids.messages)})")
                self._by_id.setdefault(cob, []).append(i)

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
            for i, f in enumerate(self.schedule.faults):
                if f.kind is FaultKind.BUS_OFF and self.schedule.active(i, max(1, self.k)):
                    self.schedule.acts(i, max(1, self.k))
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
            out += [(m, 0.0) for m in self._release(self._held_tx, k)]
            if self.bridge:  # no echo on the drive's side: received frames go by SYNCs sent
                self._rx_ready.extend(self._release(self._held_rx, k))
            return out + self._sync(msg, k)
        if msg.arbitration_id == HEARTBEAT_BASE + self.ids.gateway_node and \
                self._heartbeat_stopped("gateway"):
            return out
        frames, hold = self._frame_faults(msg, self.k, self._held_tx)
        if self._reorder_tx is not None:  # the frame held back goes after this one
            frames.append(self._reorder_tx)
        self._reorder_tx = hold
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
        delay, missing = 0.0, False
        for i, f in enumerate(self.schedule.faults):
            if f.kind is FaultKind.SYNC_MISSING and self.schedule.acts(i, k):
                missing = True
            elif f.kind is FaultKind.SYNC_LATE and self.schedule.acts(i, k):
                delay += f.delay
            elif f.kind is FaultKind.SYNC_JITTER and self.schedule.acts(i, k):
                delay += self.schedule.rng(i).uniform(0.0, f.jitter)
        self._others(k)
        if missing:  # the drive does not see it; the gateway's own echo it still gets
            if not self.bridge:
                self._rx_ready.append(_copy(msg))
            return []
        return [(msg, delay)]

    def _others(self, k: int) -> None:
        """The frames other nodes send in cycle ``k``: babble, a second master's SYNC,
        error frames."""
        if self.other is None:
            return
        for i, f in enumerate(self.schedule.faults):
            if not self.schedule.active(i, k):
                continue
            if f.kind is FaultKind.BABBLE:
                for _ in range(self._count(i, f)):
                    self.schedule.acts(i, k)
                    data = bytes(self.schedule.rng(i).randrange(256) for _ in range(8))
                    self.other.send(can.Message(arbitration_id=f.id, data=data,
                                                is_extended_id=False))
            elif f.kind is FaultKind.ERROR_FRAMES:
                for _ in range(self._count(i, f)):
                    if self.schedule.acts(i, k):
                        self.other.send(can.Message(is_error_frame=True, arbitration_id=0,
                                                    is_extended_id=False))
            elif f.kind is FaultKind.SECOND_MASTER and self.schedule.acts(i, k):
                self.other.send(can.Message(arbitration_id=SYNC_ID,
                                            data=[(k + 100) % 240 + 1],
                                            is_extended_id=False))

    def _count(self, i: int, f: BusFault) -> int:
        """Frames a rate gives this cycle (the fractions carried over)."""
        want = self._carry.get(i, 0.0) + f.rate * self.schedule.period
        n = math.floor(want)
        self._carry[i] = want - n
        return n

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
                return [msg, *self._release(self._held_rx, self._echoes)]
            return [msg]
        if self._off_until is not None and time.monotonic() < self._off_until:
            return []  # off the bus: it hears nothing
        if can_id == HEARTBEAT_BASE + self.ids.node and self._heartbeat_stopped("drive"):
            return []
        frames, hold = self._frame_faults(msg, self.k, self._held_rx, rx=True)
        if self._reorder_rx is not None:  # the frame held back goes after this one
            frames.append(self._reorder_rx)
        self._reorder_rx = hold
        return frames

    # ---------------------------------------------------------------- both ways

    def _heartbeat_stopped(self, whose: str) -> bool:
        k = max(1, self.k)
        return any(f.kind is FaultKind.HEARTBEAT_STOP and f.message == whose
                   and self.schedule.acts(i, k) for i, f in enumerate(self.schedule.faults))

    def _frame_faults(self, msg: can.Message, k: int, held: list[tuple[int, can.Message]],
                      rx: bool = False) -> tuple[list[can.Message], can.Message | None]:
        """The per-message faults on one frame: the frames that go on (maybe none, two,
        changed), and the one held back behind the next frame (reorder); delayed ones go
        into ``held`` with their release cycle."""
        frames = [msg]
        hold = None
        for i in self._by_id.get(msg.arbitration_id, ()):
            f = self.schedule.faults[i]
            if not frames or not self.schedule.acts(i, max(1, k)):
                continue
            m = frames[0]
            if f.kind is FaultKind.DROP:
                frames = []
            elif f.kind is FaultKind.DUPLICATE:
                frames = [m, _copy(m)]
            elif f.kind is FaultKind.DELAY:
                n = max(1, math.ceil(f.delay / self.schedule.period - 1e-9))
                held.append(((self._echoes if rx and not self.bridge else k) + n, m))
                frames = []
            elif f.kind is FaultKind.CORRUPT and m.dlc:
                rng = self.schedule.rng(i)
                data = bytearray(m.data)
                data[rng.randrange(len(data))] ^= 1 << rng.randrange(8)
                frames = [_copy(m, bytes(data))]
            elif f.kind is FaultKind.DLC:
                n = f.dlc if f.dlc is not None else max(0, m.dlc - 1)
                frames = [_copy(m, (bytes(m.data) + bytes(8))[:n])]
            elif f.kind is FaultKind.REORDER:
                hold, frames = m, []
        return frames, hold

    @staticmethod
    def _release(held: list[tuple[int, can.Message]], k: int) -> list[can.Message]:
        due = [m for at, m in held if at <= k]
        held[:] = [(at, m) for at, m in held if at > k]
        return due

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


def _copy(m: can.Message, data: bytes | None = None) -> can.Message:
    """A new frame like ``m`` (``data`` instead of its data)."""
    d = bytes(m.data) if data is None else data
    return can.Message(timestamp=m.timestamp or time.time(), arbitration_id=m.arbitration_id,
                       is_extended_id=m.is_extended_id, is_error_frame=m.is_error_frame,
                       dlc=len(d), data=d, channel=m.channel, check=False)


def check_faults(faults: tuple[BusFault, ...], pd: object, source: str = "") -> None:
    """Every message a fault names is one of the drive's PDOs (or SYNC); a
    :class:`gateway.errors.UserError` naming it otherwise."""
    from gateway.errors import UserError

    names = [p.name for p in getattr(pd, "pdos", ())]
    for f in faults:
        if f.kind in _FRAME_KINDS and f.message not in (*names, "SYNC"):
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
