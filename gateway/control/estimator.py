"""Rotor-flux estimation from stator-flux integration, (24) as corrected in §E1.

Only the stator flux is integrated, in the fixed (a, b) frame:

    dψ_s/dt = u_s − R_s·i_s,                     (24), first two lines, §E1

and the rotor flux follows algebraically from the flux linkages:

    ψ_r = (L_r/M)·(ψ_s − σ·i_s).                 (24), last two lines, §E1

Rotating (a, b) → (d, q) by ε0 afterwards is equivalent to the printed rotating-frame form.

The estimators work from what a drive reports each sampling period T: the currents sampled
at the period's end and the *average* applied voltage over the period. The integral of
u_s is then exact (T·ū_s); the integral of R_s·i_s uses the trapezoidal rule on the two
current samples.

Two variants:

* :class:`OpenLoopFluxEstimator` — the paper's open-loop integrator from zero initial
  conditions. Any current-sensor offset or R_s error is integrated without bound (§E2).
* :class:`DriftFreeFluxEstimator` — the integrator with a first-order correction towards
  the stator flux that field orientation implies,

      dψ_s/dt = u_s − R_s·i_s − ω_c·(ψ_s − ψ_s°),
      ψ_s° = e^{jε0}·(σ·i_sd + (M/L_r)·ψ* + j·σ·i_sq),

  a closed-loop flux observer in the spirit of Hu & Wu (1998), whose voltage model is
  corrected at low frequency by a current-model flux (here the reference flux ψ* along d).
  Above ω_c it is the voltage model; an offset produces a bounded error of about
  offset·R_s/ω_c instead of a ramp. Default ω_c = 2 rad/s, far below the speed-observer
  dynamics (√(ψ*²/γ1) ≈ 41 rad/s at 1.16 Wb).

Complex numbers carry (a, b) pairs: ``x_ab = x_a + 1j*x_b``.
"""

from __future__ import annotations

import cmath
import math
from typing import Protocol


class Motor(Protocol):
    R_s: float
    L_r: float
    M: float
    sigma: float


class OpenLoopFluxEstimator:
    """Pure integrator of (24) (§E1, §E2): ψ_s(0) = 0, drifts with any offset."""

    def __init__(self, motor: Motor) -> None:
        self._R_s = motor.R_s
        self._sigma = motor.sigma
        self._k_r = motor.L_r / motor.M
        self._m_lr = motor.M / motor.L_r
        self.psi_s_ab = 0j
        self._i_prev: complex | None = None

    def reset(self) -> None:
        """Back to ψ_s = 0 and no previous current sample."""
        self.psi_s_ab = 0j
        self._i_prev = None

    def inductances(self, M: float, L_s: float, L_r: float) -> None:
        """The inductances (H) from now on (a standstill identification that fitted M)."""
        self._sigma = L_s - M * M / L_r
        self._k_r = L_r / M
        self._m_lr = M / L_r

    def identified(self, R_s: float, psi_r_ab: complex, i_s_ab: complex,
                   mismatch_gain: float = 1.0) -> None:
        """After a standstill identification (:mod:`gateway.control.commissioning`): the
        identified R_s (Ω) from now on, and the rotor flux at this sample (Wb, (a, b)).
        ``mismatch_gain``: the weight of the measured current's mismatch in the voltage
        model from now on (:class:`IntervalFluxEstimator`; the others integrate the
        measured current itself)."""
        self._R_s = R_s
        self.psi_s_ab = self._sigma * i_s_ab + self._m_lr * psi_r_ab

    def _rate(self, i_s_ab: complex, u_s_ab: complex, T: float) -> complex:
        """∫(u_s − R_s·i_s)dt over the last period, Wb (trapezoidal current integral)."""
        i_prev = i_s_ab if self._i_prev is None else self._i_prev
        self._i_prev = i_s_ab
        return T * u_s_ab - self._R_s * T * 0.5 * (i_prev + i_s_ab)

    def update(
        self, i_s_ab: complex, u_s_ab: complex, T: float, eps_0: float = 0.0, psi_ref: float = 0.0
    ) -> complex:
        """Integrate one period and return the rotor flux ψ_r_ab, Wb.

        i_s_ab: current sampled at the end of the period, A. u_s_ab: average applied voltage
        over the period, V. T: period, s. eps_0, psi_ref: unused here (the drift-free
        variant uses them).
        """
        self.psi_s_ab += self._rate(i_s_ab, u_s_ab, T)
        return self.rotor_flux(i_s_ab)

    def coast(self, w_0: float, T: float) -> None:
        """A period without a sample (a missed cycle): the voltage integral cannot be formed,
        so the stator flux and the last current are turned by ω0·T, which is what they do in
        the steady state (dψ_s/dt = jω0·ψ_s in the fixed frame); holding them instead would
        leave the open-loop integrator with a lasting error of about |ψ_s|·ω0·T per miss."""
        rot = cmath.exp(1j * w_0 * T)
        self.psi_s_ab *= rot
        if self._i_prev is not None:
            self._i_prev *= rot

    def rotor_flux(self, i_s_ab: complex) -> complex:
        """ψ_r = (L_r/M)·(ψ_s − σ·i_s) (§E1), Wb."""
        return self._k_r * (self.psi_s_ab - self._sigma * i_s_ab)

    def _oriented(self, i_s_ab: complex, eps_0: float, psi_ref: float) -> complex:
        """ψ_s° = e^{jε0}·(σ·i_sd + (M/L_r)·ψ* + j·σ·i_sq): the stator flux field orientation
        implies (the drift-free correction's target), (a, b) frame, Wb."""
        rot = cmath.exp(1j * eps_0)
        i_s_dq = i_s_ab * rot.conjugate()
        return rot * complex(self._sigma * i_s_dq.real + self._m_lr * psi_ref,
                             self._sigma * i_s_dq.imag)

    def _adapt(self, psi_s_o: complex, i_s_ab: complex, eps_0: float, T: float) -> None:
        """Called by the corrected estimators with the correction's target ψ_s° before a
        period is integrated; the R_s-adaptive ones update R̂_s here."""


class DriftFreeFluxEstimator(OpenLoopFluxEstimator):
    """Integrator with low-frequency correction towards the field-oriented stator flux."""

    def __init__(self, motor: Motor, w_c: float = 2.0) -> None:
        super().__init__(motor)
        if not w_c > 0.0:
            raise ValueError(f"drift-free estimator: w_c = {w_c!r} rad/s must be > 0")
        self.w_c = w_c

    def update(
        self, i_s_ab: complex, u_s_ab: complex, T: float, eps_0: float = 0.0, psi_ref: float = 0.0
    ) -> complex:
        """As :meth:`OpenLoopFluxEstimator.update`, with the correction −ω_c·(ψ_s − ψ_s°).

        eps_0: frame angle at the sample, rad. psi_ref: flux reference ψ*, Wb. The
        correction is integrated exactly over T (first-order decay factor e^{−ω_c·T}).
        """
        psi_s_oriented_ab = self._oriented(i_s_ab, eps_0, psi_ref)
        self._adapt(psi_s_oriented_ab, i_s_ab, eps_0, T)
        decay = self._decay(T)
        increment = self._rate(i_s_ab, u_s_ab, T)
        # ψ_s ← ψ_s° + e^{−ω_c T}(ψ_s − ψ_s°) + increment (the increment enters undamped:
        # the first-order error of doing so is ω_c·T/2 relative, 0.1 % at T = 1 ms).
        self.psi_s_ab = psi_s_oriented_ab + decay * (self.psi_s_ab - psi_s_oriented_ab)
        self.psi_s_ab += increment
        return self.rotor_flux(i_s_ab)

    def _decay(self, T: float) -> float:
        return cmath.exp(-self.w_c * T).real


class IntervalFluxEstimator(OpenLoopFluxEstimator):
    """(24) with the current integral the drive applied (the sampled-data design).

    The trapezoid of :class:`OpenLoopFluxEstimator` weighs the sample taken *before* a
    setpoint step as if the current had moved linearly across the period; the drive steps
    it at the period's start. Here the controller, which knows what it commanded, passes the
    integral of the applied current over the period, ∫i dt, and the applied current at its
    end; the difference between the measured and the modelled current at the samples
    (sensor errors, a current loop's lag) is added as a trapezoid:

        ψ_s(t_k) = ψ_s(t_{k−1}) + T·ū − R_s·(∫i_model dt + κ·T·(δ_{k−1} + δ_k)/2),
        δ_k = i_measured(t_k) − i_model(t_k),

    with δ_{k−1} = 0 where the model starts the period from the measured current. κ = 1
    but where the standstill identification found the mismatch to be the sensors' noise
    (:attr:`mismatch_gain`, set by :meth:`identified`; docs/robustness.md §5 "Sensor
    noise"): the trapezoid of white noise is a random walk in ψ_s, R_s·T·Σn (1 mWb in a
    second for 5 mA at 1 ms), while the mismatch it is there for (the setpoints' and
    readings' resolution) is a fraction of a mA.

    The last period's charge (the bracket) is :attr:`charge`. With ``w_c > 0`` the
    drift-free correction of :class:`DriftFreeFluxEstimator` is added.
    """

    def __init__(self, motor: Motor, w_c: float = 0.0) -> None:
        super().__init__(motor)
        if w_c < 0.0:
            raise ValueError(f"interval estimator: w_c = {w_c!r} rad/s must be >= 0")
        self.w_c = w_c
        self._delta = 0j
        #: κ, the weight of the measured mismatch's trapezoid where the drive holds the
        #: current (1 until :meth:`identified` says otherwise)
        self.mismatch_gain = 1.0
        #: ∫i dt over the last period (A·s, (a, b)): the model's with the trapezoid of δ
        self.charge = 0j

    def update(  # type: ignore[override]
        self, i_s_ab: complex, u_s_ab: complex, T: float, int_i_ab: complex,
        i_end_ab: complex, eps_0: float = 0.0, psi_ref: float = 0.0,
        from_sample: bool = False,
    ) -> complex:
        """Integrate one period; returns ψ_r_ab at its end, Wb.

        i_s_ab: measured current at the end, A. u_s_ab: average applied voltage, V.
        int_i_ab: ∫ of the applied current over the period (model), A·s. i_end_ab: the
        model's current at the end, A. eps_0, psi_ref: frame angle and ψ* for w_c > 0.
        from_sample: the model starts the period from the measured current (a current
        loop's rise, a voltage drive's trajectory), so δ = 0 at its start: the trapezoid
        is T·δ_k/2 (with δ_{k−1} there it added T·δ_{k−1}/2 of charge the model already
        holds: with R_r +20 % on the voltage drive that made the identification find α
        1.1 % high and the full-order law run at 0.12 rad/s RMS instead of 0.008).
        """
        corrected = self.w_c > 0.0
        if corrected:
            target = self._oriented(i_s_ab, eps_0, psi_ref)
            self._adapt(target, i_s_ab, eps_0, T)
        delta = i_s_ab - i_end_ab
        # (κ = 1: the same bits as without it, the product 0.5·T·1.0 being exact)
        charge = self.charge = int_i_ab + (
            0.5 * T * delta if from_sample
            else 0.5 * T * self.mismatch_gain * (self._delta + delta))
        increment = T * u_s_ab - self._R_s * charge
        self._delta = delta
        if corrected:
            decay = cmath.exp(-self.w_c * T).real
            self.psi_s_ab = target + decay * (self.psi_s_ab - target)
        psi_s = self.psi_s_ab = self.psi_s_ab + increment
        return self._k_r * (psi_s - self._sigma * i_s_ab)  # rotor_flux(i_s_ab), inline

    def identified(self, R_s: float, psi_r_ab: complex, i_s_ab: complex,
                   mismatch_gain: float = 1.0) -> None:
        super().identified(R_s, psi_r_ab, i_s_ab)
        if not 0.0 <= mismatch_gain <= 1.0:
            raise ValueError(f"mismatch gain {mismatch_gain!r} must be within 0…1")
        self.mismatch_gain = mismatch_gain

    def set_rotor_flux(self, psi_r_ab: complex, i_s_ab: complex) -> None:
        """Take the stator flux σ·i_s + (M/L_r)·ψ_r of a model (a period without data)."""
        self.psi_s_ab = self._sigma * i_s_ab + self._m_lr * psi_r_ab


class RsAdaptation:
    """The on-line stator-resistance law shared by the R_s-adaptive estimators.

    With the correction −ω_c·(ψ_s − ψ_s°), a resistance error ΔR = R_s − R̂_s leaves, for a
    current phasor turning at the stator frequency ω0, the steady residual

        ε = ψ̂_s − ψ_s° = ΔR·i_s/(ω_c + jω0)      ⇒      (ω_c + jω0)·ε·conj(i_s) = ΔR·|i_s|²,

    real and of the sign of ΔR at every stator frequency, zero included (where the
    uncorrected integrator would only ramp). Hence the adaptation

        dR̂_s/dt = γ_R·Re((ω_c + jω0)·ε·conj(i_s))/|i_s|²,

    a gradient law on the residual along the current (the current-model flux ψ_s° as the
    low-frequency reference, cf. Jansen & Lorenz, IEEE Trans. IA 30(1), 1994; stator
    resistance identification from the flux residual, e.g. Marino, Peresada & Tomei,
    "On-line stator and rotor resistance estimation for induction motors", IEEE Trans.
    CST 8(3), 2000). ω0 is taken from the frame angle's increment, ε before each
    correction. The law is weighted by ω_c²/(ω_c² + ω0²), the squared sensitivity of ε to
    ΔR: it adapts at low stator frequency, where R_s matters, and barely at speed, where a
    residual mostly means an orientation error (unweighted, the paper scenario's RMS went
    from 0.27 to 3 rad/s). R̂_s is kept within [0.5, 2]·R_s(nominal); below |i_s| = 0.5 A
    nothing is adapted. Defaults ω_c = 5 rad/s, γ_R = 60 s⁻¹ (a grid over γ_R ∈ {2, 10, 30,
    60} × ω_c ∈ {2, 5, 8} on the paper, zero-speed and slow-reversal profiles with R_s ±10 %;
    docs/robustness.md). It assumes the current model is right: R_r errors and orientation
    errors also leave a residual and bias R̂_s.
    """

    def __init__(self, R_nom: float, w_c: float, gamma_r: float) -> None:
        if not gamma_r > 0.0:
            raise ValueError(f"Rs-adaptive estimator: gamma_r = {gamma_r!r} 1/s must be > 0")
        self.gamma_r = gamma_r
        self.w_c = w_c
        self._R_nom = R_nom
        self._eps_prev: float | None = None

    def update(self, R_s: float, psi_s_ab: complex, psi_s_o: complex, i_s_ab: complex,
               eps_0: float, T: float) -> float:
        """R̂_s after one period (Ω): the stator flux before the correction, its
        field-oriented target ψ_s°, the current and the frame angle at the sample."""
        w_0 = 0.0
        if self._eps_prev is not None:
            w_0 = ((eps_0 - self._eps_prev + math.pi) % (2.0 * math.pi) - math.pi) / T
        self._eps_prev = eps_0
        i2 = i_s_ab.real * i_s_ab.real + i_s_ab.imag * i_s_ab.imag
        if i2 <= 0.25:
            return R_s
        res = complex(self.w_c, w_0) * (psi_s_ab - psi_s_o) * i_s_ab.conjugate()
        w_c2 = self.w_c * self.w_c
        weight = w_c2 / (w_c2 + w_0 * w_0)  # the residual's sensitivity to ΔR, squared
        r = R_s + T * self.gamma_r * weight * res.real / i2
        return min(max(r, 0.5 * self._R_nom), 2.0 * self._R_nom)


class _AdaptsRs:
    """What the two R_s-adaptive estimators add to their base: :class:`RsAdaptation` in the
    :meth:`OpenLoopFluxEstimator._adapt` hook, before each period's integration."""

    adaptation: RsAdaptation
    _R_s: float
    psi_s_ab: complex

    @property
    def R_s_hat(self) -> float:
        """The adapted stator resistance, Ω."""
        return self._R_s

    def _adapt(self, psi_s_o: complex, i_s_ab: complex, eps_0: float, T: float) -> None:
        self._R_s = self.adaptation.update(self._R_s, self.psi_s_ab, psi_s_o, i_s_ab, eps_0, T)


class RsAdaptiveFluxEstimator(_AdaptsRs, DriftFreeFluxEstimator):
    """The drift-free estimator with on-line stator-resistance adaptation
    (:class:`RsAdaptation`), the Euler design's."""

    def __init__(self, motor: Motor, w_c: float = 5.0, gamma_r: float = 60.0) -> None:
        super().__init__(motor, w_c)
        self.adaptation = RsAdaptation(motor.R_s, w_c, gamma_r)


class IntervalRsAdaptiveFluxEstimator(_AdaptsRs, IntervalFluxEstimator):
    """:class:`IntervalFluxEstimator` with the drift-free correction and
    :class:`RsAdaptation` (the sampled-data design's R_s-adaptive estimator)."""

    def __init__(self, motor: Motor, w_c: float = 5.0, gamma_r: float = 60.0) -> None:
        super().__init__(motor, w_c)
        if not w_c > 0.0:
            raise ValueError(f"Rs-adaptive estimator: w_c = {w_c!r} rad/s must be > 0")
        self.adaptation = RsAdaptation(motor.R_s, w_c, gamma_r)
