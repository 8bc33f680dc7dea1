"""A user's own controller for can-drive-hil: field-oriented speed control with a speed
sensor, written against the controller interface alone (docs/controllers.md).

Install it beside can-drive-hil (``pip install -e examples/pi_foc``) and run it by the name
its package registers, or by module and class without installing it::

    hil-gateway simulate --controller pi-foc --controller-params examples/pi_foc/gains.toml
    PYTHONPATH=examples/pi_foc/src hil-gateway sim --controller pi_foc:PiSpeedFoc
"""

from __future__ import annotations

import cmath
import math
from collections.abc import Mapping
from typing import Any

from gateway.control.interface import Command, ControllerContext, Sample

__all__ = ["PiSpeedFoc"]


class PiSpeedFoc:
    """Rotor-flux-oriented speed control: a PI speed loop gives the torque, the rotor model
    gives the flux and the slip, the drive's current loop does the rest.

    Parameters: ``kp`` (1/s) and ``ki`` (1/s²) of the speed loop, per unit of inertia
    (defaults 100 and 2500), ``i_max`` (A, 15).
    """

    #: what it logs: the torque it asks for (N·m) and its rotor-flux model (Wb)
    signals = ("torque_demand", "flux_model")
    #: the drive must send its speed (a sensor)
    requires = ("w_m",)

    def __init__(self, context: ControllerContext, params: Mapping[str, Any]) -> None:
        unknown = set(params) - {"kp", "ki", "i_max"}
        if unknown:
            raise ValueError(f"unknown parameters {sorted(unknown)}; pi_foc takes kp, ki, "
                             "i_max")
        self.motor = m = context.motor
        self.T, self.delay = context.sampling.period, context.sampling.delay
        self.kp = float(params.get("kp", 100.0))
        self.ki = float(params.get("ki", 2500.0))
        self.i_max = float(params.get("i_max", 15.0))
        self.tau_r = m.L_r / m.R_r  # rotor time constant, s
        self.angle = 0.0  # the flux frame's angle at t_k, rad
        self.flux = 0.0  # rotor-flux model, Wb
        self.integral = 0.0  # ∫ speed error dt, rad
        self.frame_speed = 0.0

    def step(self, refs: Any, sample: Sample) -> Command:
        m = self.motor
        if sample.w_m is None:
            raise ValueError("pi_foc needs the drive's speed")
        error = refs.w_ref - sample.w_m
        torque = m.J * (self.kp * error + self.ki * self.integral)
        i_d = refs.psi_ref / m.M + self.tau_r * refs.dpsi_ref / m.M
        flux = max(self.flux, 0.01)
        i_q = torque * m.L_r / (m.M * flux)  # T_e = (M/L_r)·ψ_r·i_q
        room = math.sqrt(max(self.i_max ** 2 - i_d ** 2, 0.0))
        if abs(i_q) > room:
            i_q = math.copysign(room, i_q)  # clipped: the integral waits
        else:
            self.integral += self.T * error
        slip = m.M * i_q / (self.tau_r * flux)
        w_0 = sample.w_m + slip
        start = self.angle + self.delay * self.T * w_0  # the frame when they act
        i_dq = complex(i_d, i_q)
        self.flux += self.T / self.tau_r * (m.M * i_d - self.flux)
        self.angle = math.remainder(self.angle + self.T * w_0, 2 * math.pi)
        self.frame_speed = w_0
        return Command(i_s_dq_ref=i_dq, u_s_dq_ref=0j,
                       eps_0=math.remainder(start, 2 * math.pi), w_0=w_0,
                       i_s_ab_ref=i_dq * cmath.exp(1j * (start + 0.5 * self.T * w_0)),
                       u_s_ab_ref=0j, i_limited=abs(i_q) >= room,
                       logged=(torque, self.flux))

    def withhold(self) -> None:
        """Its setpoints were not sent: nothing to undo (its model is the command's)."""

    def coast(self) -> None:
        """A missed cycle: the drive kept turning the frame at the last speed."""
        self.angle = math.remainder(self.angle + self.T * self.frame_speed, 2 * math.pi)
