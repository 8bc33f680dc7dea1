"""Demand analysis: the peak stator current and voltage (and speed, torque) a reference
profile asks of a motor under perfect tracking (open-loop references (9)–(11)).

Units: SI (s, rad/s, Wb, N·m, A, V). Pure module: no I/O, no clock.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Protocol

import numpy as np

from gateway.reference.signals import Profile

__all__ = ["Demand", "MotorLike", "demand", "demand_trace", "sample_times"]


class MotorLike(Protocol):
    """What :func:`demand` needs of a motor (``plant.params.MotorParams``), SI units."""

    J: float
    R_s: float
    R_r: float
    L_s: float
    L_r: float
    M: float

    @property
    def alpha(self) -> float: ...
    @property
    def mu(self) -> float: ...
    @property
    def sigma(self) -> float: ...


@dataclass(frozen=True, slots=True)
class Demand:
    """Peaks a reference profile demands of a motor under perfect tracking (SI units).

    i_s_peak (A) at t_i_s_peak (s): max |i_s| = |(i_sd*, i_sq*)| of (9), (10).
    u_s_peak (V) at t_u_s_peak (s): max |u_s| from the stator flux in the rotating frame.
    w_peak (rad/s): max |ω*|; w_0_peak (rad/s): max |ω0| of (11) (electrical frequency).
    T_e_peak (N·m) at t_T_e_peak (s): max |T_e| = |J·ω̇* + T_L|.
    i_sd_peak, i_sq_peak (A): max |i_sd*|, max |i_sq*|.
    """

    i_s_peak: float
    t_i_s_peak: float
    u_s_peak: float
    t_u_s_peak: float
    w_peak: float
    w_0_peak: float
    T_e_peak: float
    t_T_e_peak: float
    i_sd_peak: float
    i_sq_peak: float


def sample_times(profile: Profile, dt: float | None = None, max_points: int = 200_000
                 ) -> np.ndarray:
    """Times to sample ``profile`` at, s: a uniform grid of step ``dt`` (default 1e-4 s or
    1/200 of the shortest ramp if smaller) when that takes at most ``max_points``;
    otherwise every transition at step ``dt`` (at most 2000 points each) and the constant
    stretches between them coarsely, so a long profile (``duration = 1e7``) costs megabytes,
    not gigabytes, and no transition is skipped."""
    steps = [s for sig in (profile.speed, profile.flux, profile.load) for s in sig.steps]
    if dt is None:
        dt = min([1e-4, *(s.ramp / 200.0 for s in steps)])
    duration = profile.duration
    n = max(2, math.ceil(duration / dt) + 1)
    if n <= max_points:
        return np.linspace(0.0, duration, n)
    parts = [np.linspace(0.0, duration, max(2, max_points // 4))]
    for s in steps:
        if s.t < duration:
            end = min(s.end, duration)
            parts.append(np.linspace(s.t, end, min(2000, max(3, math.ceil((end - s.t) / dt)))))
    return np.unique(np.concatenate(parts))


def demand_trace(profile: Profile, motor: MotorLike, dt: float | None = None
                 ) -> dict[str, np.ndarray]:
    """Open-loop currents, frame speed and voltages along the reference profile ``profile``
    on a fine grid.

    Grid (:func:`sample_times`) of step ``dt`` (s): by default 1e-4 s or 1/200 of the
    shortest ramp if smaller; long profiles get a dense grid only on their transitions.
    Perfect tracking (ω = ω*, ψ_rd = ψ*, ψ_rq = 0):
      i_sd* = ψ*/M + ψ̇*/(αM)                  (9)
      i_sq* = (T_L/J + ω̇*)/(μψ*)              (10)
      ω0 = ω* + αM·i_sq*/ψ*                     (11)
      ψ_sd = σ·i_sd* + (M/L_r)·ψ*,  ψ_sq = σ·i_sq*   (stator flux, §E1)
      u_sd = dψ_sd/dt + R_s·i_sd* − ω0·ψ_sq,  u_sq = dψ_sq/dt + R_s·i_sq* + ω0·ψ_sd
    with dψ_s/dt by central finite differences (numpy.gradient) on the grid.
    Keys: t, w_ref, psi_ref, T_L, i_sd, i_sq, w_0, u_sd, u_sq, T_e (N·m).
    """
    t = sample_times(profile, dt)
    r = profile.sample(t)
    m = motor
    alpha, mu, sigma, M = m.alpha, m.mu, m.sigma, m.M
    psi = r["psi_ref"]
    i_sd = psi / M + r["dpsi_ref"] / (alpha * M)
    i_sq = (r["T_L"] / m.J + r["dw_ref"]) / (mu * psi)
    w_0 = r["w_ref"] + alpha * M * i_sq / psi
    psi_sd = sigma * i_sd + (M / m.L_r) * psi
    psi_sq = sigma * i_sq
    u_sd = np.gradient(psi_sd, t) + m.R_s * i_sd - w_0 * psi_sq
    u_sq = np.gradient(psi_sq, t) + m.R_s * i_sq + w_0 * psi_sd
    T_e = m.J * r["dw_ref"] + r["T_L"]
    return {"t": t, "w_ref": r["w_ref"], "psi_ref": psi, "T_L": r["T_L"], "i_sd": i_sd,
            "i_sq": i_sq, "w_0": w_0, "u_sd": u_sd, "u_sq": u_sq, "T_e": T_e}


def demand(profile: Profile, motor: MotorLike, dt: float | None = None) -> Demand:
    """Peak current, voltage, speed and torque ``profile`` asks of ``motor`` (see
    :func:`demand_trace`). Compare i_s_peak with the drive's trip level and u_s_peak with
    its voltage limit u_dc/√3 before running a profile."""
    d = demand_trace(profile, motor, dt)
    t = d["t"]
    i_s = np.hypot(d["i_sd"], d["i_sq"])
    u_s = np.hypot(d["u_sd"], d["u_sq"])
    T_e = np.abs(d["T_e"])
    ki, ku, kt = int(np.argmax(i_s)), int(np.argmax(u_s)), int(np.argmax(T_e))
    return Demand(
        i_s_peak=float(i_s[ki]), t_i_s_peak=float(t[ki]),
        u_s_peak=float(u_s[ku]), t_u_s_peak=float(t[ku]),
        w_peak=float(np.max(np.abs(d["w_ref"]))), w_0_peak=float(np.max(np.abs(d["w_0"]))),
        T_e_peak=float(T_e[kt]), t_T_e_peak=float(t[kt]),
        i_sd_peak=float(np.max(np.abs(d["i_sd"]))), i_sq_peak=float(np.max(np.abs(d["i_sq"]))),
    )
