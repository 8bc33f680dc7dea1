"""The profile modes' own setpoint generators and status bits (pure; CiA 402).

In profile velocity mode (PV, 3) the master sends a target velocity (0x60FF) when it likes,
by PDO or SDO; the drive ramps its velocity demand (0x606B) to it, speeding up at the
profile acceleration (0x6083) and slowing down at the profile deceleration (0x6084), and
its speed loop follows the demand. In profile torque mode (PT, 4) the target torque
(0x6071, limited to the max torque 0x6072) is reached along a linear ramp (torque profile
type 0x6088 = 0) of the torque slope (0x6087); the torque demand (0x6074) is the ramp's
output, which the field orientation makes. Halt (controlword bit 8) ramps to zero: PV
slows down at the profile deceleration, PT's torque goes to zero at the torque slope.

Statusword (after each sample, in Operation enabled):

* PV bit 10, target reached: the velocity actual value has stayed within the velocity
  window (0x606D) of the target (of zero while halted) for the velocity window time
  (0x606E); bit 12, speed = 0: it has stayed within the velocity threshold (0x606F) of
  zero for the velocity threshold time (0x6070).
* PT bit 10, target reached: the torque demand has reached the target torque (the ramp is
  done); while halted: the speed = 0 condition above.

Times count SYNC periods of simulated time, so the bits are deterministic. The ramp starts
where the drive is when the power stage comes on: PV from the encoder's speed, PT from zero.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

from dbc.cia402 import SW_SPEED_ZERO, SW_TARGET_REACHED, OperationMode

_RPM = 2.0 * math.pi / 60.0  #: one rev/min in rad/s


@dataclass(frozen=True)
class ProfileSettings:
    """The profile parameters in SI: acceleration and deceleration, rad/s² (0x6083,
    0x6084); torque slope, N·m/s (0x6087); velocity window, rad/s, and its time, s (0x606D,
    0x606E); velocity threshold, rad/s, and its time, s (0x606F, 0x6070)."""

    acceleration: float = 1000.0 * _RPM
    deceleration: float = 1000.0 * _RPM
    torque_slope: float = 100.0
    window: float = 1.0 * _RPM
    window_time: float = 0.010
    threshold: float = 1.0 * _RPM
    threshold_time: float = 0.010


#: The emulated drive's defaults (dbc/drive.eds; a twin whose file lacks an object).
DEFAULTS = ProfileSettings()


def ramp_velocity(v: float, target: float, s: ProfileSettings, T: float) -> float:
    """The velocity demand after one period ``T`` from ``v`` towards ``target``: slowing
    down (towards zero) at the deceleration, never past zero within a period, speeding up
    at the acceleration."""
    if (v > 0.0 and target < v) or (v < 0.0 and target > v):
        if v > 0.0:
            return max(max(target, 0.0), v - s.deceleration * T)
        return min(min(target, 0.0), v + s.deceleration * T)
    if target > v:
        return min(target, v + s.acceleration * T)
    return max(target, v - s.acceleration * T)


def ramp_torque(demand: float, target: float, s: ProfileSettings, T: float) -> float:
    """The torque demand after one period ``T`` from ``demand`` towards ``target`` along
    the linear ramp of the torque slope."""
    step = s.torque_slope * T
    return min(target, demand + step) if target > demand else max(target, demand - step)


class _Held:
    """A condition that must hold for a time: how long it has, counted at the samples."""

    def __init__(self) -> None:
        self.since: float | None = None

    def update(self, condition: bool, now: float, needed: float) -> bool:
        """The condition at sample time ``now``; True once it has held for ``needed`` s."""
        if not condition:
            self.since = None
            return False
        if self.since is None:
            self.since = now
        return now - self.since >= needed - 1e-9


class ProfileRamp:
    """The setpoint generator of PV or PT and its statusword bits (see the module
    docstring). ``torque_max``: the drive's torque limit, N·m (0x6072), which bounds PT's
    target; ``T``: the period, s."""

    def __init__(self, mode: OperationMode, T: float, torque_max: float) -> None:
        if not mode.profiled:
            raise ValueError(f"{mode!r} is not a profile mode")
        self.mode, self.T, self.torque_max = mode, T, torque_max
        self.demand: float | None = None  #: the ramp's output (None: power stage off)
        self.bits = 0
        self._t = 0.0
        self._reached, self._still = _Held(), _Held()

    def stop(self) -> None:
        """The power stage is off: the ramp starts over, no status bits."""
        self.demand = None
        self.bits = 0
        self._reached, self._still = _Held(), _Held()

    def goal(self, target: float, halt: bool) -> float:
        """Where the ramp heads: zero while halted, else the target (PT: limited)."""
        if halt:
            return 0.0
        if self.mode is OperationMode.PROFILE_TORQUE:
            return max(-self.torque_max, min(self.torque_max, target))
        return target

    def step(self, target: float, s: ProfileSettings, halt: bool, w_m: float) -> float:
        """One period: the demand (rad/s or N·m) the drive's control follows; the first
        after the power stage came on starts from ``w_m`` (PV) or zero (PT)."""
        goal = self.goal(target, halt)
        if self.mode is OperationMode.PROFILE_VELOCITY:
            self.demand = ramp_velocity(w_m if self.demand is None else self.demand, goal, s,
                                        self.T)
        else:
            self.demand = ramp_torque(0.0 if self.demand is None else self.demand, goal, s,
                                      self.T)
        return self.demand

    def supervise(self, w_m: float, target: float, s: ProfileSettings, halt: bool) -> int:
        """After a sample of the speed ``w_m``: the statusword's bits 10 and 12."""
        self._t += self.T
        if self.demand is None:
            return 0
        still = self._still.update(abs(w_m) <= s.threshold, self._t, s.threshold_time)
        if self.mode is OperationMode.PROFILE_VELOCITY:
            near = abs(w_m - self.goal(target, halt)) <= s.window
            reached = self._reached.update(near, self._t, s.window_time)
            self.bits = (SW_TARGET_REACHED if reached else 0) | (SW_SPEED_ZERO if still else 0)
        else:
            reached = still if halt else self.demand == self.goal(target, halt)
            self.bits = SW_TARGET_REACHED if reached else 0
        return self.bits
