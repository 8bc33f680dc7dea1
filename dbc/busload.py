"""Bus time of one cycle: the CAN frames a cycle puts on the bus, in bits and seconds.

A CAN 2.0A (11-bit identifier) data frame of ``n`` data bytes is, on the wire:

* 44 + 8n frame bits: SOF 1, identifier 11, RTR 1, IDE 1, r0 1, DLC 4, data 8n, CRC 15,
  CRC delimiter 1, ACK slot 1, ACK delimiter 1, EOF 7;
* 3 bits of interframe space (intermission) before the next frame may start;
* at most ⌊(34 + 8n − 1)/4⌋ stuff bits: only the 34 + 8n bits from SOF to the end of the
  CRC are stuffed, and in the worst case the first stuff bit comes after 5 equal bits and
  every further one after 4 more.

So the worst case is ``47 + 8n + ⌊(33 + 8n)/4⌋`` bits, the formula of Davis, Burns, Bril
and Lukkien, "Controller Area Network (CAN) schedulability analysis: Refuted, revisited
and revised", Real-Time Systems 35 (2007), eq. (2) with g = 34 (the 3-bit interframe
space included): 0 bytes → 55 bits, 1 → 65, 2 → 75, 4 → 95, 6 → 115, 8 → 135 (their
Table: 135 bits for 8 bytes). Typical frames stuff far less; this is the bound.

What a cycle counts (:func:`cycle_bits`): every frame the cycle sends, each with its
``every`` (a frame sent on every n-th cycle counts 1/n of its bits in the average cycle
and all of them in the busiest). Heartbeats, EMCY and SDO are not cycle frames: they are
what :data:`LOAD_LIMIT` leaves room for (two 1-byte heartbeats every 50–100 ms are
2 × 65 bits, under 0.3 % of a 1 Mbit/s bus).
"""

from __future__ import annotations

import math
from collections.abc import Iterable
from dataclasses import dataclass

#: The default bit rate of the bus, bit/s (CiA 301's highest, and the project's).
DEFAULT_BITRATE = 1_000_000

#: The largest share of the period a cycle's frames may take (worst-case stuffing, the
#: busiest cycle). The rest is for the gateway's turnaround between the last TPDO and its
#: RPDOs, heartbeats, EMCY, and the SDOs of a fault; a cycle above it is refused.
LOAD_LIMIT = 0.85


def frame_bits(n_bytes: int) -> int:
    """Worst-case bits of a CAN 2.0A data frame of ``n_bytes`` (0..8) data bytes, with
    stuffing and the 3-bit interframe space (see the module docstring)."""
    if isinstance(n_bytes, bool) or not isinstance(n_bytes, int) or not 0 <= n_bytes <= 8:
        raise ValueError(f"a CAN 2.0A data frame has 0..8 data bytes, not {n_bytes!r}")
    data = 8 * n_bytes
    return 47 + data + (33 + data) // 4


@dataclass(frozen=True)
class CycleFrame:
    """A frame of a cycle: its name, data bytes, and how often it is sent (every n-th
    cycle; 1 = every cycle)."""

    name: str
    n_bytes: int
    every: int = 1

    @property
    def bits(self) -> int:
        return frame_bits(self.n_bytes)


@dataclass(frozen=True)
class CycleLoad:
    """The bus time of a cycle's frames at a bit rate.

    busiest_bits: all frames (the cycle in which every frame is due); average_bits: each
    frame's bits over its ``every``."""

    frames: tuple[CycleFrame, ...]
    bitrate: int = DEFAULT_BITRATE

    @property
    def busiest_bits(self) -> int:
        return sum(f.bits for f in self.frames)

    @property
    def average_bits(self) -> float:
        return sum(f.bits / f.every for f in self.frames)

    @property
    def busiest_time(self) -> float:
        """Bus time of the busiest cycle, s."""
        return self.busiest_bits / self.bitrate

    def load(self, period: float) -> float:
        """The busiest cycle's share of ``period`` (1.0 = the whole period)."""
        return self.busiest_time / period

    def fits(self, period: float, limit: float = LOAD_LIMIT) -> bool:
        """The busiest cycle takes at most ``limit`` of the period."""
        return self.load(period) <= limit + 1e-12

    def min_period(self, limit: float = LOAD_LIMIT) -> float:
        """The shortest period of whole µs the frames fit at ``limit``, s."""
        return math.ceil(self.busiest_bits * 1e6 / (self.bitrate * limit) - 1e-9) * 1e-6

    def describe(self, period: float | None = None) -> str:
        """One line: frames, bits, bus time, and the load at ``period``."""
        names = " + ".join(f"{f.name} {f.n_bytes} B" + (f" (every {f.every})"
                                                       if f.every > 1 else "")
                           for f in self.frames)
        text = (f"bus time per cycle {self.busiest_bits} bits = "
                f"{self.busiest_time * 1e6:.0f} us at {self.bitrate / 1e6:g} Mbit/s "
                f"(worst-case stuffing; {names})")
        if period is not None:
            text += (f", {self.load(period):.1%} of the {period * 1e6:g} us period "
                     f"(limit {LOAD_LIMIT:.0%})")
        return text


def cycle_load(frames: Iterable[CycleFrame], bitrate: int = DEFAULT_BITRATE) -> CycleLoad:
    """The :class:`CycleLoad` of ``frames`` at ``bitrate`` bit/s."""
    if isinstance(bitrate, bool) or not isinstance(bitrate, int) or bitrate <= 0:
        raise ValueError(f"bit rate {bitrate!r} must be a positive number of bit/s")
    return CycleLoad(tuple(frames), bitrate)
