"""The control laws of Marino, Tomei & Verrelli (IFAC 2002), as pure functions.

Both laws are written in the rotating (d, q) frame of angle ε0 (§E8). They take the
references of the instant (a :class:`References`-like object with ``w_ref``, ``dw_ref``,
``ddw_ref``, ``psi_ref``, ``dpsi_ref``, ``ddpsi_ref``, ``T_L``, ``dT_L``), the controller's
speed estimate ω̂ and the rotor flux in the frame, and return the setpoints, the frame speed
ω0 and the time derivative of ω̂. They hold no state: the continuous-time simulation
integrates their derivatives with scipy, and :class:`gateway.control.controller.Controller`
integrates them once per sampling period.

Units: A, V, Wb, rad/s, N·m, s.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Protocol


class Refs(Protocol):
    """The references of one instant (see ``gateway.reference.References``)."""

    w_ref: float
    dw_ref: float
    ddw_ref: float
    psi_ref: float
    dpsi_ref: float
    ddpsi_ref: float
    T_L: float
    dT_L: float


class Motor(Protocol):
    """Motor parameters with the paper's reparametrisation (section 2)."""

    J: float
    R_s: float
    M: float
    alpha: float
    beta: float
    mu: float
    sigma: float


def sat_tanh(x: float) -> float:
    """The default sat(·) of (15): tanh, C∞, odd, slope 1 at 0, limits ±1 (§E7, §C1)."""
    return math.tanh(x)


def dsat_tanh(x: float) -> float:
    """d sat(x)/dx for :func:`sat_tanh`: 1 − tanh²(x)."""
    th = math.tanh(x)
    return 1.0 - th * th


@dataclass(frozen=True, slots=True)
class Gains:
    """Controller gains (SI units).

    k_w: speed gain kω of (15)/(25), s⁻¹ (paper: 800).
    gamma_1: observer gain γ1 of (18)/(20), Wb²·s (paper: 0.0008).
    gamma_2: observer gain γ2 of (30)/(32), full-order law. The paper gives no value
        (§E7). With γ2 = γ1 the term β·ψ*·e_q/γ2 of (32) has a gain of about
        2·10⁴ s⁻¹ and the sampled loop fails (§E10: 27 rad/s peak speed error at 1 ms
        with one period of delay). Default 0.1: over γ2 ∈ {0.1, 0.3, 1, 3} × ke ∈ {300, 600,
        900} s⁻¹ at 1 ms with one period of delay, γ2 = 0.1 is the value that converges for
        every ke (larger γ2 goes unstable at larger ke); in continuous time the choice costs
        nothing measurable (peak speed error 4·10⁻⁵ rad/s either way).
    k_e: current-error gain ke of (32), s⁻¹. The paper gives no value. Default 600 s⁻¹
        (ke·T = 0.6 at 1 ms): on the grid above, 2× smaller peak speed error at 1 ms than
        300 s⁻¹ and still a margin to 900 s⁻¹.
    i_max: current-vector limit of the setpoints, A (§E11: (15) divides by μψ*, and at
        ψ* = 0.001 Wb any speed-estimate error asks for thousands of amperes). The d current
        (magnetising) has priority; i_sq* is clipped to √(i_max² − i_sd*²).
    k_w_T_max: the bound on kω·T of the full-order law's sampled-data design, where T is
        the period (docs/robustness.md §11): there the speed error reaches the torque
        through the current loop (34), and the sampled loop is stable only for kω·T < 1
        (the paper's kω at 2 ms: 1.6, a divergence). kω is lowered to k_w_T_max/T at
        periods that would exceed it (450 s⁻¹ at 2 ms); at 1 ms and faster the paper's
        kω stands. inf: the paper's kω at every period.
    """

    k_w: float = 800.0
    gamma_1: float = 0.0008
    gamma_2: float = 0.1
    k_e: float = 600.0
    i_max: float = 20.0
    k_w_T_max: float = 0.9

    def __post_init__(self) -> None:
        for name in ("k_w", "gamma_1", "gamma_2", "k_e", "i_max", "k_w_T_max"):
            if not getattr(self, name) > 0.0:
                raise ValueError(f"gain {name} = {getattr(self, name)!r} must be > 0")


@dataclass(frozen=True, slots=True)
class LawOutput:
    """What a law asks for at one instant.

    i_sd_ref, i_sq_ref: current setpoints in the (d, q) frame, A ((15) or (25)).
    u_sd_ref, u_sq_ref: voltage setpoints, V ((32) for the full-order law; the model-based
        feed-forward of the stator-flux equations for the current-fed law).
    w_0: frame speed ω0 = dε0/dt, rad/s ((15) or (26)).
    dw_hat: dω̂/dt, rad/s² ((16)+(20) or (27)+(32)).
    i_limited: True when the current limit clipped i_sq*.
    """

    i_sd_ref: float
    i_sq_ref: float
    u_sd_ref: float
    u_sq_ref: float
    w_0: float
    dw_hat: float
    i_limited: bool


def _current_references(
    r: Refs, w_hat: float, m: Motor, g: Gains, sat=sat_tanh
) -> tuple[float, float, float, bool]:
    """i_sd* and i_sq* of (15)/(25), with the current limit; also returns sat(ω̂ − ω*)."""
    psi_ref = r.psi_ref
    s = sat(w_hat - r.w_ref)
    i_sd_ref = psi_ref / m.M + r.dpsi_ref / (m.alpha * m.M)
    i_sq_ref = (-g.k_w * s + r.T_L / m.J + r.dw_ref) / (m.mu * psi_ref)
    i_q_max_sq = g.i_max * g.i_max - i_sd_ref * i_sd_ref
    i_q_max = math.sqrt(i_q_max_sq) if i_q_max_sq > 0.0 else 0.0
    limited = abs(i_sq_ref) > i_q_max
    if limited:
        i_sq_ref = math.copysign(i_q_max, i_sq_ref)
    return i_sd_ref, i_sq_ref, s, limited


def current_fed(
    r: Refs,
    w_hat: float,
    psi_rd: float,
    psi_rq: float,
    m: Motor,
    g: Gains,
    i_s_dq_applied: tuple[float, float] | None = None,
    sat=sat_tanh,
) -> LawOutput:
    """Current-fed law (15) with the speed observer (16) and adaptation (20).

    ψ_rd, ψ_rq: rotor flux in the (d, q) frame, measured or estimated (24), Wb.
    i_s_dq_applied: the current setpoints acting on the plant over the present period when
        they differ from this instant's (one period of delay); the observer (16) integrates
        the torque of the currents the motor actually receives. None: this instant's.

    The voltage setpoints are the feed-forward of the stator-flux equations of (24) with
    ψ_sd = σ·i_sd* + (M/L_r)·ψ*, ψ_sq = σ·i_sq* (field orientation reached):
    u_sd = R_s·i_sd* + (M/L_r)·ψ̇* − ω0·σ·i_sq*, u_sq = R_s·i_sq* + ω0·(σ·i_sd* + (M/L_r)·ψ*).
    A current-loop drive adds them to its PI output; an ideal current source ignores them.
    """
    i_sd_ref, i_sq_ref, _, limited = _current_references(r, w_hat, m, g, sat)
    psi_ref = r.psi_ref
    w_0 = w_hat + m.alpha * m.M * i_sq_ref / psi_ref  # (15)
    i_sd_obs, i_sq_obs = (i_sd_ref, i_sq_ref) if i_s_dq_applied is None else i_s_dq_applied
    v = psi_ref * psi_rq / g.gamma_1  # (20), with ψ̃_rq = ψ_rq
    dw_hat = m.mu * (psi_rd * i_sq_obs - psi_rq * i_sd_obs) - r.T_L / m.J + v  # (16)
    k_r = m.beta * m.sigma  # M/L_r, since β = M/(σ·L_r) (section 2)
    u_sd_ref = m.R_s * i_sd_ref + k_r * r.dpsi_ref - w_0 * m.sigma * i_sq_ref
    u_sq_ref = m.R_s * i_sq_ref + w_0 * (m.sigma * i_sd_ref + k_r * psi_ref)
    return LawOutput(i_sd_ref, i_sq_ref, u_sd_ref, u_sq_ref, w_0, dw_hat, limited)


def full_order(
    r: Refs,
    w_hat: float,
    psi_rd: float,
    psi_rq: float,
    i_sd: float,
    i_sq: float,
    m: Motor,
    g: Gains,
    sat=sat_tanh,
    dsat=dsat_tanh,
) -> LawOutput:
    """Full-order law: references (25), frame speed (26), observer (27), inputs (32).

    ψ_rd, ψ_rq: rotor flux in the (d, q) frame (measured or estimated (24)), Wb.
    i_sd, i_sq: measured stator currents in the same frame, A.

    With e_d = i_sd − i_sd*, e_q = i_sq − i_sq* (28), φ_d1 = −β·ψ_rq, φ_q1 = β·ψ_rd:
    w = (ψ*·ψ̃_rq − φ_d1·e_d − φ_q1·e_q)/γ2, u_sd = σ·(−φ_d0 − αM·ψ̃_rd − ke·e_d),
    u_sq = σ·(−φ_q0 − ke·e_q) (32). φ_q0 needs d sat(ω̂ − ω*)/dt = sat′·(dω̂/dt − ω̇*)
    (§E7), computed here from (27). When the current limit clips i_sq*, its derivative
    terms in φ_q0 are dropped (the clipped reference is constant).
    """
    alpha, beta, M, sigma, mu = m.alpha, m.beta, m.M, m.sigma, m.mu
    psi_ref = r.psi_ref
    i_sd_ref, i_sq_ref, s, limited = _current_references(r, w_hat, m, g, sat)
    w_0 = w_hat + alpha * M * i_sq / psi_ref  # (26): measured i_sq (§E5)
    e_d = i_sd - i_sd_ref  # (28)
    e_q = i_sq - i_sq_ref
    psi_rd_err = psi_rd - psi_ref
    phi_d1 = -beta * psi_rq
    phi_q1 = beta * psi_rd
    w = (psi_ref * psi_rq - phi_d1 * e_d - phi_q1 * e_q) / g.gamma_2  # (32)
    dw_hat = mu * (psi_rd * i_sq - psi_rq * i_sd) - r.T_L / m.J + w  # (27)
    a_rs = m.R_s / sigma
    phi_d0 = (
        -a_rs * i_sd
        + w_0 * i_sq
        + alpha * beta * psi_rd
        + beta * w_hat * psi_rq
        - alpha * M * beta * i_sd
        - r.dpsi_ref / M
        - r.ddpsi_ref / (alpha * M)
    )
    phi_q0 = -a_rs * i_sq - w_0 * i_sd + alpha * beta * psi_rq - beta * w_hat * psi_rd
    phi_q0 -= alpha * M * beta * i_sq
    if not limited:
        dsat_dt = dsat(w_hat - r.w_ref) * (dw_hat - r.dw_ref)
        torque_term = -g.k_w * s + r.T_L / m.J + r.dw_ref
        phi_q0 += r.dpsi_ref / (mu * psi_ref * psi_ref) * torque_term
        phi_q0 -= (-g.k_w * dsat_dt + r.dT_L / m.J + r.ddw_ref) / (mu * psi_ref)
    u_sd_ref = sigma * (-phi_d0 - alpha * M * psi_rd_err - g.k_e * e_d)  # (32)
    u_sq_ref = sigma * (-phi_q0 - g.k_e * e_q)
    return LawOutput(i_sd_ref, i_sq_ref, u_sd_ref, u_sq_ref, w_0, dw_hat, limited)
