"""Commissioning at standstill: the motor's electrical parameters, the current sensors'
offsets and the inverter's voltage error, from DC current steps on one axis
(``--controller identify``; `hil-gateway identify` writes the motor file; docs/robustness.md
§6).

The test. The drive takes current setpoints (``--drive-mode ideal`` or ``current-loop``). The
controller holds the current vector on the a axis of the fixed frame (ε0 = 0, ω0 = 0) at
+I, +2I, −I, −2I for ``hold`` seconds each, then 0. On one axis current and rotor flux stay
collinear, so the torque (M/L_r)·ψ_r × i_s is zero and the rotor does not turn: the standstill
model (1) with ω = 0 holds,

    u_s = R_s·i_s + σ·di_s/dt + (M/L_r)·dψ_r/dt,      dψ_r/dt = −α·ψ_r + α·M·i_s,      (1)

with σ = L_s − M²/L_r (§E1) and α = R_r/L_r. Per sample t_k (period T) the drive reports
the current i_k and the average voltage ū_k over (t_{k−1}, t_k] (the timing contract); a
current held over the period at i_k gives, exactly,

    T·ū_k = R_s·T·i_k + σ·(i_k − i_{k−1}) + L_μ·(c_k − c_{k−1}),                      (I1)
    c_k = e^{−αT}·c_{k−1} + (1 − e^{−αT})·i_k,     L_μ = M²/L_r,

the rotor flux of (1) in the stator's units ((M/L_r)·ψ_r = L_μ·c). Two errors of a real
drive enter linearly. A sensor offset o (the drive regulates the *measured* current, so the
true one is i − o) adds −R_s·o·T and a multiple of Δe^{−αkT} (the flux of −o settling; the
same term takes the flux at the start); the inverter's voltage error (dead time) adds
D·T·g(i_k), g the Clarke transform of the three phase currents' signs (the emulator's
dead-time model: D = dead_time·f_pwm·u_dc). For a given α, (I1) with these terms is linear
in (R_s, σ, L_μ, D, R_s·o, the start term): least squares over every sample, the real and
imaginary parts stacked. α is the minimum of the residual over a logarithmic grid
(0.2 … 5 × the nameplate's), refined by a bounded scalar search.

What the test determines and what it cannot: R_s, σ, L_μ, α, the offset (both axes: the
part across the test axis drives no flux, only R_s·o), D. At standstill only L_μ = M²/L_r is
seen, not M and L_r apart (model (1) is the same for every scaling of the rotor flux): the
motor file keeps the nameplate's L_r/L_s and gives L_s = σ + L_μ, L_r, M = √(L_μ·L_r) and
R_r = α·L_r, which make the same model. J needs a rotating test (not done here).

Uncertainty: the least-squares standard deviations (the residual's variance times
(XᵀX)⁻¹; for α from the residual's curvature), each with a verdict: ``good`` below 1 %
(offsets: below 1 mA), ``fair`` below 5 % (5 mA), else ``poor``. A fit that is not a motor
(σ, L_μ, α or R_s not positive) is refused with the reason.

Pure module: no I/O, no clock, no global state.
"""

from __future__ import annotations

import cmath
import itertools
import math
from collections.abc import Mapping
from dataclasses import asdict, dataclass
from typing import Any

import numpy as np

from dbc.modes import DriveMode
from gateway.control.interface import Command, ControllerContext, Sample, checked_params
from gateway.control.laws import Refs
from gateway.control.recursion import first_order

SQRT3 = math.sqrt(3.0)
#: the controller's parameters (``--controller-params``) and their defaults
DEFAULTS: dict[str, Any] = {"current": 1.5, "hold": 0.5}
#: the levels of the test, in units of ``current``, each held ``hold`` seconds, then 0
LEVELS = (1.0, 2.0, -1.0, -2.0)
#: the α grid: this range times the nameplate's α, log-spaced
ALPHA_RANGE = (0.2, 5.0)
ALPHA_GRID = 60


def duration(params: Mapping[str, Any] | None = None) -> float:
    """How long the test runs, s (its levels and the final zero, one hold each)."""
    p = checked_params("identify", params or {}, DEFAULTS)
    return (len(LEVELS) + 1) * float(p["hold"])


def dead_time_direction(i: np.ndarray) -> np.ndarray:
    """g(i): the amplitude-invariant Clarke transform of the signs of the phase currents of
    each current ``i`` (complex (a, b), A): the direction of a dead-time voltage error."""
    i = np.asarray(i, dtype=complex)
    i_a = i.real
    i_b = -0.5 * i.real + 0.5 * SQRT3 * i.imag
    s_a, s_b, s_c = np.sign(i_a), np.sign(i_b), np.sign(-i_a - i_b)
    a = cmath.exp(2j * math.pi / 3)
    return (2.0 / 3.0) * (s_a + s_b * a + s_c * a.conjugate())


@dataclass(frozen=True)
class Estimate:
    """One identified value, its standard deviation and verdict."""

    value: float
    std: float
    unit: str
    verdict: str


@dataclass(frozen=True)
class StandstillFit:
    """What the standstill test found (see the module docstring); ``values``: name →
    :class:`Estimate` (R_s, sigma, L_mu, alpha, u_dead, offset_a, offset_b), ``rms``: the
    residual of (I1) in V, ``samples``: the samples used."""

    values: dict[str, Estimate]
    rms: float
    samples: int

    def motor(self, nameplate: Any) -> dict[str, float]:
        """Model (1)'s parameters that make the same standstill model, with the nameplate's
        L_r/L_s and J (module docstring)."""
        v = {k: e.value for k, e in self.values.items()}
        L_s = v["sigma"] + v["L_mu"]
        L_r = L_s * nameplate.L_r / nameplate.L_s
        return {"J": float(nameplate.J), "R_s": v["R_s"], "R_r": v["alpha"] * L_r,
                "L_s": L_s, "L_r": L_r, "M": math.sqrt(v["L_mu"] * L_r)}


def verdict(rel: float, good: float = 0.01, fair: float = 0.05) -> str:
    return "good" if rel < good else ("fair" if rel < fair else "poor")


#: samples after a step whose measured current is kept as it is (the current loop settling)
SETTLE_SAMPLES = 2


def _denoised(i: np.ndarray) -> np.ndarray:
    """The measured currents with the sensor noise of each level averaged out: between two
    steps (a change of more than a quarter of the median level), the samples after the
    first :data:`SETTLE_SAMPLES` take their mean. Noise in the regressors of (I1) biases
    least squares (errors in variables); the levels are constant by design."""
    out = i.copy()
    jump = 0.25 * float(np.median(np.abs(i)))
    edges = [0, *(np.flatnonzero(np.abs(np.diff(i)) > jump) + 1), len(i)]
    for a, b in itertools.pairwise(edges):
        if b - a > SETTLE_SAMPLES + 1:
            out[a + SETTLE_SAMPLES:b] = i[a + SETTLE_SAMPLES:b].mean()
    return out


def _flux(i: np.ndarray, T: float, alpha: float) -> np.ndarray:
    """c_k of (I1): the rotor flux of the currents ``i`` held over each period, from 0."""
    q = math.exp(-alpha * T)
    return first_order(np.asarray(i, dtype=complex), q, 1.0 - q)


def _gain_direction(i: np.ndarray) -> np.ndarray:
    """e(i): the change of the (a, b) current when the phase-b reading is scaled by
    1 + g, per unit g'  (−j·(2/√3)·i_b, i_b the measured phase-b current)."""
    i_b = -0.5 * i.real + 0.5 * SQRT3 * i.imag
    return -1j * (2.0 / SQRT3) * i_b


#: The columns of the first stage (rows without a step), in order: R_s, L_μ, D, −R_s·o
#: (real, imaginary), the start term (real, imaginary), R_s's drift, the phase-b gain.
_R_S, _L_MU, _D, _O_RE, _O_IM, _E_RE, _E_IM, _DRIFT, _GAIN = range(9)


def _design(i: np.ndarray, T: float, alpha: float, gain: complex | None = None
            ) -> np.ndarray:
    """The columns of (I1) for the samples 1..n−1 (complex) but σ's (which acts on steps
    only): R_s, L_μ, D, the offset term −R_s·o (real and imaginary), the start term (both),
    R_s's drift (R_s·d·t·i), and with ``gain`` (the offset-free sensitivity of the model
    to the phase-b gain, :func:`_gain_column`) the gain's."""
    n = len(i)
    q = math.exp(-alpha * T)
    e = q ** np.arange(n)
    t = T * np.arange(1, n)
    cols = [T * i[1:], np.diff(_flux(i, T, alpha)), T * dead_time_direction(i)[1:],
            np.full(n - 1, T, dtype=complex), np.full(n - 1, 1j * T),
            np.diff(e).astype(complex), 1j * np.diff(e), T * t * i[1:]]
    if gain is not None:
        cols.append(gain)
    return np.column_stack(cols)


def _gain_column(i: np.ndarray, T: float, alpha: float, R_s: float, L_mu: float
                 ) -> np.ndarray:
    """The model's change per unit g' (the phase-b gain, first order): the current e(i)
    through R_s and the rotor flux (σ's part acts on steps only)."""
    e = _gain_direction(i)
    return R_s * T * e[1:] + L_mu * np.diff(_flux(e, T, alpha))


def _stacked(X: np.ndarray, y: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    return np.vstack([X.real, X.imag]), np.concatenate([y.real, y.imag])


def _rows(i: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(the rows of the first stage, the rows of σ): periods without a step (a change of
    more than a quarter of the median level) and those with one, neither with a phase
    current that changed sign (the dead-time error then changes within the period, where
    (I1) holds it constant; and a current loop that slews through zero is no step)."""
    g = dead_time_direction(i)
    same_signs = g[1:] == g[:-1]
    step = np.abs(np.diff(i)) > 0.25 * float(np.median(np.abs(i)))
    return same_signs & ~step, same_signs & step


def _solve(i: np.ndarray, u: np.ndarray, T: float, alpha: float, rows: np.ndarray,
           gain: complex | None = None) -> tuple[np.ndarray, float, np.ndarray]:
    """(coefficients, residual sum of squares, the stacked design) at ``alpha``."""
    A, b = _stacked(_design(i, T, alpha, gain)[rows], T * u[1:][rows])
    coef, *_ = np.linalg.lstsq(A, b, rcond=None)
    r = b - A @ coef
    return coef, float(r @ r), A


def fit_standstill(i_s_ab: np.ndarray, u_s_ab: np.ndarray, period: float,
                   alpha_nameplate: float) -> StandstillFit:
    """The standstill test's parameters from its samples (complex (a, b) currents, A, and
    period-average voltages, V) at ``period`` s; ValueError with the reason when they do not
    make a motor.

    Two stages. The periods without a step hold the current constant (a current loop that
    slews a step over part of a period breaks (I1)'s held current there only): they give
    α (the residual's minimum over the grid), R_s, L_μ, D, the offsets, R_s's drift and,
    solved again twice with its column, the phase-b gain. Then σ from the periods with a
    step, the rest fixed: exact for a current that steps at the period's start (``ideal``);
    a current loop's slew (voltage-limited) lowers it by about R_s·t_slew/2."""
    from scipy.optimize import minimize_scalar

    i = np.asarray(i_s_ab, dtype=complex)
    u = np.asarray(u_s_ab, dtype=complex)
    keep = np.isfinite(i) & np.isfinite(u)
    i, u = i[keep], u[keep]
    if len(u) and not np.any(np.abs(u) > 0.0):
        raise ValueError("the drive reported no applied voltage (all zero): the test needs "
                         "the period's average voltages (the drive profile's [pdo] voltages, "
                         "with u_sa and u_sb)")
    if len(i) < 50:
        raise ValueError(f"the test gave {len(i)} samples; it needs at least 50 (a longer "
                         "hold, or a shorter period)")
    i = _denoised(i)
    T = period
    flat, steps = _rows(i)
    if not steps.any():
        raise ValueError("the current never stepped: the drive did not follow the test's "
                         "setpoints (is its power stage enabled, in a current mode?)")
    lo, hi = (alpha_nameplate * f for f in ALPHA_RANGE)
    grid = np.geomspace(lo, hi, ALPHA_GRID)
    rss = [_solve(i, u, T, a, flat)[1] for a in grid]
    k = int(np.argmin(rss))
    if k in (0, len(grid) - 1):
        raise ValueError(f"the rotor's α lies at the edge of the search ({grid[k]:.4g} 1/s, "
                         f"{ALPHA_RANGE[0]:g}…{ALPHA_RANGE[1]:g} × the nameplate's "
                         f"{alpha_nameplate:.4g}): the motor file's rotor parameters are far "
                         "from this motor's, or the current did not follow its steps")
    best = minimize_scalar(lambda a: _solve(i, u, T, a, flat)[1],
                           bounds=(grid[k - 1], grid[k + 1]), method="bounded",
                           options={"xatol": 1e-6 * grid[k]})
    alpha = float(best.x)
    coef, _, _ = _solve(i, u, T, alpha, flat)
    for _ in range(2):  # the phase-b gain's column with the parameters found so far
        gain = _gain_column(i, T, alpha, float(coef[_R_S]), float(coef[_L_MU]))
        coef, rss_min, A = _solve(i, u, T, alpha, flat, gain)
    dof = max(1, A.shape[0] - A.shape[1] - 1)
    s2 = rss_min / dof
    std = np.sqrt(np.maximum(np.diag(s2 * np.linalg.pinv(A.T @ A)), 0.0))
    h = 1e-3 * alpha  # the residual's curvature in α: its standard deviation
    curv = (_solve(i, u, T, alpha + h, flat, gain)[1] - 2.0 * rss_min
            + _solve(i, u, T, alpha - h, flat, gain)[1]) / (h * h)
    alpha_std = math.sqrt(2.0 * s2 / curv) if curv > 0 else math.inf
    # σ: the step periods' residual of everything else, on Δi
    X = _design(i, T, alpha, gain)[steps]
    r = T * u[1:][steps] - X @ coef
    di = np.diff(i)[steps]
    den = float(np.sum(np.abs(di) ** 2))
    sigma = float(np.sum((np.conj(di) * r).real)) / den
    r_sigma = r - sigma * di
    sigma_std = math.sqrt(float(np.sum(np.abs(r_sigma) ** 2)) / max(1, 2 * len(di) - 1)
                          / den)
    R_s, L_mu, D = (float(coef[c]) for c in (_R_S, _L_MU, _D))
    for name, x in (("R_s", R_s), ("σ = L_s − M²/L_r", sigma), ("L_μ = M²/L_r", L_mu)):
        if not x > 0:
            raise ValueError(f"the fit gives {name} = {x:.4g}, not a motor: the current did "
                             "not follow its steps, or the drive's voltages are not what it "
                             "applied (check that the drive reports the average applied "
                             "voltage over each period)")
    o_ab = -complex(coef[_O_RE], coef[_O_IM]) / R_s
    o_std = math.hypot(std[_O_RE], std[_O_IM]) / R_s
    o_a = o_ab.real  # the phase offsets from their (a, b) image (a, (a + 2b)/√3)
    o_b = 0.5 * (SQRT3 * o_ab.imag - o_ab.real)
    g1 = float(coef[_GAIN])
    drift_std = float(std[_DRIFT]) / R_s
    values = {
        "R_s": Estimate(R_s, float(std[_R_S]), "Ω", verdict(std[_R_S] / R_s)),
        "sigma": Estimate(sigma, sigma_std, "H", verdict(sigma_std / sigma)),
        "L_mu": Estimate(L_mu, float(std[_L_MU]), "H", verdict(std[_L_MU] / L_mu)),
        "alpha": Estimate(alpha, alpha_std, "1/s", verdict(alpha_std / alpha)),
        "u_dead": Estimate(D, float(std[_D]), "V", verdict(std[_D], 0.05, 0.2)),
        "offset_a": Estimate(o_a, o_std, "A", verdict(o_std, 1e-3, 5e-3)),
        "offset_b": Estimate(o_b, o_std, "A", verdict(o_std, 1e-3, 5e-3)),
        "gain_b": Estimate(1.0 / (1.0 - g1), float(std[_GAIN]), "",
                           verdict(float(std[_GAIN]), 0.002, 0.01)),
        "R_s_drift": Estimate(float(coef[_DRIFT]) / R_s, drift_std, "1/s",
                              verdict(drift_std, 0.002, 0.01)),
    }
    rms = math.sqrt(rss_min / A.shape[0]) / T
    return StandstillFit(values, rms, len(i))


class StandstillTest:
    """The standstill test as a controller (``--controller identify``; a
    :class:`gateway.control.interface.DriveController`): it sends the steps and keeps the
    samples; :meth:`summary` fits them at the end of the run."""

    #: i_ref: the current sent on the a axis, A
    signals = ("i_ref",)
    #: the drive modes it drives: a current source (ideal, or the drive's current loop)
    drive_modes = (DriveMode.IDEAL, DriveMode.CURRENT_LOOP)

    def __init__(self, context: ControllerContext, params: Mapping[str, Any]) -> None:
        if context.drive_mode not in self.drive_modes:
            raise ValueError(f"identify steps the stator current: it needs a drive that takes "
                             f"current setpoints (--drive-mode ideal or current-loop), not "
                             f"'{context.drive_mode}'")
        p = checked_params("identify", params, DEFAULTS)
        self.current = float(p["current"])
        self.hold = float(p["hold"])
        if not self.current > 0 or not self.hold > 0:
            raise ValueError(f"identify: current ({self.current} A) and hold ({self.hold} s) "
                             "must be positive")
        self.motor = context.motor
        self.T = context.sampling.period
        self._k = 0
        self._i: list[complex] = []
        self._u: list[complex] = []
        self._i_ref = 0.0

    def _level(self, t: float) -> float:
        n = int(t / self.hold + 1e-9)
        return self.current * LEVELS[n] if n < len(LEVELS) else 0.0

    def step(self, refs: Refs, sample: Sample) -> Command:
        t = self._k * self.T
        self._k += 1
        if t < len(LEVELS) * self.hold:  # the final zero is not part of the test
            self._i.append(sample.i_s_ab)
            self._u.append(sample.u_s_ab)
        # the setpoint acts from the next period on (delay 1) or this one (delay 0): the
        # fit takes what the drive measured, whenever it came
        self._i_ref = self._level(t)
        i = complex(self._i_ref, 0.0)
        return Command(i_s_dq_ref=i, i_s_ab_ref=i, logged=(self._i_ref,))

    def withhold(self) -> None:
        """The drive keeps the last setpoint; the samples tell what it did."""

    def coast(self) -> None:
        """A cycle without measurements: a gap in the samples (left out of the fit)."""
        self._k += 1
        if self._k * self.T < len(LEVELS) * self.hold:
            self._i.append(complex(math.nan, math.nan))
            self._u.append(complex(math.nan, math.nan))

    def summary(self) -> dict[str, Any]:
        """The fit (summary.json's ``identification``), or why there is none."""
        try:
            fit = fit_standstill(np.array(self._i), np.array(self._u), self.T,
                                 self.motor.alpha)
        except ValueError as exc:
            return {"test": "standstill", "ok": False, "reason": str(exc)}
        return {"test": "standstill", "ok": True, "samples": fit.samples,
                "residual_rms_V": fit.rms, "current_A": self.current, "hold_s": self.hold,
                "values": {k: asdict(e) for k, e in fit.values.items()},
                "motor": fit.motor(self.motor),
                "not_measured": {"J": "needs a rotating test; the nameplate's is kept",
                                 "L_r/L_s": "not seen at standstill; the nameplate's ratio "
                                            "is kept"}}

