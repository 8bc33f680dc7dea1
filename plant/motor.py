"""Model (1) of Marino, Tomei & Verrelli (IFAC 2002) in the fixed (a, b) frame (pure).

The induction motor with one pole pair, linear magnetics, load torque T_L an input:

    dω/dt   = μ(ψ_ra·i_sb − ψ_rb·i_sa) − T_L/J                                   (1), row 1
    dψ_r/dt = −α·ψ_r + jω·ψ_r + αM·i_s                                            (1), rows 2–3
    di_s/dt = −(R_s/σ)·i_s + u_s/σ + βα·ψ_r − jβω·ψ_r − βαM·i_s                   (1), rows 4–5

written with complex space vectors ψ_r = ψ_ra + jψ_rb, i_s = i_sa + ji_sb, u_s = u_sa + ju_sb
(check: Re(jω·ψ_r) = −ω·ψ_rb, Im(−jβω·ψ_r) = −βω·ψ_ra, as printed). Rows 4–5 equal
di_s/dt = (u_s − R_s·i_s)/σ − β·dψ_r/dt, i.e. dψ_s/dt = u_s − R_s·i_s with the stator flux
ψ_s = σ·i_s + (M/L_r)·ψ_r (§E1). The current-fed model is rows 1–3 with i_s an input.

Units: ω in rad/s, ψ in Wb, i in A, u in V, T in N·m, t in s.

Two forms:

* array right-hand sides for :func:`scipy.integrate.solve_ivp` (:func:`rhs_full`,
  :func:`rhs_current_fed`; state ``[ω, ψ_ra, ψ_rb, i_sa, i_sb]`` or ``[ω, ψ_ra, ψ_rb]``);
* scalar complex forms and classical RK4 steps for the fixed-step integrator of the drive
  (:func:`rk4_step_full`, :func:`rk4_step_current_fed`), taking the precomputed
  :class:`Coeffs`. :class:`plant.drive.Drive` runs the same operations, in the same order,
  on the real and imaginary parts as float locals, a whole period's steps in one function
  (the same numbers, bit for bit: tests/test_fast_paths.py); these are its reference.
"""

from __future__ import annotations

from collections.abc import Sequence
from typing import NamedTuple

from dbc.motor import MotorParams


class Coeffs(NamedTuple):
    """Constants of model (1) precomputed from :class:`MotorParams` (SI units)."""

    alpha: float  # α = R_r/L_r, 1/s
    alpha_M: float  # α·M, Ω
    beta: float  # β = M/(σL_r), 1/H
    mu: float  # μ = M/(J·L_r)
    inv_J: float  # 1/J, 1/(kg·m²)
    inv_sigma: float  # 1/σ, 1/H
    R_s_over_sigma: float  # R_s/σ, 1/s
    R_s: float  # Ω
    sigma: float  # H
    M_over_L_r: float  # M/L_r


def coeffs(motor: MotorParams) -> Coeffs:
    """The constants of (1) for the scalar functions below."""
    return Coeffs(
        alpha=motor.alpha,
        alpha_M=motor.alpha * motor.M,
        beta=motor.beta,
        mu=motor.mu,
        inv_J=1.0 / motor.J,
        inv_sigma=1.0 / motor.sigma,
        R_s_over_sigma=motor.R_s / motor.sigma,
        R_s=motor.R_s,
        sigma=motor.sigma,
        M_over_L_r=motor.M / motor.L_r,
    )


# ---- algebraic relations -------------------------------------------------------------------
def torque(motor: MotorParams, psi_r_ab: complex, i_s_ab: complex) -> float:
    """T_e = J·μ·(ψ_ra·i_sb − ψ_rb·i_sa) = (M/L_r)·Im(conj(ψ_r)·i_s), N·m (row 1 of (1))."""
    return motor.J * motor.mu * (psi_r_ab.real * i_s_ab.imag - psi_r_ab.imag * i_s_ab.real)


def stator_flux(motor: MotorParams, psi_r_ab: complex, i_s_ab: complex) -> complex:
    """ψ_s = σ·i_s + (M/L_r)·ψ_r, Wb (§E1)."""
    return motor.sigma * i_s_ab + (motor.M / motor.L_r) * psi_r_ab


def rotor_current(motor: MotorParams, psi_r_ab: complex, i_s_ab: complex) -> complex:
    """i_r = (ψ_r − M·i_s)/L_r, A (from ψ_r = L_r·i_r + M·i_s)."""
    return (psi_r_ab - motor.M * i_s_ab) / motor.L_r


def magnetic_energy(motor: MotorParams, psi_r_ab: complex, i_s_ab: complex) -> float:
    """W = σ|i_s|²/2 + |ψ_r|²/(2L_r), J: the energy stored in the magnetic field."""
    return 0.5 * motor.sigma * abs(i_s_ab) ** 2 + 0.5 * abs(psi_r_ab) ** 2 / motor.L_r


# ---- right-hand sides for scipy -------------------------------------------------------------
def rhs_full(
    t: float, x: Sequence[float], motor: MotorParams, u_s_ab: complex, T_L: float
) -> list[float]:
    """d/dt [ω, ψ_ra, ψ_rb, i_sa, i_sb] of the full model (1); inputs u_s_ab (V), T_L (N·m).

    For ``solve_ivp(rhs_full, ..., args=(motor, u_s_ab, T_L))``; time-varying inputs via a
    lambda. Written from the printed rows of (1), component by component.
    """
    w, pa, pb, ia, ib = x
    a, b, mu, M = motor.alpha, motor.beta, motor.mu, motor.M
    rs = motor.R_s / motor.sigma
    return [
        mu * (pa * ib - pb * ia) - T_L / motor.J,
        -a * pa - w * pb + a * M * ia,
        -a * pb + w * pa + a * M * ib,
        -rs * ia + u_s_ab.real / motor.sigma + b * a * pa + b * w * pb - b * a * M * ia,
        -rs * ib + u_s_ab.imag / motor.sigma + b * a * pb - b * w * pa - b * a * M * ib,
    ]


def rhs_current_fed(
    t: float, x: Sequence[float], motor: MotorParams, i_s_ab: complex, T_L: float
) -> list[float]:
    """d/dt [ω, ψ_ra, ψ_rb] of the current-fed model (first three rows of (1)), i_s_ab in A."""
    w, pa, pb = x
    a, M = motor.alpha, motor.M
    ia, ib = i_s_ab.real, i_s_ab.imag
    return [
        motor.mu * (pa * ib - pb * ia) - T_L / motor.J,
        -a * pa - w * pb + a * M * ia,
        -a * pb + w * pa + a * M * ib,
    ]


# ---- scalar complex forms and RK4 ------------------------------------------------------------
def derivs_full(
    c: Coeffs, w_m: float, psi_r_ab: complex, i_s_ab: complex, u_s_ab: complex, T_L: float
) -> tuple[float, complex, complex]:
    """(dω/dt, dψ_r/dt, di_s/dt) of (1) in complex form (rad/s², Wb/s, A/s)."""
    dpsi = complex(-c.alpha, w_m) * psi_r_ab + c.alpha_M * i_s_ab
    di = (u_s_ab - c.R_s * i_s_ab) * c.inv_sigma - c.beta * dpsi
    dw = c.mu * (psi_r_ab.real * i_s_ab.imag - psi_r_ab.imag * i_s_ab.real) - T_L * c.inv_J
    return dw, dpsi, di


def rk4_step_full(
    c: Coeffs, w_m: float, psi_r_ab: complex, i_s_ab: complex, u_s_ab: complex, T_L: float,
    h: float,
) -> tuple[float, complex, complex]:
    """One classical RK4 step of (1) over h (s) with u_s_ab and T_L held (ZOH).

    Returns (ω, ψ_r, i_s) at t + h. Written out (no calls, no allocations beyond the
    complex scalars); the drive's internal steps are this step on float locals.
    """
    a = c.alpha
    aM = c.alpha_M
    beta = c.beta
    mu = c.mu
    rs = c.R_s_over_sigma
    u_sig = u_s_ab * c.inv_sigma
    load = T_L * c.inv_J
    hh = 0.5 * h
    w, p, i = w_m, psi_r_ab, i_s_ab
    # stage 1
    dp1 = complex(-a, w) * p + aM * i
    di1 = u_sig - rs * i - beta * dp1
    dw1 = mu * (p.real * i.imag - p.imag * i.real) - load
    # stage 2
    w2 = w + hh * dw1
    p2 = p + hh * dp1
    i2 = i + hh * di1
    dp2 = complex(-a, w2) * p2 + aM * i2
    di2 = u_sig - rs * i2 - beta * dp2
    dw2 = mu * (p2.real * i2.imag - p2.imag * i2.real) - load
    # stage 3
    w3 = w + hh * dw2
    p3 = p + hh * dp2
    i3 = i + hh * di2
    dp3 = complex(-a, w3) * p3 + aM * i3
    di3 = u_sig - rs * i3 - beta * dp3
    dw3 = mu * (p3.real * i3.imag - p3.imag * i3.real) - load
    # stage 4
    w4 = w + h * dw3
    p4 = p + h * dp3
    i4 = i + h * di3
    dp4 = complex(-a, w4) * p4 + aM * i4
    di4 = u_sig - rs * i4 - beta * dp4
    dw4 = mu * (p4.real * i4.imag - p4.imag * i4.real) - load
    h6 = h / 6.0
    return (
        w + h6 * (dw1 + 2.0 * (dw2 + dw3) + dw4),
        p + h6 * (dp1 + 2.0 * (dp2 + dp3) + dp4),
        i + h6 * (di1 + 2.0 * (di2 + di3) + di4),
    )


def rk4_step_current_fed(
    c: Coeffs, w_m: float, psi_r_ab: complex, i_s_0: complex, i_s_mid: complex,
    i_s_1: complex, T_L: float, h: float,
) -> tuple[float, complex]:
    """One classical RK4 step of rows 1–3 of (1) over h (s), current-fed.

    The stator current is an input known at the step's start, midpoint and end
    (``i_s_0``, ``i_s_mid``, ``i_s_1``, A), as RK4 samples it. Returns (ω, ψ_r) at t + h.
    """
    a = c.alpha
    aM = c.alpha_M
    mu = c.mu
    load = T_L * c.inv_J
    hh = 0.5 * h
    w, p = w_m, psi_r_ab
    dp1 = complex(-a, w) * p + aM * i_s_0
    dw1 = mu * (p.real * i_s_0.imag - p.imag * i_s_0.real) - load
    w2 = w + hh * dw1
    p2 = p + hh * dp1
    dp2 = complex(-a, w2) * p2 + aM * i_s_mid
    dw2 = mu * (p2.real * i_s_mid.imag - p2.imag * i_s_mid.real) - load
    w3 = w + hh * dw2
    p3 = p + hh * dp2
    dp3 = complex(-a, w3) * p3 + aM * i_s_mid
    dw3 = mu * (p3.real * i_s_mid.imag - p3.imag * i_s_mid.real) - load
    w4 = w + h * dw3
    p4 = p + h * dp3
    dp4 = complex(-a, w4) * p4 + aM * i_s_1
    dw4 = mu * (p4.real * i_s_1.imag - p4.imag * i_s_1.real) - load
    h6 = h / 6.0
    return (
        w + h6 * (dw1 + 2.0 * (dw2 + dw3) + dw4),
        p + h6 * (dp1 + 2.0 * (dp2 + dp3) + dp4),
    )
