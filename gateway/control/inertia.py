"""Commissioning, rotating: the rotor's inertia J and its friction, from torque steps within
a speed and a torque limit (``--controller identify-rotating``; `hil-gateway identify
--rotate` runs it after the standstill test, with the motor that test found;
docs/robustness.md §8).

The test. Field-oriented with the drive's speed sensor (the rotor-flux model of
:mod:`gateway.control.ifoc`): the flux is set to ``flux`` and held for five rotor time
constants, then the torque current i_sq = ±T/((M/L_r)·ψ̂_r) for the torque ``torque`` takes
the rotor from rest to +W (``speed``), down to −W and back to 0, and a speed loop brings it
to rest and holds it there. Over the steps the mechanical equation of (1) with one pole
pair,

    J·dω/dt = T_e − B·ω − c·sign(ω) − T_L,       T_e = (M/L_r)·Im(ψ̄_r·i_s),        (1)

holds with T_L = 0 (no load: the standstill profile), viscous friction B and Coulomb
friction c. Integrated from the first step's start t_0 to each sample t_k, with the torque
T_e,j each period j acted with (the current commanded d periods before, held; the flux
model's ψ̂_r):

    J·(ω_k − ω_0) + B·∫ω dt + c·∫sign(ω) dt = ∫T_e dt,                               (J1)

linear in (J, B, c): least squares over the samples of the steps (the integrals by the
trapezoid rule; ∫sign(ω) exact between the samples where ω changes sign). The integrated
form keeps the speed sensor's noise out of the regressors' differences.

The frame (docs/robustness.md §8): the setpoints computed at t_k act over
(t_{k+d}, t_{k+d+1}]; their frame speed takes the speed extrapolated to that interval's
middle, their angle is where the last commanded interval ends (no jump between intervals).

What it needs: a drive that takes current setpoints and reports its speed (the ``w_m``
role); the motor file's electrical parameters (the standstill test's), for the torque.
A rotor that does not reach the speed limit within the test's time (J more than
:data:`J_RANGE` times the motor file's, or a load), or runs past 1.5 × the limit, is
refused with the reason.

Pure module: no I/O, no clock, no global state.
"""

from __future__ import annotations

import cmath
import math
from collections import deque
from collections.abc import Mapping
from dataclasses import asdict
from enum import Enum
from typing import Any

import numpy as np

from dbc.modes import DriveMode
from gateway.control.controller import wrap_angle
from gateway.control.identify import Estimate, verdict
from gateway.control.interface import Command, ControllerContext, Sample, checked_params
from gateway.control.laws import Refs

#: the controller's parameters and their defaults: speed limit W, rad/s; torque, N·m;
#: rotor flux, Wb
DEFAULTS: dict[str, Any] = {"speed": 50.0, "torque": 1.0, "flux": 1.0}
#: the test allows J up to this many times the motor file's (its duration)
J_RANGE = 3.0
#: the magnetisation lasts this many rotor time constants
MAGNETISE_TAUS = 5.0
#: the speed loop that brings the rotor to rest after the steps, 1/s
BRAKE_GAIN = 20.0
#: |ω| beyond this many times the speed limit: torque off, the test refused
OVERSPEED = 1.5


class Phase(Enum):
    MAGNETISE = 0
    UP = 1  # +T until ω ≥ W
    DOWN = 2  # −T until ω ≤ −W
    BACK = 3  # +T until ω ≥ 0
    REST = 4  # the speed loop to rest
    STOPPED = 5  # overspeed: torque off


def duration(motor: Any, params: Mapping[str, Any] | None = None) -> float:
    """How long the test runs, s: the magnetisation, the three steps for J up to
    :data:`J_RANGE` × the motor's (J·W/T each, two of them across 2W), and 1 s at rest."""
    p = checked_params("identify-rotating", params or {}, DEFAULTS)
    steps = 4.0 * J_RANGE * motor.J * float(p["speed"]) / float(p["torque"])
    return MAGNETISE_TAUS / motor.alpha + steps + 1.0


def fit_rotating(w: np.ndarray, T_e: np.ndarray, period: float) -> dict[str, Any]:
    """(J1) over the samples ``w`` (rad/s, w[0] at the first step's start) with the torque
    ``T_e[k]`` (N·m) that acted over (t_{k−1}, t_k] (T_e[0] unused): J, B, c, each with its
    standard deviation; ValueError when they do not make a rotor."""
    w = np.asarray(w, dtype=float)
    T_e = np.asarray(T_e, dtype=float)
    if len(w) < 20:
        raise ValueError(f"the rotating test gave {len(w)} samples; it needs at least 20")
    T = period
    w0, w1 = w[:-1], w[1:]
    int_w = np.concatenate([[0.0], np.cumsum(0.5 * T * (w0 + w1))])
    # ∫sign(ω) over each period: exact for ω linear between the samples
    same = np.sign(w0) == np.sign(w1)
    frac = np.where(same, 1.0, np.abs(w1) / np.maximum(np.abs(w1) + np.abs(w0), 1e-300))
    sgn = np.where(same, np.sign(w1), np.sign(w1) * (2.0 * frac - 1.0))
    int_s = np.concatenate([[0.0], np.cumsum(T * sgn)])
    int_t = np.concatenate([[0.0], np.cumsum(T * T_e[1:])])
    X = np.column_stack([w - w[0], int_w, int_s])[1:]
    y = int_t[1:]
    coef, *_ = np.linalg.lstsq(X, y, rcond=None)
    r = y - X @ coef
    dof = max(1, len(y) - 3)
    s2 = float(r @ r) / dof
    # the integrated rows' residuals are correlated: the standard deviations from the
    # per-period rows (J1 differenced) instead
    dX, dy = np.diff(np.vstack([np.zeros(3), X]), axis=0), np.diff(np.concatenate([[0.0], y]))
    rd = dy - dX @ coef
    sd2 = float(rd @ rd) / dof
    cov = sd2 * np.linalg.pinv(dX.T @ dX)
    std = np.sqrt(np.maximum(np.diag(cov), 0.0))
    J, B, c = (float(x) for x in coef)
    if not J > 0:
        raise ValueError(f"the fit gives J = {J:.4g} kg·m², not a rotor: the speed did not "
                         "follow the torque (is the drive's speed the rotor's, in rad/s?)")
    return {"J": J, "J_std": float(std[0]), "B": B, "B_std": float(std[1]), "c": c,
            "c_std": float(std[2]), "rms_Nms": math.sqrt(s2), "samples": len(w)}


class RotatingTest:
    """The rotating test as a controller (see the module docstring); a
    :class:`gateway.control.interface.DriveController`. :meth:`summary` fits it."""

    #: i_sq_test: the torque current commanded, A; T_e_hat: the torque it makes, N·m;
    #: phase: the test's phase (0 magnetise, 1 up, 2 down, 3 back, 4 rest, 5 stopped)
    signals = ("i_sq_test", "T_e_hat", "phase")
    drive_modes = (DriveMode.IDEAL, DriveMode.CURRENT_LOOP)
    #: the drive's speed (a speed sensor)
    requires = ("w_m",)

    def __init__(self, context: ControllerContext, params: Mapping[str, Any]) -> None:
        if context.drive_mode not in self.drive_modes:
            raise ValueError(f"identify-rotating sets the stator current: it needs a drive "
                             f"that takes current setpoints (--drive-mode ideal or "
                             f"current-loop), not '{context.drive_mode}'")
        p = checked_params("identify-rotating", params, DEFAULTS)
        m = context.motor
        self.motor = m
        self.speed = float(p["speed"])
        self.torque = float(p["torque"])
        self.flux = float(p["flux"])
        self._T = context.sampling.period
        self._delay = context.sampling.delay
        self._k_t = m.M / m.L_r  # T_e = k_t·ψ_r·i_sq
        self._decay = math.exp(-m.alpha * self._T)
        self._t_mag = MAGNETISE_TAUS / m.alpha
        self.i_sd = self.flux / m.M
        self.i_sq_step = self.torque / (self._k_t * self.flux)
        self.phase = Phase.MAGNETISE
        self._k = 0
        # the frame angle at the start of the next interval to command: the end of the
        # last one commanded (the frame turns on without a jump from interval to interval)
        self.eps_next = context.eps_0
        self._w_prev: float | None = None
        self._w0s = (0.0, 0.0)
        self.psi = 0.0  # the flux model's |ψ̂_r|, Wb
        # (i_sd, i_sq) of the intervals in flight (the drive holds zero until it receives any)
        self._in_flight: deque[tuple[float, float]] = deque([(0.0, 0.0)] * self._delay)
        self._acting = (0.0, 0.0)  # what acted over the period that ended at this sample
        self._held: tuple[float, float] | None = None
        self._w: list[float] = []
        self._T_e: list[float] = []
        self._why = ""

    @property
    def speed_limit(self) -> float:
        """The divergence guard's bound (:meth:`gateway.guard.Envelope.for_controller`)."""
        return self.speed

    def _next_phase(self, w_m: float) -> None:
        ph, W = self.phase, self.speed
        if ph in (Phase.STOPPED, Phase.REST):
            return
        if abs(w_m) > OVERSPEED * W:
            self.phase = Phase.STOPPED
            self._why = (f"the rotor ran to {w_m:.4g} rad/s, past {OVERSPEED:g} × the "
                         f"speed limit of {W:g} rad/s: torque off (is the drive's speed "
                         "the rotor's, and the motor file's?)")
        elif ph is Phase.MAGNETISE and self._k * self._T >= self._t_mag:
            self.phase = Phase.UP
        elif ph is Phase.UP and w_m >= W:
            self.phase = Phase.DOWN
        elif ph is Phase.DOWN and w_m <= -W:
            self.phase = Phase.BACK
        elif ph is Phase.BACK and w_m >= 0.0:
            self.phase = Phase.REST

    def step(self, refs: Refs, sample: Sample) -> Command:
        if sample.w_m is None:
            raise ValueError("identify-rotating needs the drive's speed (w_m): a drive with "
                             "a speed sensor, or the emulator")
        w_m, T = sample.w_m, self._T
        was = self.phase
        self._next_phase(w_m)
        if self.phase in (Phase.UP, Phase.DOWN, Phase.BACK) or (
                was in (Phase.UP, Phase.DOWN, Phase.BACK)):
            # the sample ends a period of the steps: its speed and the torque that acted
            self._w.append(w_m)
            self._T_e.append(self._k_t * self.psi * self._acting[1])
        ph = self.phase
        if ph in (Phase.UP, Phase.BACK):
            i_sq = self.i_sq_step
        elif ph is Phase.DOWN:
            i_sq = -self.i_sq_step
        elif ph is Phase.REST:
            i_sq = max(-self.i_sq_step, min(self.i_sq_step, -BRAKE_GAIN * self.motor.J * w_m
                                            / (self._k_t * max(self.psi, 1e-3))))
        else:
            i_sq = 0.0
        i_sd = self.i_sd if ph is not Phase.STOPPED else 0.0
        psi = max(self.psi, 1e-3)
        # the speed over the commanded interval, t_k + (d + ½)·T on: extrapolated from the
        # last period's change (a stale speed makes the slip short by the acceleration's
        # worth and the torque low: 1.5 % at 133 rad/s²)
        dw = w_m - self._w_prev if self._w_prev is not None else 0.0
        self._w_prev = w_m
        w_mid = w_m + (self._delay + 0.5) * dw
        w_0 = w_mid + self.motor.alpha * self.motor.M * i_sq / psi  # the slip relation
        eps_app = self.eps_next
        i_dq = complex(i_sd, i_sq)
        to_ab = cmath.exp(1j * (eps_app + 0.5 * T * w_0))
        cmd = Command(i_s_dq_ref=i_dq, eps_0=eps_app, w_0=w_0, i_s_ab_ref=i_dq * to_ab,
                      logged=(i_sq, self._k_t * self.psi * i_sq, float(ph.value)))
        if self._delay:
            self._in_flight.append((i_sd, i_sq))
            acting = self._in_flight.popleft()
            self._held = acting
        else:
            acting = (i_sd, i_sq)
        self._advance(acting, w_0)
        self._k += 1
        return cmd

    def _advance(self, acting: tuple[float, float], w_0: float) -> None:
        """The flux model and the frame over the coming period, with the currents that act
        over it."""
        self.psi = self.psi * self._decay + self.motor.M * acting[0] * (1.0 - self._decay)
        self.eps_next = wrap_angle(self.eps_next + self._T * w_0)
        self._w0s = (self._w0s[1], w_0)  # (the interval before's ω0, this one's)
        self._acting = acting

    def withhold(self) -> None:
        """The last command was not sent: the drive keeps what it holds, and turns its frame
        on at the interval before's ω0."""
        if self._delay and self._held is not None:
            self._in_flight[-1] = self._held
        before, sent = self._w0s
        self.eps_next = wrap_angle(self.eps_next + self._T * (before - sent))
        self._w0s = (before, before)

    def coast(self) -> None:
        """A cycle without a sample: a gap in the record (the fit needs none: refused)."""
        self._k += 1
        if self.phase in (Phase.UP, Phase.DOWN, Phase.BACK):
            self._why = self._why or "cycles were missed during the steps"

    def summary(self) -> dict[str, Any]:
        """The fit (summary.json's ``identification``), or why there is none."""
        out: dict[str, Any] = {"test": "rotating", "speed_limit": self.speed,
                               "torque": self.torque, "flux": self.flux}
        if self._why:
            return {**out, "ok": False, "reason": self._why}
        if self.phase is not Phase.REST:
            return {**out, "ok": False, "reason": (
                f"the steps did not end within the test (phase {self.phase.name.lower()}): "
                f"J more than {J_RANGE:g} × the motor file's ({self.motor.J:g} kg·m²), or a "
                "load; give the motor file a J nearer the motor's, or a larger --torque")}
        try:
            fit = fit_rotating(np.array(self._w), np.array(self._T_e), self._T)
        except ValueError as exc:
            return {**out, "ok": False, "reason": str(exc)}
        scale = self.torque / self.speed  # friction in units of the test's torque at W
        values = {
            "J": Estimate(fit["J"], fit["J_std"], "kg·m²", verdict(fit["J_std"] / fit["J"])),
            "friction_viscous": Estimate(fit["B"], fit["B_std"], "N·m·s",
                                         verdict(fit["B_std"] / scale)),
            "friction_coulomb": Estimate(fit["c"], fit["c_std"], "N·m",
                                         verdict(fit["c_std"] / self.torque)),
        }
        return {**out, "ok": True, "samples": fit["samples"], "residual_Nms": fit["rms_Nms"],
                "values": {k: asdict(e) for k, e in values.items()}}
