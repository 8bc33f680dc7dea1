"""Indirect field-oriented control with a speed sensor: the baseline of a vector drive
(``--controller ifoc``), beside which the paper's sensorless law is compared.

It is what a drive engineer's vector drive does (Blaschke/Hasse; e.g. Novotny & Lipo,
*Vector Control and Dynamics of AC Drives*, ch. 5), written on model (1) of the paper with
one pole pair:

* Flux: the rotor flux is commanded open loop in the frame of the rotor-flux model,
  i_sd* = ψ*/M + dψ*/dt/(α·M), and the model |ψ̂_r| follows the rotor equation of (1),
  d|ψ_r|/dt = −α·|ψ_r| + α·M·i_sd, integrated exactly over each period with the i_sd that
  acts over it.
* Slip: the frame turns at ω0 = ω + α·M·i_sq/|ψ̂_r| (the slip relation of the rotor
  equation in the flux frame), with ω the measured speed.
* Speed: a PI loop on e = ω* − ω places the closed loop s² + k_p·s + k_i with k_p = 2ζω_n
  and k_i = ω_n² for the mechanical equation dω/dt = T_e/J − T_L/J; the torque demand
  T* = J·(k_p·e + k_i·∫e + dω*/dt) (+ T_L when ``load_feedforward``) becomes
  i_sq* = T*/(J·μ·|ψ̂_r|), since T_e = J·μ·|ψ_r|·i_sq. The integral stops while the
  current limit clips (anti-windup).
* Voltages: the steady-state decoupling feed-forward of the stator equations,
  u_sd* = R_s·i_sd* − ω0·σ·i_sq* + (M/L_r)·d|ψ̂_r|/dt and u_sq* = R_s·i_sq* +
  ω0·(σ·i_sd* + (M/L_r)·|ψ̂_r|), for drives that use them.
* Sampling: the setpoints act over the interval ``delay`` periods after the sample; the
  frame angle sent is the one predicted for that interval's start, as for the paper's laws.

Parameters (``--controller-params FILE.toml``): ``speed_bandwidth`` ω_n (rad/s, default 60),
``damping`` ζ (1.0), ``i_max`` (A, 20: the paper's limit), ``load_feedforward`` (false).
It needs the drive's speed (the ``w_m`` role: a speed sensor; the emulator sends its truth).
"""

from __future__ import annotations

import cmath
import math
from collections import deque
from collections.abc import Mapping
from typing import Any

from gateway.control.controller import wrap_angle
from gateway.control.interface import Command, ControllerContext, Sample, checked_params
from gateway.control.laws import Refs

#: The parameters and their defaults.
DEFAULTS: dict[str, Any] = {"speed_bandwidth": 60.0, "damping": 1.0, "i_max": 20.0,
                            "load_feedforward": False}


class IndirectFieldOriented:
    """IFOC with a speed sensor (see the module docstring); a
    :class:`gateway.control.interface.DriveController`."""

    #: T_ref: torque demand, N·m; w_slip: slip speed, rad/s; psi_r_mod_hat: the flux model,
    #: Wb; w_int: the speed loop's integral, rad.
    signals = ("T_ref", "w_slip", "psi_r_mod_hat", "w_int")
    #: the drive's speed (a speed sensor)
    requires = ("w_m",)

    def __init__(self, context: ControllerContext, params: Mapping[str, Any]) -> None:
        if context.drive_mode.standard:
            raise ValueError(f"ifoc sends current setpoints: it drives a vector drive "
                             f"(--drive-mode ideal, current-loop or voltage), not "
                             f"'{context.drive_mode}'; for a standard drive use speed-pi")
        p = checked_params("ifoc", params, DEFAULTS)
        m = context.motor
        self.motor = m
        self.refs_at = context.refs_at
        self._T = context.sampling.period
        self._delay = context.sampling.delay
        w_n, zeta = float(p["speed_bandwidth"]), float(p["damping"])
        self.k_p, self.k_i = 2.0 * zeta * w_n, w_n * w_n
        self.i_max = float(p["i_max"])
        self.load_feedforward = bool(p["load_feedforward"])
        self._alpha, self._k_r = m.alpha, m.M / m.L_r
        self._decay = math.exp(-m.alpha * self._T)
        self.eps = context.eps_0
        self.psi = 0.0  # |ψ̂_r| at t_k, Wb
        self.w_int = 0.0  # ∫(ω* − ω) dt, rad
        # i_sd of the intervals in flight (the drive holds zero until it receives any)
        self._in_flight: deque[float] = deque([0.0] * self._delay)
        self._last: tuple[float, float] | None = None  # (ω0, i_sd) of the last step
        self._held: float | None = None

    def _flux(self, i_sd: float) -> float:
        """|ψ̂_r| one period on, with ``i_sd`` held over it (exact for (1)'s rotor equation)."""
        return self.psi * self._decay + self.motor.M * i_sd * (1.0 - self._decay)

    def step(self, refs: Refs, sample: Sample) -> Command:
        if sample.w_m is None:
            raise ValueError("ifoc needs the drive's speed (w_m): a drive with a speed "
                             "sensor, or the emulator")
        m, T = self.motor, self._T
        w_m = sample.w_m
        # the flux and its demand
        psi = max(self.psi, 1e-3)
        i_sd = refs.psi_ref / m.M + refs.dpsi_ref / (self._alpha * m.M)
        # the speed loop
        e = refs.w_ref - w_m
        T_ref = m.J * (self.k_p * e + self.k_i * self.w_int + refs.dw_ref)
        if self.load_feedforward:
            T_ref += refs.T_L
        i_sq = T_ref / (m.J * m.mu * psi)
        i_sd = max(-self.i_max, min(self.i_max, i_sd))
        q_max = math.sqrt(max(self.i_max ** 2 - i_sd ** 2, 0.0))
        limited = abs(i_sq) > q_max
        if limited:
            i_sq = math.copysign(q_max, i_sq)
        else:
            self.w_int += T * e  # anti-windup: no integration while clipped
        w_slip = self._alpha * m.M * i_sq / psi
        w_0 = w_m + w_slip
        eps_app = wrap_angle(self.eps + self._delay * T * w_0)
        dpsi = self._alpha * (m.M * i_sd - self.psi)
        sigma = m.sigma
        u_sd = m.R_s * i_sd - w_0 * sigma * i_sq + self._k_r * dpsi
        u_sq = m.R_s * i_sq + w_0 * (sigma * i_sd + self._k_r * self.psi)
        i_dq, u_dq = complex(i_sd, i_sq), complex(u_sd, u_sq)
        to_ab = cmath.exp(1j * (eps_app + 0.5 * T * w_0))
        cmd = Command(i_s_dq_ref=i_dq, u_s_dq_ref=u_dq, eps_0=eps_app, w_0=w_0,
                      i_s_ab_ref=i_dq * to_ab, u_s_ab_ref=u_dq * to_ab, i_limited=limited,
                      logged=(T_ref, w_slip, self.psi, self.w_int))
        # the model over the coming period: the i_sd that acts over it
        if self._delay:
            self._in_flight.append(i_sd)
            acting = self._in_flight.popleft()
            self._held = acting
        else:
            acting = i_sd
        self.psi = self._flux(acting)
        self.eps = wrap_angle(self.eps + T * w_0)
        self._last = (w_0, acting)
        return cmd

    def withhold(self) -> None:
        """The last command was not sent: the drive keeps the i_sd it holds."""
        if self._delay and self._held is not None:
            self._in_flight[-1] = self._held
        self._held = None

    def coast(self) -> None:
        """A missed cycle: the drive holds the last setpoints and turns their frame at ω0."""
        if self._last is None:
            return
        w_0, i_sd = self._last
        self.psi = self._flux(i_sd)
        self.eps = wrap_angle(self.eps + self._T * w_0)
        if self._delay and self._in_flight:
            self._in_flight.append(self._in_flight[-1])
            self._in_flight.popleft()
