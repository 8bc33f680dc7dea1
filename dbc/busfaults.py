"""Bus faults injected on purpose between the gateway and the drive: what they are, when
they act, and what each does to a frame — pure, with no I/O. Two carriers use it: a bus
(:mod:`gateway.faultbus`, `sim` and the two-process bridge) and `simulate`'s PDO link
(:mod:`gateway.faultlink`); both act through :class:`FrameFaults`, so a fault does the
same thing to the same frame in either.

A fault is an entry of a plant scenario's ``[[bus.fault]]`` list::

    [[bus.fault]]
    kind = "drop"          # see FaultKind
    message = "TPDO1"      # a message of the drive's DBC, where the kind needs one
    start = 1.0            # s (or cycle = N)
    duration = 0.2         # s; omitted: to the end
    probability = 0.2      # per frame (per cycle for the SYNC kinds); omitted: every one
    seed = 3

Time is the loop's: cycle k is the k-th SYNC the gateway sends, at t = (k − 1)·T, so a
lockstep run with a seed is the same bit for bit whatever the host does. Each fault draws
its random numbers from its own generator (``seed``), only for the frames it may act on.
"""

from __future__ import annotations

import math
import random
from collections.abc import Mapping
from dataclasses import dataclass, replace
from enum import StrEnum
from typing import Any

from dbc.cia301 import HEARTBEAT_BASE, NMT_ID, SYNC_ID

__all__ = [
    "PER_MESSAGE",
    "BusFault",
    "BusFaultError",
    "Fate",
    "FaultKind",
    "FaultSchedule",
    "Frame",
    "FrameFaults",
    "FrameIds",
    "Lane",
    "parse_bus_faults",
]


class FaultKind(StrEnum):
    """What an injected fault does (``kind`` in the scenario)."""

    DROP = "drop"  #: the message's frames are lost
    DELAY = "delay"  #: they arrive ``delay`` s later (whole cycles)
    DUPLICATE = "duplicate"  #: they arrive twice
    REORDER = "reorder"  #: each is held back behind the next frame of its direction
    CORRUPT = "corrupt"  #: one bit of the data flipped (the CRC missed it)
    DLC = "dlc"  #: the data length is wrong (``dlc`` bytes)
    SYNC_LATE = "sync-late"  #: the SYNC leaves ``delay`` s late
    SYNC_JITTER = "sync-jitter"  #: the SYNC leaves up to ``jitter`` s late, at random
    SYNC_MISSING = "sync-missing"  #: the drive does not receive the SYNC
    ERROR_FRAMES = "error-frames"  #: error frames, ``rate`` per second
    BUS_OFF = "bus-off"  #: the gateway's controller is off the bus, then recovers
    BABBLE = "babble"  #: another node sends on ``id`` at ``rate`` frames per second
    HEARTBEAT_STOP = "heartbeat-stop"  #: ``message`` "drive" or "gateway": its heartbeat
    SECOND_MASTER = "second-master"  #: another master sends SYNC every cycle

    @property
    def needs_message(self) -> bool:
        """A DBC message (or the heartbeat's owner) the fault acts on."""
        return self in PER_MESSAGE or self is FaultKind.HEARTBEAT_STOP

    @property
    def bit(self) -> int:
        """Its bit in ``signals.csv``'s ``faults`` column."""
        return 1 << list(FaultKind).index(self)


PER_MESSAGE = frozenset({FaultKind.DROP, FaultKind.DELAY, FaultKind.DUPLICATE,
                          FaultKind.REORDER, FaultKind.CORRUPT, FaultKind.DLC})
_KEYS = {"kind": str, "message": str, "start": (int, float), "cycle": int,
         "duration": (int, float), "probability": (int, float), "seed": int,
         "delay": (int, float), "jitter": (int, float), "rate": (int, float), "id": int,
         "dlc": int}


class BusFaultError(ValueError):
    """A ``[[bus.fault]]`` entry that cannot be used, with where and why."""


@dataclass(frozen=True)
class BusFault:
    """One injected fault (see the module docstring). ``start``/``duration`` in s, or
    ``cycle`` (the first cycle it acts in, from 1)."""

    kind: FaultKind
    message: str | None = None
    start: float = 0.0
    cycle: int | None = None
    duration: float | None = None
    probability: float = 1.0
    seed: int = 0
    delay: float = 0.0
    jitter: float = 0.0
    rate: float = 0.0
    id: int | None = None
    dlc: int | None = None

    def first_cycle(self, period: float) -> int:
        """The first cycle it acts in."""
        return self.cycle if self.cycle is not None else 1 + math.ceil(self.start / period
                                                                        - 1e-9)

    def last_cycle(self, period: float) -> float:
        """The last cycle it acts in (inf: to the end)."""
        if self.duration is None:
            return math.inf
        return self.first_cycle(period) + max(1, round(self.duration / period)) - 1

    def describe(self) -> str:
        where = f" on {self.message}" if self.message else ""
        when = f"cycle {self.cycle}" if self.cycle is not None else f"{self.start:g} s"
        span = f" for {self.duration:g} s" if self.duration is not None else ""
        p = f", p = {self.probability:g}" if self.probability < 1 else ""
        return f"{self.kind}{where} from {when}{span}{p}"


def parse_bus_faults(entries: Any, source: str) -> tuple[BusFault, ...]:
    """The ``[[bus.fault]]`` list of a scenario; :class:`BusFaultError` naming the entry."""
    if not isinstance(entries, list):
        raise BusFaultError(f"{source}: bus.fault must be a list of [[bus.fault]] tables")
    return tuple(_one(e, f"{source}: [[bus.fault]] entry {k}")
                 for k, e in enumerate(entries, 1))


def _one(e: Any, where: str) -> BusFault:
    if not isinstance(e, Mapping):
        raise BusFaultError(f"{where} must be a table")
    for key, value in e.items():
        types = _KEYS.get(key)
        if types is None:
            raise BusFaultError(f"{where}: unknown key {key!r}; the keys are "
                                f"{', '.join(_KEYS)}")
        if not isinstance(value, types) or isinstance(value, bool):
            raise BusFaultError(f"{where}: {key} = {value!r} has the wrong type")
    try:
        kind = FaultKind(e.get("kind"))
    except ValueError:
        raise BusFaultError(f"{where}: kind = {e.get('kind')!r}; the kinds are "
                            f"{', '.join(k.value for k in FaultKind)}") from None
    f = BusFault(kind=kind, message=e.get("message"), start=float(e.get("start", 0.0)),
                 cycle=e.get("cycle"), duration=_opt(e, "duration"),
                 probability=float(e.get("probability", 1.0)), seed=e.get("seed", 0),
                 delay=float(e.get("delay", 0.0)), jitter=float(e.get("jitter", 0.0)),
                 rate=float(e.get("rate", 0.0)), id=e.get("id"), dlc=e.get("dlc"))
    _check(f, where)
    return f


def _opt(e: Mapping[str, Any], key: str) -> float | None:
    return None if key not in e else float(e[key])


def _check(f: BusFault, where: str) -> None:
    if f.kind.needs_message and not f.message:
        raise BusFaultError(f"{where}: {f.kind} needs message = \"...\" ("
                            + ("\"drive\" or \"gateway\"" if f.kind is FaultKind.HEARTBEAT_STOP
                               else "a PDO of the drive's DBC, e.g. \"TPDO1\"") + ")")
    if f.kind is FaultKind.HEARTBEAT_STOP and f.message not in ("drive", "gateway"):
        raise BusFaultError(f"{where}: heartbeat-stop's message is \"drive\" or \"gateway\"")
    if not 0.0 < f.probability <= 1.0:
        raise BusFaultError(f"{where}: probability = {f.probability:g} must be in (0, 1]")
    if f.start < 0 or (f.cycle is not None and f.cycle < 1):
        raise BusFaultError(f"{where}: start must be ≥ 0 s (cycle ≥ 1)")
    if f.duration is not None and f.duration <= 0:
        raise BusFaultError(f"{where}: duration = {f.duration:g} must be > 0 s")
    need = {FaultKind.DELAY: ("delay", f.delay), FaultKind.SYNC_LATE: ("delay", f.delay),
            FaultKind.SYNC_JITTER: ("jitter", f.jitter),
            FaultKind.ERROR_FRAMES: ("rate", f.rate), FaultKind.BABBLE: ("rate", f.rate)}
    if f.kind in need and not need[f.kind][1] > 0:
        raise BusFaultError(f"{where}: {f.kind} needs {need[f.kind][0]} > 0")
    if f.kind is FaultKind.BABBLE and (f.id is None or not 0 <= f.id <= 0x7FF):
        raise BusFaultError(f"{where}: babble needs id = 0x000..0x7FF (the COB-ID it sends on)")
    if f.kind is FaultKind.BUS_OFF and f.duration is None:
        raise BusFaultError(f"{where}: bus-off needs duration (the time to its recovery)")
    if f.dlc is not None and not 0 <= f.dlc <= 8:
        raise BusFaultError(f"{where}: dlc = {f.dlc} must be 0..8")


class FaultSchedule:
    """The faults of one run at period ``period``: which act in a cycle, and their draws.

    :meth:`acts` says whether a fault acts on one more frame (or SYNC) of cycle ``k``: in its
    cycles, with its probability, from its own seeded generator. :meth:`marks` is the
    bitmask of kinds that acted in a cycle (``signals.csv``'s ``faults``)."""

    def __init__(self, faults: tuple[BusFault, ...], period: float) -> None:
        self.faults = faults
        self.period = period
        self._rng = [random.Random(f.seed) for f in faults]
        self._span = [(f.first_cycle(period), f.last_cycle(period)) for f in faults]
        self._marks: dict[int, int] = {}
        #: frames each fault acted on, by its index
        self.counts = [0] * len(faults)

    def active(self, i: int, k: int) -> bool:
        lo, hi = self._span[i]
        return lo <= k <= hi

    def acts(self, i: int, k: int) -> bool:
        """Fault ``i`` acts on a frame of cycle ``k`` (a draw when its probability < 1)."""
        if not self.active(i, k):
            return False
        f = self.faults[i]
        if f.probability < 1.0 and self._rng[i].random() >= f.probability:
            return False
        self.counts[i] += 1
        self._marks[k] = self._marks.get(k, 0) | f.kind.bit
        return True

    def rng(self, i: int) -> random.Random:
        """Fault ``i``'s own generator (which bit to flip, how late)."""
        return self._rng[i]

    def marks(self, k: int) -> int:
        """The kinds that acted in cycle ``k`` (bits of :attr:`FaultKind.bit`)."""
        return self._marks.get(k, 0)

    def account(self) -> list[dict[str, Any]]:
        """Each fault and how many frames (or cycles) it acted on, for summary.json."""
        return [{"fault": f.describe(), "kind": f.kind.value, "acted": n}
                for f, n in zip(self.faults, self.counts, strict=True)]


# ------------------------------------------------------------------- frame by frame

_SDO_RX = 0x600  #: SDO requests to the drive (client → server)


@dataclass(frozen=True)
class FrameIds:
    """The COB-IDs of the run: message name → COB-ID (the drive profile's PDOs), the
    drive's node, the gateway's node, the gateway's RPDOs."""

    messages: dict[str, int]
    node: int
    gateway_node: int
    rpdos: frozenset[int]

    @classmethod
    def of(cls, pd: object, node: int, gateway_node: int) -> FrameIds:
        """The COB-IDs of a drive's process data (``gateway.process_data.ProcessData``)."""
        pdos = getattr(pd, "pdos", ())
        return cls({p.name: p.cob_id for p in pdos}, node, gateway_node,
                   frozenset(p.cob_id for p in pdos if not p.tx))

    def from_gateway(self, can_id: int) -> bool:
        """A frame the gateway sends (SYNC, RPDOs, NMT, SDO requests, its heartbeat)."""
        return (can_id in (SYNC_ID, NMT_ID, _SDO_RX + self.node,
                           HEARTBEAT_BASE + self.gateway_node) or can_id in self.rpdos)



@dataclass(frozen=True, slots=True)
class Frame:
    """A CAN frame as the faults see it: COB-ID, data, an error frame or not, and the time
    it was received (s; 0: none)."""

    can_id: int
    data: bytes = b""
    error: bool = False
    timestamp: float = 0.0

    def with_data(self, data: bytes) -> Frame:
        return replace(self, data=data)


@dataclass(frozen=True)
class Fate:
    """What the per-message faults do to one frame: the frames that go on now (none when it
    is lost, delayed or held back), the frame held back behind the next frame of its
    direction (reorder), a frame delayed by ``later[0]`` cycles."""

    now: tuple[Frame, ...]
    held: Frame | None = None
    later: tuple[int, Frame] | None = None


class Lane:
    """One direction of frames (the gateway's, or those to the gateway): the frames delayed
    to a later cycle, and the one held back behind the next frame (reorder)."""

    def __init__(self) -> None:
        self._delayed: list[tuple[int, Frame]] = []
        self._behind: Frame | None = None

    def pass_on(self, fate: Fate, now: int) -> list[Frame]:
        """The frames that go on now for ``fate`` (in cycle, or count, ``now``: a delayed
        frame is released ``later[0]`` after it); the frame held back before goes after
        them."""
        if fate.later is not None:
            n, frame = fate.later
            self._delayed.append((now + n, frame))
        frames = list(fate.now)
        if self._behind is not None:
            frames.append(self._behind)
        self._behind = fate.held
        return frames

    def release(self, now: int) -> list[Frame]:
        """The delayed frames due by ``now``, in the order they were delayed."""
        due = [f for at, f in self._delayed if at <= now]
        self._delayed = [(at, f) for at, f in self._delayed if at > now]
        return due


class FrameFaults:
    """What the faults of ``schedule`` do, frame by frame and cycle by cycle, whatever
    carries the frames. ``messages``: the drive's message names → COB-IDs (a per-message
    fault names one, or SYNC)."""

    def __init__(self, schedule: FaultSchedule, messages: Mapping[str, int]) -> None:
        self.schedule = schedule
        self._carry: dict[int, float] = {}  # fractional frames per cycle (rates)
        self._by_id: dict[int, list[int]] = {}
        for i, f in enumerate(schedule.faults):
            if f.kind in PER_MESSAGE and f.message is not None:
                cob = SYNC_ID if f.message == "SYNC" else messages.get(f.message)
                if cob is None:
                    raise ValueError(f"bus fault {f.describe()}: {f.message!r} is not a "
                                     f"message of the drive's DBC ({', '.join(messages)})")
                self._by_id.setdefault(cob, []).append(i)

    def on_frame(self, frame: Frame, k: int) -> Fate:
        """The per-message faults on one frame in cycle ``k``."""
        s = self.schedule
        now: tuple[Frame, ...] = (frame,)
        for i in self._by_id.get(frame.can_id, ()):
            f = s.faults[i]
            if not now or not s.acts(i, max(1, k)):
                continue
            m = now[0]
            if f.kind is FaultKind.DROP:
                return Fate(())
            if f.kind is FaultKind.DUPLICATE:
                now = (m, m)
            elif f.kind is FaultKind.DELAY:
                return Fate((), later=(max(1, math.ceil(f.delay / s.period - 1e-9)), m))
            elif f.kind is FaultKind.CORRUPT and m.data:
                rng = s.rng(i)
                data = bytearray(m.data)
                data[rng.randrange(len(data))] ^= 1 << rng.randrange(8)
                now = (m.with_data(bytes(data)),)
            elif f.kind is FaultKind.DLC:
                n = f.dlc if f.dlc is not None else max(0, len(m.data) - 1)
                now = (m.with_data((m.data + bytes(8))[:n]),)
            elif f.kind is FaultKind.REORDER:
                return Fate((), held=m)
        return Fate(now)

    def sync(self, k: int) -> tuple[float, bool]:
        """SYNC ``k``: how late it leaves (s), and whether the drive misses it."""
        s = self.schedule
        delay, missing = 0.0, False
        for i, f in enumerate(s.faults):
            if f.kind is FaultKind.SYNC_MISSING and s.acts(i, k):
                missing = True
            elif f.kind is FaultKind.SYNC_LATE and s.acts(i, k):
                delay += f.delay
            elif f.kind is FaultKind.SYNC_JITTER and s.acts(i, k):
                delay += s.rng(i).uniform(0.0, f.jitter)
        return delay, missing

    def others(self, k: int) -> list[Frame]:
        """The frames other nodes send in cycle ``k``, before its SYNC: babble, error
        frames, a second master's SYNC."""
        s = self.schedule
        out: list[Frame] = []
        for i, f in enumerate(s.faults):
            if not s.active(i, k):
                continue
            if f.kind is FaultKind.BABBLE:
                for _ in range(self._count(i, f)):
                    s.acts(i, k)
                    assert f.id is not None
                    out.append(Frame(f.id, bytes(s.rng(i).randrange(256) for _ in range(8))))
            elif f.kind is FaultKind.ERROR_FRAMES:
                out += [Frame(0, error=True) for _ in range(self._count(i, f))
                        if s.acts(i, k)]
            elif f.kind is FaultKind.SECOND_MASTER and s.acts(i, k):
                out.append(Frame(SYNC_ID, bytes([(k + 100) % 240 + 1])))
        return out

    def _count(self, i: int, f: BusFault) -> int:
        """Frames a rate gives this cycle (the fractions carried over)."""
        want = self._carry.get(i, 0.0) + f.rate * self.schedule.period
        n = math.floor(want)
        self._carry[i] = want - n
        return n

    def heartbeat_stopped(self, whose: str, k: int) -> bool:
        """The heartbeat of ``whose`` ("drive" or "gateway") is lost in cycle ``k``."""
        s = self.schedule
        return any(f.kind is FaultKind.HEARTBEAT_STOP and f.message == whose
                   and s.acts(i, max(1, k)) for i, f in enumerate(s.faults))

    def bus_off(self, k: int) -> BusFault | None:
        """The bus-off that takes the gateway's controller off the bus at a send in cycle
        ``k`` (counted once it acts), or None; the carrier keeps it off for its
        ``duration``."""
        s = self.schedule
        for i, f in enumerate(s.faults):
            if f.kind is FaultKind.BUS_OFF and s.active(i, max(1, k)):
                s.acts(i, max(1, k))
                return f
        return None
