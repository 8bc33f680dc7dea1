"""On-line inertia: the ratio ρ = J/J_true of the motor file's inertia to the rotor's, from
the flux the estimator measures (docs/robustness.md §9).

Why. The speed law (15) and the observer (16)/(27) take J: the feed-forward of the speed
reference's acceleration, and the mechanical copy that predicts ω̂. With the rotor's
inertia twice the model's, the observer predicts twice the acceleration the rotor makes,
and the correction (20) — a lightly damped loop, ψ*²/γ1 ≈ 1700 s⁻² against the rotor's
α ≈ 9 s⁻¹ of damping — lets ω̂ run 28 rad/s ahead within the first speed step; the speed
loop, whose feedback sat(·) caps at k_ω = 800 rad/s², cannot make up half the torque
either: the run diverges. The inertia is a mechanical constant a standstill test cannot
see (`hil-gateway identify --rotate` measures it on request).

What the flux tells. Over each interval the controller models the rotor flux from the
measured flux at its start at the midpoint speed ω̂_m (:meth:`SampledController._advance`).
The rotor's true speed ω turns the measured flux away from the model's by
δ = ψ_meas(T) − ψ_model(T) ≈ −j·(ω̂_m − ω)·∫ψ dτ, so each interval gives a measurement of
the rotor's mean speed,

    y_k = ω̂_m + Im(δ / ∫ψ dτ)                                                     (I1)

noisy (it is the derivative of a flux: 0.025 rad/s rms with the PDOs' 1 mA and 20 mV, 0.4
with 5 mA of current noise) but independent of J. The mechanical equation of (1) in the
motor file's terms is dω/dt = ρ·a, a = μ(ψ_rd·i_sq − ψ_rq·i_sd) − T_L/J (the model's
acceleration with the file's J, known each interval as A_k = ∫a dτ), so with the state
x = (ω, ρ):

    ω_{k+1} = ω_k + ρ·A_k,   ρ_{k+1} = ρ_k,   y_k = ω_k + ρ·A_k/2 + n_k              (I2)

linear in x: a Kalman filter with a prior ρ = 1 ± 1, process noise for the speed (torque the
model does not know) and, slowly, ρ; the measurement's variance estimated on line from
successive differences of the flux's speed error (the true error changes slowly, the
noise does not). The information on ρ grows with (ΣA)², the speed the model's torque
would have given: a few milliseconds into a speed step.

What is applied. The motor file's J stays until the data reject it: ρ̂ is applied (J/ρ̂ and
μ·ρ̂ in (15), (16)/(27)) once |ρ̂ − 1| exceeds :attr:`z` standard deviations for
:attr:`persist` samples in a row, and from then on follows the filter. At that moment ω̂
takes the filter's speed (the observer had integrated the wrong acceleration until then).
A motor that is the model's keeps the model's numbers bit for bit.

Pure module: no I/O, no clock, no global state.
"""

from __future__ import annotations

from dataclasses import dataclass

#: ρ applied is kept within this range (J from a fifth to five times the file's)
RHO_RANGE = (0.2, 5.0)


@dataclass(frozen=True)
class InertiaTuning:
    """The tracker's tuning (what ``--inertia tracked`` uses; docs/robustness.md §9).

    z, persist: the test that rejects the file's J: |ρ̂ − 1| > z·σ_ρ for ``persist``
    samples in a row. p_rho: the prior variance of ρ. q_w: the speed's process noise per
    sample, (rad/s)². q_rho: ρ's per sample. r0, n0: the prior of the measurement's
    variance ((rad/s·Wb)², the variance of (I1) times |ψ|²) and its weight in samples;
    r_min: its floor."""

    z: float = 4.0
    persist: int = 1
    p_rho: float = 1.0
    q_w: float = 1e-4
    q_rho: float = 1e-8
    r0: float = 1e-2
    n0: float = 20.0
    r_min: float = 1e-4


class InertiaTracker:
    """The Kalman filter (I2) on (ω, ρ) and the test that applies ρ̂ (module docstring)."""

    __slots__ = ("_e_prev", "_n", "_p00", "_p01", "_p11", "_r", "_run", "_w", "applied", "reset",
                 "rho", "switched", "tuning")

    def __init__(self, tuning: InertiaTuning | None = None) -> None:
        self.tuning = t = tuning or InertiaTuning()
        self._w = 0.0  # ω at t_k, rad/s
        self.rho = 1.0  # the filter's ρ̂
        self._p00, self._p01, self._p11 = 1e4, 0.0, t.p_rho
        self._r = t.r0  # the measurement's variance × |ψ|²
        self._n = 0  # differences seen
        self._e_prev: float | None = None
        self._run = 0  # samples in a row that reject ρ = 1
        #: the ρ the controller applies: 1 until the test rejects it, then ρ̂ (clipped)
        self.applied = 1.0
        #: the test has rejected ρ = 1: ρ̂ is applied from then on
        self.switched = False
        #: set at the sample the test rejects ρ = 1: the controller takes :attr:`speed` as
        #: ω̂ and clears it
        self.reset = False

    @property
    def speed(self) -> float:
        """The filter's rotor speed at the last sample, rad/s."""
        return self._w

    @property
    def rho_std(self) -> float:
        """The standard deviation of ρ̂."""
        return max(self._p11, 0.0) ** 0.5

    def update(self, w_mid: float, e_hat: float, A: float, weight: float) -> float:
        """One interval: the model's midpoint speed ``w_mid`` and the flux's measure of its
        error ``e_hat`` (y = w_mid − e_hat, (I1)), the model's ∫a dτ ``A`` with the file's J
        (rad/s), the flux's |ψ|² ``weight`` (Wb²; 0: no measurement this interval, only the
        prediction). Returns the ρ to apply."""
        t = self.tuning
        w, rho = self._w, self.rho
        p00, p01, p11 = self._p00, self._p01, self._p11
        if weight > 0.0:
            e_prev = self._e_prev
            if e_prev is not None:  # the noise's variance from successive differences
                self._n += 1
                g = max(1.0 / (self._n + t.n0), 0.02)
                d = e_hat - e_prev
                self._r += g * (0.5 * d * d * weight - self._r)
            self._e_prev = e_hat
            h = 0.5 * A  # y = ω + ρ·A/2
            ph0, ph1 = p00 + h * p01, p01 + h * p11
            s = ph0 + h * ph1 + max(self._r, t.r_min) / weight
            k0, k1 = ph0 / s, ph1 / s
            nu = (w_mid - e_hat) - (w + h * rho)
            w += k0 * nu
            rho += k1 * nu
            p00 -= k0 * ph0
            p01 -= k0 * ph1
            p11 -= k1 * ph1
        else:
            self._e_prev = None
        # to the interval's end: ω += ρ·A
        w += rho * A
        p00 += 2.0 * A * p01 + A * A * p11 + t.q_w
        p01 += A * p11
        p11 += t.q_rho
        self._w, self.rho = w, rho
        self._p00, self._p01, self._p11 = p00, p01, p11
        if weight > 0.0 and not self.switched:
            if abs(rho - 1.0) > t.z * max(p11, 0.0) ** 0.5:
                self._run += 1
                if self._run >= t.persist:
                    self.switched = self.reset = True
            else:
                self._run = 0
        if self.switched:
            lo, hi = RHO_RANGE
            self.applied = min(hi, max(lo, rho))
        return self.applied

    def coast(self, A: float) -> float:
        """An interval without a measurement: the prediction alone."""
        return self.update(0.0, 0.0, A, 0.0)
