"""The sampled timing contract of a cycle (docs/ARCHITECTURE.md, "Sampled timing").

:class:`Sampling` is the one home of the cycle period T, the delay between a sample and
the interval its setpoints act on, and the frame the setpoints are sent in; the
controller, the loop, `simulate` and a run take it from here.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from enum import IntEnum, StrEnum

from dbc.modes import RpdoApply, SetpointFrame


@dataclass(frozen=True)
class Sampling:
    """period: T, s (0x1006 in µs on the bus). delay: 1 = CiA 301 synchronous RPDOs (the
    setpoints act over the interval after the next SYNC), 0 = on receipt (emulator only).
    setpoint_frame: :class:`SetpointFrame`."""

    period: float = 1e-3
    delay: int = 1
    setpoint_frame: SetpointFrame = SetpointFrame.DQ

    def __post_init__(self) -> None:
        if isinstance(self.period, bool) or not (isinstance(self.period, int | float)
                                                 and 0.0 < self.period < math.inf):
            raise ValueError(f"period {self.period!r} s must be a finite number > 0")
        if self.delay not in (0, 1) or isinstance(self.delay, bool):
            raise ValueError(f"delay {self.delay!r} must be 0 or 1 periods")
        object.__setattr__(self, "setpoint_frame", SetpointFrame(self.setpoint_frame))

    @property
    def apply(self) -> RpdoApply:
        """When the drive makes received setpoints active."""
        return RpdoApply.for_delay(self.delay)

    def t_apply(self, t: float) -> float:
        """Start of the interval the setpoints computed at ``t`` act on, s."""
        return t + self.delay * self.period


class Timing(StrEnum):
    """How the master paces SYNC. LOCKSTEP: the next SYNC as soon as the RPDOs are out
    (deterministic); REALTIME: SYNC on an absolute schedule."""

    LOCKSTEP = "lockstep"
    REALTIME = "realtime"


class TimeBase(IntEnum):
    """The emulated drive's time base for its supervision (0x2205).

    WALL: the heartbeat consumer (0x1016) counts wall-clock time, as a real device's does.
    SYNC: lockstep — the simulation advances only on SYNC, so the consumer counts simulated
    time (SYNC periods since the master's last heartbeat, checked at each SYNC): the same
    run gives the same result whatever the host's load. The wall clock is then only a
    backstop for a master that stopped altogether (no heartbeat and no SYNC for
    :data:`LOCKSTEP_BACKSTOP_S`, or the consumer time if longer).
    """

    WALL = 0
    SYNC = 1


#: Lockstep: how long a master may be silent on the wall clock (no heartbeat, no SYNC)
#: before the emulated drive trips, and how long the gateway waits for a drive that answers
#: nothing, s. Only a process that stopped altogether is this silent; a stalled host is not.
LOCKSTEP_BACKSTOP_S = 2.0

#: `sim`: how long the emulated drive started in the gateway's process waits for the
#: gateway's heartbeat (0x1016), ms. The two share one interpreter: a stall of the process
#: (a loaded host, the GIL) stops the heartbeat and its watch together, and the 300 ms of
#: the emulator's profile tripped on busy 2-core hosts before cycle 1 (EMCY 0x8130); a
#: dead gateway thread is still caught, within a second.
SIM_HEARTBEAT_TIMEOUT_MS = 1000


#: Bounds of the cycle period T, s: 0x1006 allows 100 µs to 1 s; above 100 ms the frame
#: turns by more than ω0·T = 20 rad a period at 200 rad/s and the sampled laws mean nothing.
PERIOD_MIN = 100e-6
PERIOD_MAX = 100e-3
#: The emulated drive's internal rate (0x2201 sub 8, UINT32 Hz): EDS range.
INTERNAL_RATE_MAX = 100e3


def _whole_us(period: float) -> int | None:
    """The period in whole microseconds, or None when it is not one."""
    us = round(period * 1e6)
    return us if abs(period * 1e6 - us) < 1e-6 else None


def internal_rate(f_pwm: float, period: float) -> float:
    """The emulated drive's internal rate, raised if needed to a whole number of steps per
    period (250 µs at 10 kHz: 3 steps, 12 kHz), Hz. For a period of whole microseconds the
    rate is also a whole number of Hz (0x2201 sub 8 is UINT32): 150 µs at 10 kHz gives
    3 steps, 20 kHz (2 steps would be 13333.3 Hz)."""
    n = max(1, math.ceil(period * f_pwm - 1e-9))
    if abs(n - period * f_pwm) < 1e-9:
        return f_pwm
    us = _whole_us(period)
    if us is not None:
        k = us // math.gcd(us, 1_000_000)  # n·10⁶/us is whole when k divides n
        n = -(-n // k) * k
        return float(n * 1_000_000 // us)
    return n / period


def check_period(period: float, what: str = "period", f_pwm: float | None = None) -> None:
    """Refuse a cycle period that the bus or the drive cannot run, with the one message
    `simulate`, `sim` and `run` give (:class:`dbc.errors.UserError`).

    T must lie in [:data:`PERIOD_MIN`, :data:`PERIOD_MAX`] and be whole microseconds (0x1006
    is in µs). ``f_pwm``: the emulated drive's nominal internal rate, Hz; given, the rate
    :func:`internal_rate` picks must not exceed :data:`INTERNAL_RATE_MAX`.
    """
    from dbc.errors import UserError

    def us(x: float) -> str:
        return f"{x * 1e6:g}us" if x < 1e-3 else f"{x * 1e3:g}ms"

    if not (PERIOD_MIN - 1e-12 <= period <= PERIOD_MAX + 1e-12):
        raise UserError(
            f"{what} {us(period)} is outside {us(PERIOD_MIN)} … {us(PERIOD_MAX)}: the drive "
            f"takes at least {us(PERIOD_MIN)} (0x1006), and above {us(PERIOD_MAX)} the frame "
            "turns too far within a period for the sampled laws; choose e.g. 1ms or 250us")
    whole = _whole_us(period)
    if whole is None:
        lo, hi = math.floor(period * 1e6), math.ceil(period * 1e6)
        raise UserError(f"{what} {period * 1e6:.6g}us is not a whole number of microseconds, "
                        f"the unit of the cycle period on the bus (0x1006): use {lo}us or "
                        f"{hi}us")
    if f_pwm is not None:
        rate = internal_rate(f_pwm, period)
        if rate > INTERNAL_RATE_MAX:
            ok = [p for p in range(whole - 50, whole + 51)
                  if p >= PERIOD_MIN * 1e6 and internal_rate(f_pwm, p * 1e-6)
                  <= INTERNAL_RATE_MAX]
            near = min(ok, key=lambda p: abs(p - whole)) if ok else 100
            raise UserError(
                f"{what} {whole}us: the emulated drive runs its current loop a whole number "
                f"of times per period at a whole number of Hz, which for {whole}us means "
                f"{rate / 1e3:g} kHz, above its {INTERNAL_RATE_MAX / 1e3:g} kHz limit "
                f"(0x2201 sub 8); choose a rounder period, e.g. {near}us")
