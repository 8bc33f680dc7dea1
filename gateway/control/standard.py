"""Controllers for standard CiA 402 drives, which take a target every SYNC and run their own
field orientation: cyclic synchronous torque (CST), velocity (CSV) and position (CSP),
``--drive-mode torque``, ``velocity`` and ``position`` (or the profile torque and velocity
modes, where the drive profile's [modes] names them).

* ``speed-pi`` (:class:`SpeedPi`, CST): the speed loop in the gateway, the drive's torque
  loop below it — the baseline for drives that offer no vector current or voltage process
  data. A PI on e = ω* − ω with the measured speed (the drive's velocity actual value
  0x606C) places the closed loop s² + k_p·s + k_i, k_p = 2ζω_n, k_i = ω_n², for the
  mechanical equation dω/dt = T_e/J − T_L/J of model (1) (row 1): the target torque
  T* = J·(k_p·e + k_i·∫e dt + dω*/dt) (+ T_L with ``load_feedforward``), limited to
  ±``T_max``; the integral stops while the limit clips (anti-windup). With the period's
  delay the torque acts one period after the sample; the loop's bandwidth (60 rad/s by
  default) is far below the sampling rate, as in ``ifoc``.
* ``stream`` (:class:`Stream`, CSV, CST or CSP): no loop in the gateway — the reference
  profile is the target, predicted to the start of the interval it acts on
  (x + delay·T·dx/dt): its speed ω* (CSV; the drive's speed loop does the work); (CSP) its
  position θ* = ∫ω* dt, integrated from 0 at the start of the run by the trapezoidal rule
  over each period (the drive's position and speed loops do the work); or (CST) the torque
  that makes ω* against the profile's load by row 1 of (1) inverted, T* = J·dω*/dt + T_L —
  open loop, so the speed drifts with any error of J or of the load: what a user streaming
  a setpoint profile to a standard drive wants.

Parameters (``--controller-params FILE.toml``), ``speed-pi``: ``speed_bandwidth`` ω_n
(rad/s, 60), ``damping`` ζ (1.0), ``T_max`` (N·m, 20), ``load_feedforward`` (false).
``stream`` takes none.
"""

from __future__ import annotations

import math
from collections.abc import Mapping
from typing import Any

from dbc.modes import DriveMode
from gateway.control.interface import Command, ControllerContext, Sample, checked_params
from gateway.control.laws import Refs

#: ``speed-pi``'s parameters and their defaults.
SPEED_PI_DEFAULTS: dict[str, Any] = {"speed_bandwidth": 60.0, "damping": 1.0, "T_max": 20.0,
                                     "load_feedforward": False}


class SpeedPi:
    """A speed PI over a standard drive's torque (CST; see the module docstring); a
    :class:`gateway.control.interface.DriveController`."""

    #: T_ref: the target torque sent, N·m; w_int: the speed loop's integral, rad.
    signals = ("T_ref", "w_int")
    #: the drive's speed (its velocity actual value)
    requires = ("w_m",)
    #: the drive mode it drives (the command line's default for it)
    drive_modes = (DriveMode.TORQUE,)

    def __init__(self, context: ControllerContext, params: Mapping[str, Any]) -> None:
        if context.drive_mode is not DriveMode.TORQUE:
            raise ValueError(f"speed-pi sends a target torque: it drives a standard drive in "
                             f"cyclic synchronous torque mode (--drive-mode torque), not "
                             f"'{context.drive_mode}'")
        p = checked_params("speed-pi", params, SPEED_PI_DEFAULTS)
        w_n, zeta = float(p["speed_bandwidth"]), float(p["damping"])
        self.k_p, self.k_i = 2.0 * zeta * w_n, w_n * w_n
        self.T_max = float(p["T_max"])
        self.load_feedforward = bool(p["load_feedforward"])
        self.J = context.motor.J
        self._T = context.sampling.period
        self.w_int = 0.0  # ∫(ω* − ω) dt, rad

    def step(self, refs: Refs, sample: Sample) -> Command:
        if sample.w_m is None:
            raise ValueError("speed-pi needs the drive's speed (w_m): map its velocity "
                             "actual value 0x606C")
        e = refs.w_ref - sample.w_m
        T_ref = self.J * (self.k_p * e + self.k_i * self.w_int + refs.dw_ref)
        if self.load_feedforward:
            T_ref += refs.T_L
        limited = abs(T_ref) > self.T_max
        if limited:
            T_ref = math.copysign(self.T_max, T_ref)
        else:
            self.w_int += self._T * e  # anti-windup: no integration while clipped
        return Command(target_torque=T_ref, i_limited=limited, logged=(T_ref, self.w_int))

    def withhold(self) -> None:
        """The drive keeps its last target; the loop's state needs no correction."""

    def coast(self) -> None:
        """A missed cycle: the drive holds the last target torque; the integral holds."""


class Stream:
    """The reference profile's speed (CSV), position (CSP) or torque (CST) as the standard
    drive's target (see the module docstring); a
    :class:`gateway.control.interface.DriveController`."""

    #: the drive modes it drives; the first is the command line's default for it
    drive_modes = (DriveMode.VELOCITY, DriveMode.TORQUE, DriveMode.POSITION)

    def __init__(self, context: ControllerContext, params: Mapping[str, Any]) -> None:
        if not context.drive_mode.standard:
            raise ValueError(f"stream sends a target speed, position or torque: it drives a "
                             f"standard drive (--drive-mode velocity, position or torque), "
                             f"not '{context.drive_mode}'")
        checked_params("stream", params, {})
        self.mode = context.drive_mode
        #: the target sent: torque in N·m (CST), speed in rad/s (CSV), position in rad (CSP)
        self.signals = {DriveMode.TORQUE: ("T_ref",), DriveMode.POSITION: ("theta_target",)
                        }.get(self.mode, ("w_target",))
        self._T = context.sampling.period
        self._ahead = context.sampling.delay * self._T
        self.J = context.motor.J
        self._theta = 0.0  # θ* = ∫ω* dt at the last sample, rad
        self._w_last: float | None = None  # ω* at the last sample, rad/s

    def step(self, refs: Refs, sample: Sample) -> Command:
        if self.mode is DriveMode.TORQUE:  # row 1 of (1) inverted: T* that makes ω* vs T_L
            T_ref = (self.J * (refs.dw_ref + self._ahead * refs.ddw_ref)
                     + refs.T_L + self._ahead * refs.dT_L)
            return Command(target_torque=T_ref, logged=(T_ref,))
        if self.mode is DriveMode.POSITION:
            if self._w_last is not None:  # the trapezoid over the period just ended
                self._theta += 0.5 * self._T * (self._w_last + refs.w_ref)
            self._w_last = refs.w_ref
            theta = self._theta + self._ahead * refs.w_ref
            return Command(target_position=theta, logged=(theta,))
        w_target = refs.w_ref + self._ahead * refs.dw_ref
        return Command(target_velocity=w_target, logged=(w_target,))

    def withhold(self) -> None:
        """Nothing to correct: the next target is the profile's again."""

    def coast(self) -> None:
        """A missed cycle: the position integral advances one period at the last ω*."""
        if self._w_last is not None:
            self._theta += self._T * self._w_last
