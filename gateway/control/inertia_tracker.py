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

The flux's own error. The measured flux is the estimator's: a current offset the
identification left (a few tenths of a mA) integrates into an error D constant in the
stator frame (or drifting slowly), which the interval model carries from the interval's
start with its own rotation; the reading gains

    Im(g_k·D),   g_k = e^{−jε_k}(1 − e^{(−α + jω̂_m)T}) / ∫ψ dτ                      (I3)

a ripple at the stator frequency that grows as the flux falls (±1 rad/s in field
weakening with 0.4 mA left), and that the filter of (I2) alone read as inertia. D = D_a +
jD_b joins the state, x = (ω, ρ, D_a, D_b), as a slow random walk.

What is applied. The motor file's J stays until the data reject it: ρ̂ is applied (J/ρ̂ and
μ·ρ̂ in (15), (16)/(27)) once |ρ̂ − 1| exceeds :attr:`z` standard deviations for
:attr:`persist` samples in a row, and from then on follows the filter. At that moment ω̂
takes the filter's speed (the observer had integrated the wrong acceleration until then).
A motor that is the model's keeps the model's numbers bit for bit.

Lost samples: the controller coasts through them on its model (:meth:`InertiaTracker.coast`);
the estimator's integral over them may take an unknown constant, so D's prior reopens, and
after a few in a row the tracker stops reading and keeps the ρ it applies.

The load. Where the laws are not told it (``--load observed``), ℓ = T_L/J is a state (I4).
Where they are told it, the filter stops once ρ is known (J is constant) and then watches
(:meth:`InertiaTracker.watch`, (I5)): (ω, D) alone, each innovation tested, outliers
counted and not taken; three or more in a row of one sign that grow reject the told load,
and the filter runs again with ℓ a state, the load the told one leaves out
(docs/robustness.md §10).

Pure module: no I/O, no clock, no global state.
"""

from __future__ import annotations

from dataclasses import dataclass

#: ρ applied is kept within this range (J from a fifth to five times the file's)
RHO_RANGE = (0.2, 5.0)


@dataclass(frozen=True)
class InertiaTuning:
    """The tracker's tuning (what ``--inertia tracked`` uses; docs/robustness.md §9).

    z, persist: the test that rejects the file's J: |ρ̂ − 1| > z·σ_ρ for ``persist`` samples
    in a row; z_observed its z with the load observed (ℓ a state: J is then read from the
    changes of the acceleration alone, where the readings' errors run in one sign for tens
    of readings and σ_ρ, which takes them as white, understates ρ̂'s error: `real-drive`,
    whose J is the file's, reached 5–7σ; docs/robustness.md §12). p_rho: the prior variance
    of ρ. q_w: the speed's process noise per sample, (rad/s)². q_rho: ρ's per sample. r0,
    n0: the prior of the measurement's variance ((rad/s·Wb)², the variance of (I1) times
    |ψ|²) and its weight in samples; r_min: its floor. p_d, q_d: the prior variance of each
    component of the flux's (a, b)-constant error D (Wb²) and its process noise per sample;
    p_d_lost: D's variance after an interval the controller coasted through; max_coast: the
    coasted intervals in a row after which the tracker stops (an unknown late latch after
    113 of them shifted the estimator's integral by 0.45 Wb, beyond what (I3) holds to first
    order). p_l, q_l: the prior variance of ℓ ((rad/s²)²) and its process noise ((rad/s²)²
    per second: per sample q_l·T), with the load observed; k_s: the pull of ω̂ towards the
    filter's speed then, 1/s ((I4)); z_load, hold: the innovation (in standard deviations)
    taken as a load step, and the readings ρ is held for after one. settle: the standard
    deviation of ρ̂ at which the filter stops when the load is not observed (J is constant).
    persist_load: with the load told, the readings in a row, each beyond z_load standard
    deviations on the same side (and growing), that may reject the told load once the filter
    has stopped (:meth:`InertiaTracker.watch`, (I5)); max_gate: the outliers in a row after
    which, not grown, they are a jump of the reading, taken; settle_told: how long after the
    told load last moved outliers are not counted, s (the drive's own response to it)."""

    z: float = 4.0
    z_observed: float = 8.0
    persist: int = 1
    p_rho: float = 1.0
    q_w: float = 1e-4
    q_rho: float = 1e-8
    r0: float = 1e-2
    n0: float = 20.0
    r_min: float = 1e-4
    p_d: float = 1e-6
    q_d: float = 1e-8
    p_d_lost: float = 1e-4
    max_coast: int = 3
    p_l: float = 1e4
    q_l: float = 1e4
    k_s: float = 500.0
    z_load: float = 4.0
    hold: int = 100
    settle: float = 0.002
    persist_load: int = 3
    max_gate: int = 10
    settle_told: float = 0.02


class InertiaTracker:
    """The Kalman filter (I2)–(I4) on x = (ω, ρ, ℓ, D_a, D_b) and the test that applies ρ̂
    (module docstring). ``load``: ℓ, the load the laws are not told, is a state ((I4):
    ``--load observed``); else it is held at 0. ``inertia``: ρ is a state; else held at 1
    (``--inertia file`` with the load observed). ``T``: the period, s. Written out by
    element: the covariance's fifteen entries are floats, and a state held is one whose
    entries stay exact zeros (the same numbers, bit for bit, as a filter without it)."""

    __slots__ = (
        "_T",
        "_coasts",
        "_da",
        "_db",
        "_e_prev",
        "_hold",
        "_l",
        "_n",
        "_nu_first",
        "_p00",
        "_p01",
        "_p02",
        "_p03",
        "_p04",
        "_p11",
        "_p12",
        "_p13",
        "_p14",
        "_p22",
        "_p23",
        "_p24",
        "_p33",
        "_p34",
        "_p44",
        "_q_l",
        "_q_rho",
        "_r",
        "_run",
        "_run_load",
        "_w",
        "_watch_off",
        "applied",
        "frozen",
        "reset",
        "rho",
        "settled",
        "switched",
        "tuning",
    )

    def __init__(self, tuning: InertiaTuning | None = None, *, T: float = 1e-3,
                 load: bool = False, inertia: bool = True) -> None:
        self.tuning = t = tuning or InertiaTuning()
        self._T = T
        self._w = 0.0  # ω at t_k, rad/s
        self.rho = 1.0  # the filter's ρ̂
        self._l = 0.0  # ℓ̂, rad/s²
        self._da = self._db = 0.0  # D, Wb
        self._p00, self._p01, self._p02, self._p03, self._p04 = 1e4, 0.0, 0.0, 0.0, 0.0
        self._p11 = t.p_rho if inertia else 0.0
        self._p12 = self._p13 = self._p14 = 0.0
        self._p22 = t.p_l if load else 0.0
        self._p23 = self._p24 = 0.0
        self._p33, self._p34, self._p44 = t.p_d, 0.0, t.p_d
        self._q_rho = t.q_rho if inertia else 0.0
        self._q_l = t.q_l * T if load else 0.0
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
        #: no more readings (a long coast, or ρ settled): the applied ρ is kept
        self.frozen = False
        #: ρ is known within :attr:`InertiaTuning.settle` (one standard deviation)
        self.settled = False
        self._coasts = 0  # coasted intervals in a row
        self._hold = 0  # readings left that hold ρ (after a load step)
        self._run_load = 0  # readings in a row that reject the told load (watch), signed
        self._nu_first = 0.0  # the first innovation of that run
        self._watch_off = False  # the watch stopped (a long coast)

    def expect_noise(self, r: float) -> None:
        """Before its readings: the reading's noise variance (× |ψ|², (rad/s·Wb)²) that
        the current sensors' measured noise implies, if above the prior
        :attr:`InertiaTuning.r0` (learnt from the readings from then on). With the prior
        alone a reading 20 times noisier than assumed (5 mA per axis) took the filter's
        first readings at their word, and one noise seed in twenty rejected the file's J
        with ρ̂ 2.9 sixteen samples into the speed step."""
        if r > self._r:
            self._r = r

    @property
    def speed(self) -> float:
        """The filter's rotor speed at the last sample, rad/s."""
        return self._w

    @property
    def load(self) -> float:
        """ℓ̂: the deceleration of the load the laws are not told, T_L/J, rad/s²."""
        return self._l

    @property
    def flux_error(self) -> complex:
        """The filter's D = D_a + jD_b: the measured flux's (a, b)-constant error, Wb."""
        return complex(self._da, self._db)

    @property
    def rho_std(self) -> float:
        """The standard deviation of ρ̂."""
        return max(self._p11, 0.0) ** 0.5

    def update(self, w_mid: float, e_hat: float, A: float, weight: float,
               g: complex = 0j) -> float:
        """One interval: the model's midpoint speed ``w_mid`` and the flux's measure of its
        error ``e_hat`` (y = w_mid − e_hat, (I1)), the model's ∫a dτ ``A`` with the file's J
        and the told load (rad/s), the flux's |ψ|² ``weight`` (Wb²; 0: no measurement this
        interval, only the prediction), and ``g``, what an (a, b)-constant flux error D adds
        to y: Im(g·D) ((I3), rad/s per Wb). Returns the ρ to apply."""
        t = self.tuning
        if self.frozen:
            return self.applied
        T = self._T
        w, rho, lam, da, db = self._w, self.rho, self._l, self._da, self._db
        p00, p01, p02, p03, p04 = self._p00, self._p01, self._p02, self._p03, self._p04
        p11, p12, p13, p14 = self._p11, self._p12, self._p13, self._p14
        p22, p23, p24 = self._p22, self._p23, self._p24
        p33, p34, p44 = self._p33, self._p34, self._p44
        if weight > 0.0:
            self._coasts = 0
            self._learn_noise(e_hat, weight)
            # y = ω + ρ·A/2 − ℓ·T/2 + Im(g)·D_a + Re(g)·D_b: H = (1, h1, h2, h3, h4)
            h1, h2, h3, h4 = 0.5 * A, -0.5 * T, g.imag, g.real
            ph0 = p00 + h1 * p01 + h2 * p02 + h3 * p03 + h4 * p04
            ph1 = p01 + h1 * p11 + h2 * p12 + h3 * p13 + h4 * p14
            ph2 = p02 + h1 * p12 + h2 * p22 + h3 * p23 + h4 * p24
            ph3 = p03 + h1 * p13 + h2 * p23 + h3 * p33 + h4 * p34
            ph4 = p04 + h1 * p14 + h2 * p24 + h3 * p34 + h4 * p44
            s = (ph0 + h1 * ph1 + h2 * ph2 + h3 * ph3 + h4 * ph4
                 + max(self._r, t.r_min) / weight)
            nu = (w_mid - e_hat) - (w + h1 * rho + h2 * lam + h3 * da + h4 * db)
            if self._q_l and nu * nu > t.z_load * t.z_load * s:
                # a load step, not a random walk: ℓ's variance reopens (its prior), so
                # that the jump goes to ℓ rather than to ρ or D, and ρ is held meanwhile
                p22 += t.p_l
                ph2 += t.p_l * h2
                s += t.p_l * h2 * h2
                self._hold = t.hold
            k0, k1, k2, k3, k4 = ph0 / s, ph1 / s, ph2 / s, ph3 / s, ph4 / s
            held = self._hold > 0
            if held:  # ρ a "consider" state (Schmidt): not updated, its covariance kept
                self._hold -= 1
                k1 = 0.0
            w += k0 * nu
            rho += k1 * nu
            lam += k2 * nu
            da += k3 * nu
            db += k4 * nu
            p00 -= k0 * ph0
            p01 -= k0 * ph1
            p02 -= k0 * ph2
            p03 -= k0 * ph3
            p04 -= k0 * ph4
            if held:
                p12 -= k2 * ph1
                p13 -= k3 * ph1
                p14 -= k4 * ph1
            else:
                p11 -= k1 * ph1
                p12 -= k1 * ph2
                p13 -= k1 * ph3
                p14 -= k1 * ph4
            p22 -= k2 * ph2
            p23 -= k2 * ph3
            p24 -= k2 * ph4
            p33 -= k3 * ph3
            p34 -= k3 * ph4
            p44 -= k4 * ph4
        else:
            self._e_prev = None
        # to the interval's end: ω += ρ·A − ℓ·T  (F = I + e0·(0, A, −T, 0, 0)ᵀ)
        # (the terms of a held state are exact zeros, which leave each sum as it was)
        w += rho * A - lam * T
        p00 += (2.0 * A * p01 + A * A * p11 - 2.0 * T * (p02 + A * p12) + T * T * p22
                + t.q_w)
        p01 += A * p11 - T * p12
        p02 += A * p12 - T * p22
        p03 += A * p13 - T * p23
        p04 += A * p14 - T * p24
        self._w, self.rho, self._l, self._da, self._db = w, rho, lam, da, db
        self._p00, self._p01, self._p02, self._p03, self._p04 = p00, p01, p02, p03, p04
        self._p11, self._p12, self._p13, self._p14 = p11 + self._q_rho, p12, p13, p14
        self._p22, self._p23, self._p24 = p22 + self._q_l, p23, p24
        self._p33, self._p34, self._p44 = p33 + t.q_d, p34, p44 + t.q_d
        p11 = self._p11
        if weight > 0.0 and not self.switched and self._hold == 0:
            z = t.z_observed if self._q_l else t.z
            if abs(rho - 1.0) > z * max(p11, 0.0) ** 0.5:
                self._run += 1
                if self._run >= t.persist:
                    self.switched = self.reset = True
            else:
                self._run = 0
        if self.switched:
            lo, hi = RHO_RANGE
            self.applied = min(hi, max(lo, rho))
        if not self._q_l and p11 < t.settle * t.settle and weight > 0.0:
            # J is a constant of the machine: known this well, the filter stops (and with it
            # the exposure of the decision to biased readings, and its cost per step)
            self.frozen = self.settled = True
        return self.applied

    def watch(self, w_mid: float, e_hat: float, A: float, weight: float,
              g: complex = 0j, lost: bool = False, count: bool = True) -> bool:
        """After the filter stopped with ρ settled and the load told (I5): the filter of
        (I3) on (ω, D_a, D_b) alone, ρ held as it settled, and a test of its innovations
        against the told load (the arguments are :meth:`update`'s; ``weight`` 0: no
        reading, the prediction alone; ``lost``: an interval the controller coasted
        through, as in :meth:`coast`). An innovation beyond ``z_load`` standard deviations
        is an outlier: counted, not taken. :attr:`InertiaTuning.persist_load` of them or more
        in a row, of one sign, reject the told load where they grow — the last beyond the
        first by ``z_load`` standard deviations of a difference. A load the laws are not
        told decelerates the rotor steadily, and the model, not taking the readings, falls
        further behind each period. The method then returns True: from then on the filter
        runs again with ℓ a state, as with the load observed (ρ held as after a load step).
        A run of :attr:`InertiaTuning.max_gate` outliers that has not grown is a jump of
        the reading (a bias that the told load's own step leaves with an imperfect drive
        model): the last one is taken, with ω's variance reopened by ν². ``count`` False
        (the told load moving, or just moved): outliers are taken so, never counted."""
        t = self.tuning
        if self._watch_off:
            return False
        if lost:
            self._coasts += 1
            if self._coasts >= t.max_coast:  # the estimator's integral is not known now
                self._watch_off = True
                return False
            self._reopen_flux_error()
        w, da, db = self._w, self._da, self._db
        p00, p03, p04 = self._p00, self._p03, self._p04
        p33, p34, p44 = self._p33, self._p34, self._p44
        rejected = False
        if weight > 0.0:
            self._coasts = 0
            self._learn_noise(e_hat, weight)
            h3, h4 = g.imag, g.real  # H = (1, h3, h4) on (ω, D_a, D_b)
            ph0 = p00 + h3 * p03 + h4 * p04
            ph3 = p03 + h3 * p33 + h4 * p34
            ph4 = p04 + h3 * p34 + h4 * p44
            s = ph0 + h3 * ph3 + h4 * ph4 + max(self._r, t.r_min) / weight
            nu = (w_mid - e_hat) - (w + 0.5 * A * self.rho + h3 * da + h4 * db)
            take = True
            z2 = t.z_load * t.z_load
            if nu * nu > z2 * s:  # an outlier
                step = 1 if nu > 0.0 else -1
                run = self._run_load
                if run * step > 0:
                    run += step
                else:
                    run, self._nu_first = step, nu
                take = False
                grown = (nu - self._nu_first) * step
                if (count and abs(run) >= t.persist_load and grown > 0.0
                        and grown * grown > 2.0 * z2 * s):
                    rejected = True
                elif not count or abs(run) >= t.max_gate:
                    # a jump, not a load (or the told load moving): taken, ω's variance
                    # reopened by ν²
                    p00 += nu * nu
                    ph0 += nu * nu
                    s += nu * nu
                    run, take = 0, True
                self._run_load = run
            else:
                self._run_load = 0
            if take:
                k0, k3, k4 = ph0 / s, ph3 / s, ph4 / s
                w += k0 * nu
                da += k3 * nu
                db += k4 * nu
                p00 -= k0 * ph0
                p03 -= k0 * ph3
                p04 -= k0 * ph4
                p33 -= k3 * ph3
                p34 -= k3 * ph4
                p44 -= k4 * ph4
        else:
            self._e_prev = None
        self._w, self._da, self._db = w + self.rho * A, da, db
        self._p00, self._p03, self._p04 = p00 + t.q_w, p03, p04
        self._p33, self._p34, self._p44 = p33 + t.q_d, p34, p44 + t.q_d
        if rejected:  # the load the laws are not told becomes a state
            # the readings gated out left ω off by about the last innovation: its variance
            # reopens by ν², so that the filter takes that error as ω's, not as ℓ's
            self._p00 += nu * nu
            self.frozen = False
            self._q_l = t.q_l * self._T
            self._p22 = t.p_l
            self._p01 = self._p02 = self._p12 = self._p13 = self._p14 = 0.0
            self._p23 = self._p24 = 0.0
            self._hold = t.hold
            self._run_load = 0
        return rejected

    def stop_watch(self) -> None:
        """The watch (I5) takes no more readings: the caller knows they cannot tell a load
        the laws are not told from what follows (a lost sample at the told load's step)."""
        self._watch_off = True

    @property
    def watching(self) -> bool:
        """The watch (I5) still takes readings (not stopped by a long coast or the caller)."""
        return not self._watch_off

    def rescale_load(self, f: float) -> None:
        """ℓ → f·ℓ with its covariance: the load's deceleration against a J the laws now
        apply 1/f times the one it was read against (ℓ = T_L/J; (I6))."""
        self._l *= f
        self._p02 *= f
        self._p12 *= f
        self._p22 *= f * f
        self._p23 *= f
        self._p24 *= f

    def hold_ratio(self) -> None:
        """ρ is held through the next reading (a consider state, as after a load step): for
        a reading of a rotor no torque is asked of, whose model's torque is the sensors'
        error alone (:meth:`update` would read it as inertia)."""
        self._hold = max(self._hold, 1)

    def coast(self, A: float) -> float:
        """An interval the controller coasted through on its model (a lost sample): the
        prediction alone. The estimator's integral over a lost interval takes an unknown
        constant (the drive latched setpoints whose frame the loop does not know): after
        one, D's prior reopens to :attr:`InertiaTuning.p_d_lost`; after
        :attr:`InertiaTuning.max_coast` in a row the tracker takes no more readings and
        keeps the ρ it applies (:attr:`frozen`)."""
        applied = self.update(0.0, 0.0, A, 0.0)
        self._coasts += 1
        if self._coasts >= self.tuning.max_coast:
            self.frozen = True
        self._reopen_flux_error()
        return applied

    def _learn_noise(self, e_hat: float, weight: float) -> None:
        """A reading's part in the estimate of its noise's variance (× |ψ|²): half the
        squared difference of successive readings (the error moves slowly, the noise does
        not)."""
        e_prev = self._e_prev
        if e_prev is not None:
            self._n += 1
            gain = max(1.0 / (self._n + self.tuning.n0), 0.02)
            d = e_hat - e_prev
            self._r += gain * (0.5 * d * d * weight - self._r)
        self._e_prev = e_hat

    def _reopen_flux_error(self) -> None:
        """After a lost interval: D's prior reopens to :attr:`InertiaTuning.p_d_lost`, its
        cross terms dropped (the estimator's integral took an unknown constant)."""
        p_d = self.tuning.p_d_lost
        self._p03 = self._p04 = self._p13 = self._p14 = self._p23 = self._p24 = 0.0
        self._p34 = 0.0
        self._p33 = max(self._p33, p_d)
        self._p44 = max(self._p44, p_d)
