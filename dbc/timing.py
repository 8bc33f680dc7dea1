"""The sampled timing contract of a cycle (docs/ARCHITECTURE.md, "Sampled timing").

:class:`Sampling` is the one home of the cycle period T, the delay between a sample and
the interval its setpoints act on, and the frame the setpoints are sent in; the
controller, the loop, `simulate` and a run take it from here.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

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


def internal_rate(f_pwm: float, period: float) -> float:
    """The emulated drive's internal rate, raised if needed to a whole number of steps per
    period (250 µs at 10 kHz: 3 steps, 12 kHz), Hz."""
    n = max(1, math.ceil(period * f_pwm - 1e-9))
    return f_pwm if abs(n - period * f_pwm) < 1e-9 else n / period
