"""Standstill identification of R_s and the rotor time constant during the magnetisation
(docs/robustness.md §5).

At standstill the rotor flux obeys rows 2–3 of model (1) with ω = 0,

    dψ_r/dt = −α·ψ_r + α·M·i_s,                                  (1), α = R_r/L_r

while the voltage model of (24) gives the same flux from the terminals (§E1),

    ψ_r = (L_r/M)·(∫(u_s − R_s·i_s)dt − σ·i_s).                    (24)

Both are exact; their difference depends on the two parameters a motor changes most with
temperature and that the controller cannot see in steady state: R_s (the voltage model) and
α (the current model). In steady state at standstill (a DC flux) only R_s shows; in steady
state at speed only the products that (11) and (15) use, so an R_r error is invisible from
the terminals (docs/robustness.md §4). The magnetisation before the profile's speed starts
is a transient at standstill: the flux rises from zero with the dynamics of α, so the two
models agree for one pair (R_s, α) only.

Per sample t_k (period T) with the measured current i_k and the period's average voltage
ū_k (a current held over the period, the drive's timing contract), in the (a, b) frame:

    a_k = (L_r/M)·(T·Σ_{j≤k} ū_j − σ·i_k),   b_k = (L_r/M)·T·Σ_{j≤k} i_j,
    c_k(α) = e^{−αT}·c_{k−1}(α) + (1 − e^{−αT})·M·i_k,   c_0 = 0 (the motor starts unmagnetised),

and the voltage model is a_k − R_s·b_k. Where the drive does not hold the current over the
period (a voltage drive, a current loop's rise), T·i_j in b_k is the period's charge ∫i dt
from the controller's model of the current, and the rotor model takes charge/T as held. For
each α of a grid the least-squares R_s is R(α) = Σ Re(b̄·(a − c))/Σ|b|², with the residual
J(α) = Σ|a − c|² − (Σ Re(b̄·(a − c)))²/Σ|b|²; the identified pair is the grid's minimum of
J, refined by a parabola through its neighbours. The sums are accumulated sample by sample
(O(grid) per sample, no record kept), so the solution at the end of the magnetisation costs
one pass over the grid.

Missed cycles (a lost TPDO, a SYNC the drive did not receive): the voltage model's flux
moves by an unknown constant δ_j at each gap j, so the residual is a − c − R_s·b − δ_j over
the samples between gaps; each δ_j is eliminated by its segment's mean (its sums taken off
Σ|a − c|², Σ Re(b̄·(a − c)) and Σ|b|²), and the fit uses what varies within segments.

Limits: needs a magnetisation from (near) zero flux at standstill (the paper's profile has
0.32 s of it); the result is refused when the flux did not rise (too little excitation),
when the minimum lies on the edge of the α grid (0.5…2 × the controller's α) or when the
R_s found is outside 0.5…2 × the controller's. The sensor offset and the inverter's dead time
enter R_s as what they are at standstill: an effective resistance.

Pure module: no I/O, no clock, no global state.
"""

from __future__ import annotations

import cmath
import math
from dataclasses import asdict, dataclass, replace
from typing import Any, Protocol

import numpy as np

from gateway.control.correction import SQRT3, SensorCorrection, phases
from gateway.control.recursion import first_order


class Refs(Protocol):
    w_ref: float
    dw_ref: float
    T_L: float


class Motor(Protocol):
    R_s: float
    R_r: float
    L_r: float
    M: float
    sigma: float


@dataclass(frozen=True)
class Identification:
    """The result of a standstill identification.

    R_s: stator resistance, Ω; R_r: rotor resistance, Ω (α·L_r); alpha: α = R_r/L_r, 1/s;
    fit: the residual relative to the voltage-model flux's energy (0 = exact); samples:
    how many samples it used; accepted: whether the controller applies it; reason: why
    not, when it does not; M, L_s, L_r: the inductances, H (the controller's, or the
    sensors' fit's, which fits M with the leakages held).
    """

    R_s: float
    R_r: float
    alpha: float
    fit: float
    samples: int
    accepted: bool
    reason: str = ""
    M: float = math.nan
    L_s: float = math.nan
    L_r: float = math.nan
    #: the phase current sensors' errors fitted with R_s and α as in a motor file's
    #: [commissioning] (offsets of phases a and b, A; phase b's gain relative to a's),
    #: their least-squares standard deviations, whether the run corrects them (then R_s,
    #: R_r and α above are the joint fit's), and why not when not
    offset_a: float = 0.0
    offset_b: float = 0.0
    gain_b: float = 1.0
    offset_a_std: float = 0.0
    offset_b_std: float = 0.0
    gain_b_std: float = 0.0
    sensors_corrected: bool = False
    sensors_reason: str = ""
    #: the measured current's mismatch with the controller's model of it over the
    #: standstill, rms (A; NaN where the controller has no such model), and what follows
    #: from it: the weight κ of the mismatch in the voltage model from now on and of the
    #: voltage model in the flux handed over (1, or below where it is the sensors' noise:
    #: :attr:`Commissioning.NOISE_RMS`)
    mismatch_rms: float = math.nan
    mismatch_gain: float = 1.0
    #: R_s and α fitted with the controller's model of the current in the regressors (the
    #: mismatch being the sensors' noise: :meth:`StandstillIdentifier.solve`'s ``noisy``)
    model_current: bool = False
    #: the inverter's voltage error (dead time, V: the motor file's ``u_dead``) fitted with
    #: R_s and α where the drive's reported voltages are not the applied ones
    #: (:meth:`StandstillIdentifier.solve_dead_time`); the run corrects it from the end of
    #: the standstill (0: none fitted)
    u_dead: float = 0.0


@dataclass(frozen=True)
class OffsetFit:
    """:meth:`StandstillIdentifier.solve_offsets`: R_s (Ω) and α (1/s) fitted with the
    current sensors' offsets, whose (a, b) image is ``offset_ab`` (A) with the standard
    deviations ``std_ab`` (of the real and imaginary parts, as real + j·imaginary, A),
    and phase b's reading gain ``gain_b`` (± ``gain_b_std``); ``psi_ab``: the rotor flux at
    the last sample (the rotor model's with the true current, Wb); ``fit``: the relative
    residual; ``edge``: α's minimum on the edge of the search."""

    R_s: float
    alpha: float
    M: float
    offset_ab: complex
    std_ab: complex
    gain_b: float
    gain_b_std: float
    psi_ab: complex
    fit: float
    edge: bool


def _vertex(logf: np.ndarray, y: np.ndarray, k: int) -> float:
    """The fits' α in log α: the vertex of the parabola through the residuals ``y`` at
    grid points k − 1, k, k + 1 (``logf`` evenly spaced), logf[k] where it opens down."""
    y0, y1, y2 = y
    den = y0 - 2.0 * y1 + y2
    if den > 0.0:
        return logf[k] + 0.5 * (logf[1] - logf[0]) * (y0 - y2) / den
    return logf[k]


class StandstillIdentifier:
    """R_s and α from the standstill magnetisation (see the module docstring).

    ``StandstillIdentifier(motor, period)``; :meth:`add` each sample while the rotor is at
    rest; :meth:`solve` at the end of the magnetisation.
    """

    #: the α grid, as factors of the controller's α
    SPAN = (0.5, 2.0)
    POINTS = 151
    #: least flux rise (Wb, |voltage-model ψ_r| at the end) for a usable identification
    PSI_MIN = 0.2
    #: largest relative residual of an accepted identification (measured: ≤ 3.2e-6 on every
    #: shipped plant but the PI-current-loop drive with 2 µs dead time, 9e-4, whose reported
    #: voltages are not the applied ones at standstill)
    FIT_MAX = 1e-4
    #: the most samples kept for the offsets' fit (a longer standstill: no offsets)
    RECORD_MAX = 60_000
    #: the α range of the offsets' fit, as factors of the first fit's α̂ (an offset moves
    #: α̂ by about 0.15 % per mA)
    OFFSET_SPAN = (0.8, 1.25)
    #: the offsets' fit: Gauss–Newton steps at most (bilinear in R_s and o, smooth in M and
    #: log α: it converges in 4–6), and the largest step in log α
    GN_STEPS = 20
    GN_LOG_ALPHA_STEP = 0.05

    def __init__(self, motor: Motor, period: float) -> None:
        if not period > 0.0:
            raise ValueError(f"standstill identification: period {period!r} s must be > 0")
        self.motor = motor
        self._T = period
        self._alpha0 = motor.R_r / motor.L_r
        self._f = np.geomspace(self.SPAN[0], self.SPAN[1], self.POINTS)
        self._e = np.exp(-self._f * self._alpha0 * period)
        self._k_r = motor.L_r / motor.M
        self._c = np.zeros(self.POINTS, dtype=complex)
        self._sum_u = 0j
        self._sum_i = 0j
        self._n = 0
        self._s_bb = 0.0
        self._s_ab = 0.0
        self._s_aa = 0.0
        self._s_bc = np.zeros(self.POINTS)
        self._s_ac = np.zeros(self.POINTS)
        self._s_cc = np.zeros(self.POINTS)
        self._a = 0j
        self._b = 0j
        self._gaps = 0
        self._i_last = 0j
        self.gaps = 0  #: periods without a sample since the start
        # the sums over the samples since the last gap (the voltage model's offset since
        # that gap is one more unknown), and what the closed segments take off the fit's
        self._n_h = 0
        self._a_h = 0j
        self._b_h = 0j
        self._c_h = np.zeros(self.POINTS, dtype=complex)
        self._off_dd = np.zeros(self.POINTS)
        self._off_cross = np.zeros(self.POINTS)
        self._off_bb = 0.0
        # the samples, for the offsets' fit (:meth:`solve_offsets`): i_k, a_k, b_k
        # (and the period's mean current where it is not held: the rotor model's input)
        self._rec: list[tuple[complex, complex, complex, complex]] = []
        # the controller's model of the current at each sample, where it came with every
        # one (:meth:`solve`'s ``noisy`` fit)
        self._rec_model: list[complex] = []

    def gap(self) -> None:
        """A period without a sample (a missed cycle): the motor lived it, its voltage and
        current were not reported. The next :meth:`add` stands in for it too, so that the
        sums cover the whole time (left out, a period's R_s·i·T, about 0.02 Wb, would be
        missing from the voltage model's flux for good)."""
        self._gaps += 1
        self.gaps += 1

    def add(self, i_s_ab: complex, u_s_ab: complex, charge: complex | None = None,
            i_model: complex | None = None) -> None:
        """One sample: the measured current at t_k (A) and the average voltage the drive
        applied over the period before it (V), (a, b) frame; ``charge``: ∫i dt over that
        period (A·s) where the drive does not hold its current over the period (a voltage
        drive, a current loop's rise: the controller's model of it), else None (T·i_k);
        ``i_model``: the controller's model of the current the drive holds, A (for
        :meth:`solve`'s ``noisy`` fit).

        After a :meth:`gap`, each missing period takes this period's voltage and the
        current halfway from the last sample's to this one's, in the integrals and the
        current model only (not in the fit's sums: they are no samples). Whether the drive
        changed its current at the missing sample (a lost TPDO) or held it (a SYNC it did
        not receive) cannot be told: the voltage model's flux moves by an unknown constant
        at each gap (the missing period's σ·Δi and R_s·i·T), which the fit takes as one
        more unknown per gap (:meth:`solve`; one for all gaps found α 17 % low with a
        third of the cycles missed on a loaded host); the current model's flux is barely
        touched (its error decays with the rotor time constant), so after a gap the
        identification hands over that one (:meth:`current_model_flux_at`)."""
        gaps, self._gaps = self._gaps, 0
        if gaps:
            self._close_segment()
            i_mid = 0.5 * (self._i_last + i_s_ab)
            for _ in range(gaps):
                self._integrate(i_mid, u_s_ab, i_mid)
        self._add(i_s_ab, u_s_ab, i_s_ab if charge is None else charge / self._T)
        if i_model is not None and len(self._rec_model) < self.RECORD_MAX:
            self._rec_model.append(i_model)

    def _segment(self) -> tuple[np.ndarray, np.ndarray, float]:
        """What the segment since the last gap takes off the fit's sums (Σ|a − c|²,
        Σ Re(b̄·(a − c)), Σ|b|²): its own offset of the voltage model, the least-squares
        constant over its samples."""
        n = self._n_h
        if not n:
            return np.zeros(self.POINTS), np.zeros(self.POINTS), 0.0
        d_h, b_h = self._a_h - self._c_h, self._b_h
        return ((d_h.real ** 2 + d_h.imag ** 2) / n,
                (d_h.real * b_h.real + d_h.imag * b_h.imag) / n,
                (b_h.real ** 2 + b_h.imag ** 2) / n)

    def _close_segment(self) -> None:
        """A gap ends the segment since the last one (:meth:`_segment`)."""
        dd, cross, bb = self._segment()
        self._off_dd += dd
        self._off_cross += cross
        self._off_bb += bb
        self._n_h = 0
        self._a_h = 0j
        self._b_h = 0j
        self._c_h = np.zeros(self.POINTS, dtype=complex)

    def _integrate(self, i_s_ab: complex, u_s_ab: complex, i_mean: complex
                   ) -> tuple[complex, complex]:
        """One period into the integrals and the current model: (a_k, b_k). ``i_mean``: the
        period's mean current, charge/T (``i_s_ab`` where the drive holds it), which the
        rotor model takes as held (for a current linear over the period its error is
        M·Δi·(αT)²/12)."""
        m, T = self.motor, self._T
        self._n += 1
        self._sum_u += u_s_ab
        self._sum_i += i_mean
        c = self._c
        c *= self._e
        c += (1.0 - self._e) * (m.M * i_mean)
        return (self._k_r * (T * self._sum_u - m.sigma * i_s_ab),
                self._k_r * T * self._sum_i)

    def _add(self, i_s_ab: complex, u_s_ab: complex, i_mean: complex) -> None:
        a, b = self._integrate(i_s_ab, u_s_ab, i_mean)
        c = self._c
        self._s_bb += b.real * b.real + b.imag * b.imag
        self._s_ab += (b.conjugate() * a).real
        self._s_aa += a.real * a.real + a.imag * a.imag
        self._s_bc += b.real * c.real + b.imag * c.imag
        self._s_ac += a.real * c.real + a.imag * c.imag
        self._s_cc += c.real * c.real + c.imag * c.imag
        self._a, self._b = a, b
        self._i_last = i_s_ab
        if len(self._rec) < self.RECORD_MAX:
            self._rec.append((i_s_ab, a, b, i_mean))
        if self.gaps:  # the sums over the samples of this segment's offset
            self._n_h += 1
            self._a_h += a
            self._b_h += b
            self._c_h += c

    @property
    def samples(self) -> int:
        return self._n

    def flux(self, R_s: float) -> complex:
        """The voltage-model rotor flux at the last sample with ``R_s``, Wb (a, b)."""
        return self._a - R_s * self._b

    def current_model_flux_at(self, alpha: float) -> complex:
        """The current-model rotor flux at the last sample for the rotor pole ``alpha``
        (1/s), interpolated on the search grid in log α, Wb (a, b): R_s does not enter it."""
        x = math.log(alpha / self._alpha0)
        logf = np.log(self._f)
        c = self._c
        return complex(float(np.interp(x, logf, c.real)), float(np.interp(x, logf, c.imag)))

    def current_model_flux(self) -> complex:
        """The current-model rotor flux at the last sample with the controller's α (row 2–3
        of (1) at ω = 0, from zero flux), Wb (a, b): R_s does not enter it."""
        return complex(self._c[self.POINTS // 2])

    #: the noisy fit searches α within this many points of the grid either side of the
    #: least-squares minimum (about ±14 %)
    NOISY_REACH = 15

    def _noisy(self, k: int) -> tuple[float, float, float] | None:
        """(log(α/α₀), R_s, Σ|r|²) with the controller's model of the current in the fit's
        regressors — the charge b_k and the rotor model c_k(α) — and the measured voltage
        model a_k, on the grid within :attr:`NOISY_REACH` of ``k``, refined by a parabola;
        None where the model did not come with every sample, or samples were missing.

        With the sensors' noise n the measured regressors are b + (L_r/M)·T·Σn, a random
        walk, and c(α) + the noise through the rotor's filter: errors in variables, whose
        one realisation over a magnetisation biases α̂ by up to 0.3 % (5 mA per axis) — the
        random walk does not average out against the regressors' own slow trends, so an
        instrumental-variable fit with the model as instrument keeps the bias. The model's
        current is the current the drive holds (less its resolution), noise-free."""
        n = len(self._rec)
        if self.gaps or n < 10 or len(self._rec_model) != n or n >= self.RECORD_MAX:
            return None
        m, T = self.motor, self._T
        a = np.array([r[1] for r in self._rec])
        z = np.array(self._rec_model)
        b = self._k_r * T * np.cumsum(z)
        bb = float(np.sum(b.real ** 2 + b.imag ** 2))
        if not bb > 0.0:
            return None
        lo, hi = max(k - self.NOISY_REACH, 0), min(k + self.NOISY_REACH, self.POINTS - 1)
        J = np.empty(hi - lo + 1)
        R = np.empty(hi - lo + 1)
        for j in range(lo, hi + 1):
            e = float(self._e[j])
            d = a - first_order(m.M * z, e, 1.0 - e)
            R[j - lo] = float(np.sum(b.real * d.real + b.imag * d.imag)) / bb
            J[j - lo] = float(np.sum(d.real ** 2 + d.imag ** 2)) - R[j - lo] ** 2 * bb
        q = int(np.argmin(J))
        if q in (0, hi - lo):
            return None  # no minimum within reach
        logf = np.log(self._f)
        x = _vertex(logf, J[q - 1:q + 2], lo + q)
        R_s = float(np.interp(x, logf[lo:hi + 1], R))
        return x, R_s, float(J[q])

    def solve(self, noisy: bool = False) -> Identification:
        """The identified R_s and α (see the module docstring), accepted or not; ``noisy``:
        the current's mismatch with the controller's model is the sensors' noise, and the
        fit's regressors take the model's current (:meth:`_noisy`) where it came with
        every sample."""
        m = self.motor
        if self._n < 10 or self._s_bb <= 0.0:
            return Identification(m.R_s, m.R_r, self._alpha0, math.nan, self._n, False,
                                  "too few samples at standstill", m.M, m.L_s, m.L_r)
        cross = self._s_ab - self._s_bc  # Σ Re(b̄·(a − c)) per α
        dd = self._s_aa - 2.0 * self._s_ac + self._s_cc  # Σ|a − c|²
        bb = self._s_bb
        if self.gaps:  # and a constant δ_j added to a − c − R_s·b from each gap j on
            s_dd, s_cross, s_bb = self._segment()
            dd = dd - self._off_dd - s_dd
            cross = cross - self._off_cross - s_cross
            bb = bb - self._off_bb - s_bb
        J = dd - cross * cross / bb
        k = int(np.argmin(J))
        logf = np.log(self._f)
        x = _vertex(logf, J[k - 1:k + 2], k) if 0 < k < self.POINTS - 1 else logf[k]
        R_s = float(np.interp(x, logf, cross)) / bb
        J_min = float(J[k])
        found = self._noisy(k) if noisy else None
        if found is not None:
            x, R_s, J_min = found
        f = math.exp(x)
        alpha = f * self._alpha0
        fit = float(max(J_min, 0.0) / self._s_aa) if self._s_aa > 0.0 else math.nan
        reason = ""
        psi_end = abs(self.flux(R_s))
        if psi_end < self.PSI_MIN:
            reason = (f"the flux rose to {psi_end:.3g} Wb only (at least "
                      f"{self.PSI_MIN:g} Wb needed)")
        elif not fit <= self.FIT_MAX:
            reason = (f"the two flux models do not agree (relative residual {fit:.2g} > "
                      f"{self.FIT_MAX:g}): the voltages the drive reports are not the ones it "
                      "applies at standstill (a dead time? `hil-gateway identify` measures it "
                      "for the motor file: README \"Commissioning the motor\"), or the rotor "
                      "moved")
        elif k in (0, self.POINTS - 1):
            reason = (f"α at the edge of the search ({f:.3g} × the controller's): the motor "
                      "is not the one the controller was given")
        elif not 0.5 * m.R_s <= R_s <= 2.0 * m.R_s:
            reason = f"R_s = {R_s:.3g} Ω is not within 0.5…2 × the controller's {m.R_s:g} Ω"
        return Identification(R_s, alpha * m.L_r, alpha, fit, self._n, not reason, reason,
                              m.M, m.L_s, m.L_r, model_current=found is not None)

    #: the dead-time fit (:meth:`solve_dead_time`) starts where the current has reached this
    #: share of its largest magnitude (below it, a current of a few mA chatters about zero
    #: in the dead time's own dead zone, which no sign of the period's current describes)
    DEAD_START = 0.25
    #: and wants the current's direction steady within this from there (rad)
    DEAD_TURN = math.radians(5.0)
    #: a phase current below this share of the current's magnitude is at a sector boundary
    #: (its mean sign over the record is then a further unknown)
    DEAD_BOUNDARY = 0.1
    #: the least samples of the fit
    DEAD_SAMPLES = 40

    def solve_dead_time(self) -> tuple[Identification, complex] | None:
        """R_s, α and the inverter's voltage error u_dead together, for a drive that reports
        the voltage it was told rather than the one it applied (dead time): (the
        identification, the current model's rotor flux at the last sample with its α, Wb
        (a, b)); None where it cannot be fitted (samples missing, or more than
        :attr:`RECORD_MAX`).

        The inverter applies ū_k − u_dead·g(i), g the phases' current signs (the motor
        file's (C2), :func:`gateway.control.identify.dead_time_direction`). At standstill
        the current keeps one direction once it has built (the magnetisation); over the
        samples from k0, where |i| first reaches :attr:`DEAD_START` of its largest, the
        error is then a constant vector E = u_dead·g, and

            a_k − a_k0 − c̃_k(α) = R_s·(b_k − b_k0) + E·(L_r/M)·T·(k − k0)
                                  + c_k0·(e^{−α(k − k0)T} − 1)                     (D1)

        with c̃ the rotor model from zero at k0 and c_k0 the rotor flux there: linear in
        (R_s, E, c_k0) for each α of the grid (five real unknowns), α the residual's minimum
        refined by a parabola. E along the current is told from R_s·i because the current's
        magnitude changes (the magnetisation's ψ̇* term: it peaks, then settles); across the
        current E is alone. The drive's current loop holds the frame where a phase current
        is zero (a sector boundary: with 5 mA of noise the magnetisation settled at ±30°),
        and that phase's mean sign σ_z over the record is unknown: E = u_dead·(g₀ + σ_z·h),
        two real equations for u_dead and u_dead·σ_z. Off a boundary g is known and the
        part of E across it is a check. Measured (full-order law, voltage drive, 2 µs dead
        time, 11.2 V): u_dead 11.19 V, R_s and α exact on the axis; at the −30° boundary
        with 5 mA of noise 11.51 V, R_s −1.4 %, α +2.9 %; `real-drive` 11.32 V, R_s 5.805 Ω
        for 5.83–5.86 (warming), α +0.3 % (docs/robustness.md §5)."""
        n = len(self._rec)
        if self.gaps or n < self.DEAD_SAMPLES or n >= self.RECORD_MAX:
            return None
        m, T = self.motor, self._T
        rec = np.array(self._rec)
        i, a, b, i_f = rec[:, 0], rec[:, 1], rec[:, 2], rec[:, 3]
        mag = np.abs(i)
        k0 = int(np.argmax(mag >= self.DEAD_START * mag.max()))
        if n - k0 < self.DEAD_SAMPLES:
            return None
        direction = complex(np.mean(i[k0:]))
        unit = direction / abs(direction) if direction else 1.0 + 0j
        turn = float(np.max(np.abs(np.angle(i[k0:] * unit.conjugate()))))
        ks = np.arange(k0, n)
        ramp = self._k_r * T * (ks - k0)
        y0 = a[ks] - a[k0]
        bb = b[ks] - b[k0]
        rows = 2 * len(ks)
        x = np.zeros((rows, 5))
        x[0::2, 0], x[1::2, 0] = bb.real, bb.imag
        x[0::2, 1], x[1::2, 2] = ramp, ramp

        def fit_at(e: float) -> tuple[float, np.ndarray, np.ndarray]:
            # the rotor model from zero at k0, and the decay of its flux there
            c = np.zeros(len(ks), dtype=complex)
            c_k, gain = 0j, (1.0 - e) * m.M
            for j in range(1, len(ks)):
                c_k = e * c_k + gain * i_f[k0 + j]
                c[j] = c_k
            decay = e ** (ks - k0) - 1.0
            x[0::2, 3], x[1::2, 4] = decay, decay
            r = y0 - c
            yy = np.empty(rows)
            yy[0::2], yy[1::2] = r.real, r.imag
            sol = np.linalg.lstsq(x, yy, rcond=None)[0]
            res = yy - x @ sol
            return float(res @ res), sol, c

        costs = np.array([fit_at(float(e))[0] for e in self._e])
        k = int(np.argmin(costs))
        logf = np.log(self._f)
        lx = _vertex(logf, costs[k - 1:k + 2], k) if 0 < k < self.POINTS - 1 else logf[k]
        alpha = math.exp(lx) * self._alpha0
        cost, sol, _ = fit_at(math.exp(-alpha * T))
        R_s, E = float(sol[0]), complex(sol[1], sol[2])
        energy = float(np.sum(y0.real ** 2 + y0.imag ** 2))
        fit = cost / energy if energy > 0.0 else math.nan
        # u_dead from E: the phases' signs along the current's direction
        phase = phases(unit)
        phase = (*phase, -phase[0] - phase[1])
        axes = (1.0 + 0j, cmath.exp(2j * math.pi / 3), cmath.exp(-2j * math.pi / 3))
        z = int(np.argmin(np.abs(phase)))
        if abs(phase[z]) < self.DEAD_BOUNDARY:
            g0 = sum((2.0 / 3.0) * math.copysign(1.0, phase[j]) * axes[j]
                     for j in range(3) if j != z)
            h = (2.0 / 3.0) * axes[z]
            det = g0.real * h.imag - g0.imag * h.real
            u_dead = (E.real * h.imag - E.imag * h.real) / det
            mean_sign = ((g0.real * E.imag - g0.imag * E.real) / det / u_dead
                         if u_dead else 0.0)
            across = 0.0
        else:
            g = sum((2.0 / 3.0) * math.copysign(1.0, phase[j]) * axes[j] for j in range(3))
            u_dead = (E * g.conjugate()).real / abs(g) ** 2
            across = abs((E * g.conjugate()).imag) / abs(g)
            mean_sign = 0.0
        reported = np.diff(a / self._k_r + m.sigma * i, prepend=0.0) / T
        u_max = float(np.max(np.abs(reported)))
        reason = ""
        if turn > self.DEAD_TURN:
            reason = (f"the current turned by {math.degrees(turn):.1f}° during the "
                      "magnetisation: the dead time's error is not one vector")
        elif not fit <= self.FIT_MAX:
            reason = (f"the two flux models do not agree with a dead time either (relative "
                      f"residual {fit:.2g} > {self.FIT_MAX:g})")
        elif k in (0, self.POINTS - 1):
            reason = (f"α at the edge of the dead-time fit's search "
                      f"({math.exp(lx):.3g} × the controller's)")
        elif not 0.5 * m.R_s <= R_s <= 2.0 * m.R_s:
            reason = (f"R_s = {R_s:.3g} Ω of the dead-time fit is not within 0.5…2 × the "
                      f"controller's {m.R_s:g} Ω")
        elif not 0.0 < u_dead <= 0.5 * u_max or abs(mean_sign) > 1.0 or across > 0.2 * u_dead:
            reason = (f"the voltage the drive left out ({abs(E):.3g} V) is not a dead time "
                      f"(u_dead {u_dead:.3g} V against the largest reported "
                      f"{u_max:.3g} V, a boundary phase's mean sign {mean_sign:.2f}, "
                      f"{across:.3g} V across the phases' signs)")
        ident = Identification(R_s, alpha * m.L_r, alpha, fit, self._n, not reason, reason,
                               m.M, m.L_s, m.L_r, u_dead=u_dead if not reason else 0.0)
        return ident, self.current_model_flux_at(alpha)

    def solve_offsets(self, first: Identification, fit_M: bool = True, noisy: bool = False
                      ) -> OffsetFit | None:
        """R_s, α, the current sensors' offsets and phase b's gain together, and M with the
        leakages held (``fit_M``), from the first fit ``first`` (:meth:`solve`;
        docs/robustness.md §5); None where they cannot be fitted (samples missing, or more
        than :attr:`RECORD_MAX`). The rotor model and the charge take each period's mean
        current (the sample where the drive holds it); ``noisy``: the controller's model of
        the current in place of the readings (:meth:`solve`'s ``noisy``).

        The drive regulates the current it reads, i_k, and the motor carries
        i_t = i_k − o − λ·e_b,k (o the offsets' (a, b) image, e_b phase b's reading in the
        (a, b) frame, λ = 1 − 1/g_b). With the true current in both flux models, U and Q
        the integrals of ū and i (T·Σ),

            (24):  (L_r/M)·(U_k − R_s·(Q_k − o·T·k − λ·T·Σe_b) − σ·i_t,k),
            (1):   M·(f_k(α)[i] − o·(1 − e^{−αTk}) − λ·f_k(α)[e_b]),

        f the rotor's unit filter (c_k = e^{−αT}·c_{k−1} + (1 − e^{−αT})·i_k). Their difference
        is bilinear in R_s and (o, λ) and, through L_r/M, σ and the filter's gain, smooth in
        M (L_s − M and L_r − M held: at standstill only M²/L_r shows), and in log α through
        the filter (whose derivative in α is the same recursion driven by T·e^{−αT}·(i_k −
        f_{k−1})). Gauss–Newton on (R_s, o, λ, M, log α) from (``first``'s R_s, 0, 0, the
        controller's M, ``first``'s α), never uphill, log α within :attr:`OFFSET_SPAN`
        (``edge`` where it ends on a bound). Each value's standard deviation is the
        least-squares one at the fitted α. A few Gauss–Newton passes over the record: about
        1 ms for the paper's magnetisation, so the cycle that ends it stays within its
        period."""
        n = len(self._rec)
        if self.gaps or n < 10 or n >= self.RECORD_MAX:
            return None
        rec = np.array(self._rec)
        i, a, b, i_f = rec[:, 0], rec[:, 1], rec[:, 2], rec[:, 3]
        m, T = self.motor, self._T
        L_ls, L_lr = m.L_s - m.M, m.L_r - m.M
        U = a / self._k_r + m.sigma * i  # T·Σ ū
        Q = b / self._k_r  # T·Σ i (charge)
        if noisy and len(self._rec_model) == n:
            # the reading the drive regulated, without the sensors' noise: the model's
            # current in every place the reading enters (see :meth:`_noisy`)
            i = i_f = np.array(self._rec_model)
            Q = T * np.cumsum(i)
        Tk = T * np.arange(1, n + 1, dtype=float)
        # phase b's reading in the (a, b) frame: a gain error λ moves i_true by −λ·e_b
        e_b = 1j * (2.0 / SQRT3) * phases(i)[1]
        e_b_f = 1j * (2.0 / SQRT3) * phases(i_f)[1]  # of the mean currents
        E = T * np.cumsum(e_b_f)
        x = np.stack([i_f, e_b_f])  # the rotor model's inputs
        lo, hi = (math.log(f) for f in self.OFFSET_SPAN)
        # θ = (R_s, Re o, Im o, λ, M, s), α = α̂·e^s (α̂ the first fit's)
        theta = np.array([float(first.R_s), 0.0, 0.0, 0.0, float(m.M), 0.0])
        free = [0, 1, 2, 3, 4, 5] if fit_M else [0, 1, 2, 3, 5]

        def residual(th: np.ndarray) -> tuple[np.ndarray, np.ndarray, float, np.ndarray]:
            """(r, the unit filter of i_true, Σ|r|², ∂r/∂θ's real and imaginary rows)"""
            R, o, lam, M = th[0], complex(th[1], th[2]), th[3], th[4]
            alpha = first.alpha * math.exp(th[5])
            e = math.exp(-alpha * T)
            f = first_order(x, e, 1.0 - e)
            F, F_b = f  # f_k(α)[i], f_k(α)[e_b]
            decay = np.exp(-alpha * Tk)
            flux_i = F - o * (1.0 - decay) - lam * F_b  # unit filter of i_true
            L_r = L_lr + M
            kr = L_r / M
            sigma = L_ls + M - M * M / L_r
            i_t = i - o - lam * e_b
            I_t = Q - o * Tk - lam * E
            r = kr * (U - R * I_t - sigma * i_t) - M * flux_i
            # ∂f_k/∂α = e·∂f_{k−1}/∂α + T·e·(x_k − f_{k−1}): the same filter's recursion
            prev = np.concatenate((np.zeros((2, 1), dtype=complex), f[:, :-1]), axis=1)
            G, G_b = first_order(T * e * (x - prev), e)
            q = kr * (R * Tk + sigma) + M * (1.0 - decay)
            p = kr * (R * E + sigma * e_b) + M * F_b
            d_kr = -L_lr / (M * M)
            d_sigma = 1.0 - (M * M + 2.0 * M * L_lr) / (L_r * L_r)
            d_M = d_kr * (U - R * I_t - sigma * i_t) - kr * d_sigma * i_t - flux_i
            d_s = -M * alpha * (G - o * Tk * decay - lam * G_b)
            cols = np.stack((-kr * I_t, q + 0j, 1j * q, p, d_M, d_s))[free]  # ∂r/∂θ
            J = np.concatenate((cols.real, cols.imag), axis=1)
            return r, flux_i, float(np.sum(r.real ** 2 + r.imag ** 2)), J

        r, flux_i, cost, J = residual(theta)
        for _ in range(self.GN_STEPS):
            A = J @ J.T
            step = np.linalg.solve(A, -(J @ np.concatenate((r.real, r.imag))))
            ds = step[-1]
            if abs(ds) > self.GN_LOG_ALPHA_STEP:  # the fit is bilinear but for α: a trust
                step *= self.GN_LOG_ALPHA_STEP / abs(ds)  # region on log α
            new = theta.copy()
            new[free] += step
            new[5] = min(max(new[5], lo), hi)
            for _ in range(8):  # never uphill: halve the step until the cost falls
                trial = residual(new)
                if trial[2] <= cost:
                    break
                new = 0.5 * (theta + new)
            else:
                break
            done = np.all(np.abs(new - theta) <= 1e-12 * (1.0 + np.abs(theta)))
            theta = new
            r, flux_i, cost, J = trial
            if done:
                break
        # the standard deviations of (o, λ): least squares at the fitted α
        A = J[:-1] @ J[:-1].T
        s2 = cost / max(2 * n - 1 - (len(free) - 1), 1)
        std = np.sqrt(np.diag(np.linalg.inv(A))[1:4] * s2)
        ssa = float(np.sum(a.real ** 2 + a.imag ** 2))
        # the flux at the last sample: the rotor model's with the true current (exact at
        # standstill for α; the voltage model's would carry the fit's R_s error times ∫i:
        # 0.029 against 0.0096 rad/s RMS with a 10 mA offset after the handover)
        s, M = float(theta[5]), float(theta[4])
        return OffsetFit(R_s=float(theta[0]), alpha=first.alpha * math.exp(s), M=M,
                         offset_ab=complex(theta[1], theta[2]), std_ab=complex(std[0], std[1]),
                         gain_b=1.0 / (1.0 - float(theta[3])), gain_b_std=float(std[2]),
                         psi_ab=complex(M * flux_i[-1]),
                         fit=cost / ssa if ssa > 0.0 else math.nan,
                         edge=s <= lo + 1e-9 or s >= hi - 1e-9)


class Commissioning:
    """The controller's side of the identification: samples fed while the speed reference
    and the load rest at zero (the magnetisation at standstill), solved once at the first
    sample where either does not, or once the flux reference, after it rose, has held still
    for :attr:`SETTLED_S` (a profile that stays at standstill under load, or long after its
    magnetisation, gets the identified values before it needs them). :attr:`result` is
    None until then."""

    #: how long the flux reference holds still after its rise before the magnetisation is
    #: over, s (the controller's flux follows its reference: (16)'s feedforward)
    SETTLED_S = 0.05
    #: the least phase offset (A), and gain error, the run corrects: the fit is within
    #: 0.5 mA and 0.1 % on the shipped plants (5 mA of noise alone gives 0.4 mA); below
    #: both the sensors are read as they are
    OFFSET_MIN = 1e-3
    GAIN_MIN = 5e-3
    #: the least change of M (relative) the fit applies without a sensor error: 5 mA of
    #: noise alone moves it by 2.2 %
    M_MIN = 0.03
    #: the rms (A) of the measured current's mismatch with the controller's model at
    #: standstill up to which it is the setpoints' and readings' resolution (the bus's
    #: 1 mA: 0.29 mA; 5 mA of noise per axis: 7.1 mA), which the voltage model corrects
    #: sample by sample; above it the sensors' noise dominates, and the mismatch's weight
    #: κ = (NOISE_RMS/rms)² is the Wiener gain for a systematic part of at most NOISE_RMS
    #: (docs/robustness.md §5 "Sensor noise")
    NOISE_RMS = 2e-3

    def __init__(self, motor: Motor, period: float, sensors: bool = False) -> None:
        self.identifier = StandstillIdentifier(motor, period)
        self.sensors = sensors
        self.result: Identification | None = None
        self._settled = max(1, round(self.SETTLED_S / period))
        self._rose = False  # the flux reference has moved
        self._still = 0  # samples since it last moved
        self._psi_fit = 0j  # the rotor flux of the sensors' fit at its last sample
        self._joint = False  # the result is the sensors' fit's (with its M)
        self._mismatch_ss = 0.0  # Σ|i_measured − i_model|² over the standstill
        self._mismatch_n = 0
        self._charged = False  # the drive does not hold the current (a voltage drive, a loop)
        self._psi_dead: complex | None = None  # the dead-time fit's flux, where accepted

    def step(self, refs: Refs, i_s_ab: complex, u_s_ab: complex,
             charge: complex | None = None, i_model: complex | None = None
             ) -> Identification | None:
        """One sample with its references (``charge``: :meth:`StandstillIdentifier.add`;
        ``i_model``: the controller's model of the current at the sample, A (a, b), where
        the drive holds the current it was given); the identification at the sample that
        ends the standstill, else None."""
        if self.result is not None:
            return None
        self.identifier.add(i_s_ab, u_s_ab, charge, i_model)
        self._charged = self._charged or charge is not None
        if i_model is not None:
            d = i_s_ab - i_model
            self._mismatch_ss += d.real * d.real + d.imag * d.imag
            self._mismatch_n += 1
        moving = getattr(refs, "dpsi_ref", 0.0) != 0.0 or getattr(refs, "ddpsi_ref", 0.0) != 0.0
        self._rose = self._rose or moving
        self._still = 0 if moving else self._still + 1
        magnetised = self._rose and self._still >= self._settled
        if (refs.w_ref == 0.0 and refs.dw_ref == 0.0 and refs.T_L == 0.0
                and not magnetised):
            return None
        rms, gain = math.nan, 1.0
        if self._mismatch_n:
            rms = math.sqrt(self._mismatch_ss / self._mismatch_n)
            gain = 1.0 if rms <= self.NOISE_RMS else (self.NOISE_RMS / rms) ** 2
        found = self.identifier.solve(noisy=gain < 1.0)
        ident = self.identifier
        if (self.sensors and not math.isnan(found.fit)
                and abs(ident.flux(found.R_s)) >= StandstillIdentifier.PSI_MIN):
            found = self._with_offsets(found, gain < 1.0)
        if (self._charged and not found.accepted
                and found.fit > StandstillIdentifier.FIT_MAX):
            found = self._with_dead_time(found)
        if self._mismatch_n:
            found = replace(found, mismatch_rms=rms, mismatch_gain=gain)
        self.result = found
        return found

    def _with_dead_time(self, first: Identification) -> Identification:
        """``first``, refused for its residual on a drive that does not hold the current
        (only there does the inverter's voltage error reach the motor), fitted again with
        that error (:meth:`StandstillIdentifier.solve_dead_time`): accepted with it where
        that fit agrees, else ``first`` with why not added to its reason. The sensors are
        read as they are then: an offset along the current makes the same ramp in (D1)."""
        fitted = self.identifier.solve_dead_time()
        if fitted is None:
            return first
        found, psi = fitted
        if not found.accepted:
            return replace(first, reason=f"{first.reason}; {found.reason}")
        self._psi_dead = psi
        return replace(found, offset_a=first.offset_a, offset_b=first.offset_b,
                       gain_b=first.gain_b, offset_a_std=first.offset_a_std,
                       offset_b_std=first.offset_b_std, gain_b_std=first.gain_b_std,
                       sensors_reason="not fitted with the dead time (an offset along the "
                                      "current makes the same ramp)")

    def _with_offsets(self, first: Identification, noisy: bool = False) -> Identification:
        """``first`` with the current sensors' errors fitted (:meth:`StandstillIdentifier.
        solve_offsets`): where they are corrected, accepted with the joint fit's R_s and α
        (also when ``first`` was refused for its residual: a sensor error the first fit
        cannot explain); else ``first``, with the errors found and why they are not."""
        fit = self.identifier.solve_offsets(first, noisy=noisy)
        m = self.identifier.motor
        if fit is not None and abs(fit.M / m.M - 1.0) < self.M_MIN:  # M: the controller's
            fit = self.identifier.solve_offsets(first, fit_M=False, noisy=noisy)
        if fit is None:
            return replace(first, sensors_reason="samples missing during the standstill: "
                                                  "sensor errors not fitted")
        o_a, o_b = phases(fit.offset_ab)
        s_a = fit.std_ab.real
        s_b = 0.5 * math.sqrt(3.0 * fit.std_ab.imag ** 2 + s_a ** 2)
        found = replace(first, offset_a=o_a, offset_b=o_b, gain_b=fit.gain_b,
                        offset_a_std=s_a, offset_b_std=s_b, gain_b_std=fit.gain_b_std)
        largest = max(abs(o_a), abs(o_b))
        if fit.edge:
            reason = "α at the edge of the offsets' fit"
        elif not fit.fit <= StandstillIdentifier.FIT_MAX:
            reason = f"the offsets' fit does not agree (relative residual {fit.fit:.2g})"
        elif not (0.5 * m.R_s <= fit.R_s <= 2.0 * m.R_s
                  and StandstillIdentifier.SPAN[0] <= fit.alpha * m.L_r / m.R_r
                  <= StandstillIdentifier.SPAN[1]):
            reason = (f"R_s = {fit.R_s:.3g} Ω or α = {fit.alpha:.3g} 1/s of the offsets' fit "
                      "is out of range")
        elif not 0.5 <= fit.gain_b <= 2.0:
            reason = f"phase b's gain {fit.gain_b:.3g} of the offsets' fit is out of range"
        elif not 0.5 <= fit.M / m.M <= 2.0:
            reason = f"M = {fit.M:.3g} H of the offsets' fit is out of range"
        else:
            reason = ""
        sensors = largest >= self.OFFSET_MIN or abs(fit.gain_b - 1.0) >= self.GAIN_MIN
        inductance = abs(fit.M / m.M - 1.0) >= self.M_MIN
        if not reason and not (sensors or inductance):
            reason = (f"offsets below {1e3 * self.OFFSET_MIN:g} mA, gain within "
                      f"{100 * self.GAIN_MIN:g} % and M within {100 * self.M_MIN:g} % (the "
                      "fit's own error on the shipped plants): the sensors are read as they "
                      "are")
        if reason:
            return replace(found, sensors_reason=reason)
        self._psi_fit = fit.psi_ab
        self._joint = True
        L_s, L_r = m.L_s - m.M + fit.M, m.L_r - m.M + fit.M
        if not sensors:
            found = replace(found, offset_a=0.0, offset_b=0.0, gain_b=1.0)
        return replace(found, R_s=fit.R_s, R_r=fit.alpha * L_r, alpha=fit.alpha, M=fit.M,
                       L_s=L_s, L_r=L_r, fit=fit.fit, sensors_corrected=sensors,
                       accepted=True, reason="", sensors_reason="" if sensors else (
                           f"offsets below {1e3 * self.OFFSET_MIN:g} mA and gain within "
                           f"{100 * self.GAIN_MIN:g} %: the sensors are read as they are "
                           "(M is the fit's)"))

    @property
    def correction(self) -> SensorCorrection | None:
        """The sensors' correction the identification found (None: none, or not yet)."""
        f = self.result
        if f is None or not (f.sensors_corrected or f.u_dead):
            return None
        if not f.sensors_corrected:
            return SensorCorrection(u_dead=f.u_dead)
        return SensorCorrection(offset_a=f.offset_a, offset_b=f.offset_b, gain_b=f.gain_b,
                                u_dead=f.u_dead)

    def gap(self) -> None:
        """A period without a sample (a missed cycle) while the identification is pending:
        :meth:`StandstillIdentifier.gap`."""
        if self.result is None:
            self.identifier.gap()

    def apply(self, refs: Refs, i_s_ab: complex, u_s_ab: complex, estimator: Any,
              psi_hat_ab: complex | None, charge: complex | None = None,
              i_model: complex | None = None
              ) -> tuple[Identification | None, complex | None]:
        """:meth:`step`, and the rotor flux the laws take at this sample (Wb, (a, b)), with
        the identification when it is accepted at this sample (else None):

        * at standstill, while the identification is pending: the current model's flux
          (:meth:`standstill_flux`; R_s and the sensors' offsets do not enter its frame:
          it holds the frame still, and with it the rotor, while the voltage model would
          integrate an R_s or offset error into a turning frame, and the torque of the
          offset current would turn the rotor the identification takes to be at rest);
        * at the sample that ends an accepted identification: the flux ``estimator``
          restarts from (its ``identified``), the voltage model with the identified R_s;
          the controller uses the identified R_s and R_r from now on;
        * at the sample that ends a refused one: the current model's flux, which the
          ``estimator`` restarts from with the controller's R_s (not the flux it integrated
          over the magnetisation with an R_s error);
        * after: the estimator's ``psi_hat_ab`` (None: the laws take the true flux).

        ``i_model``: :meth:`step`; where the mismatch was the sensors' noise the estimator
        weighs it by the result's ``mismatch_gain`` from now on."""
        found = self.step(refs, i_s_ab, u_s_ab, charge, i_model)
        if found is None:
            if self.pending and psi_hat_ab is not None:
                return None, self.standstill_flux()
            return None, psi_hat_ab
        kappa = found.mismatch_gain
        if kappa < 1.0 and i_model is not None:
            # the stator flux the estimator restarts from is σ·i + (M/L_r)·ψ_r: with this
            # sample's noise in i it would keep σ·n for good (0.3 mWb at 5 mA)
            i_s_ab = i_model + kappa * (i_s_ab - i_model)
        if not found.accepted:
            psi = self.standstill_flux()
            estimator.identified(self.identifier.motor.R_s, psi, i_s_ab, kappa)
            return None, psi if psi_hat_ab is not None else None
        psi = self.flux()
        corr = self.correction
        if self._joint:  # the fit's inductances from now on
            estimator.inductances(found.M, found.L_s, found.L_r)
        estimator.identified(found.R_s, psi,
                             i_s_ab if corr is None else corr.true_current(i_s_ab), kappa)
        return found, psi

    @property
    def pending(self) -> bool:
        """The standstill lasts and its identification is yet to come."""
        return self.result is None

    def standstill_flux(self) -> complex:
        """While :attr:`pending`: the rotor flux of the current model (R_s-free; exact at
        standstill for the controller's α), Wb (a, b)."""
        return self.identifier.current_model_flux()

    def flux(self) -> complex:
        """The voltage-model rotor flux at the last sample with the identified R_s, Wb; the
        current model's with the identified α where samples were missing during the
        standstill (:meth:`StandstillIdentifier.add`). Where the current's mismatch was
        the sensors' noise (``mismatch_gain`` κ < 1) κ of the voltage model's and 1 − κ of
        the current model's: the voltage model carries the last sample's noise (σ·L_r/M
        times it) and the random walk of R_s·T·Σn over the standstill, the current model
        the noise through the rotor's filter (√(αT/2) of it)."""
        result = self.result
        assert result is not None
        ident = self.identifier
        if ident.gaps:
            return ident.current_model_flux_at(result.alpha)
        if self._joint:
            return self._psi_fit
        if self._psi_dead is not None:  # the dead-time fit's: the current model's, its α
            return self._psi_dead
        psi = ident.flux(result.R_s)
        kappa = result.mismatch_gain
        if kappa < 1.0:
            psi = kappa * psi + (1.0 - kappa) * ident.current_model_flux_at(result.alpha)
        return psi

    def describe(self) -> dict[str, object]:
        """For summary.json: the identification, or why there is none."""
        if self.result is None:
            return {"accepted": False, "samples": self.identifier.samples,
                    "reason": "the speed and load references never left zero: no end of "
                              "the standstill"}
        return asdict(self.result)
