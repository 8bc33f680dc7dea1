"""The sampled-data controller: the laws designed for the bus's timing contract.

The plain :class:`gateway.control.controller.Controller` is a forward-Euler copy of the
continuous laws. This one is designed for what the drive does between two samples
(docs/ARCHITECTURE.md, "Sampled timing"; the derivation is docs/sampled-control.md):

* **the frame follows the drive** — over interval I_j = (t_j, t_{j+1}] the drive turns its
  frame from ε_j at the ω0 of that interval's command, so the controller's frame angle is
  ε_{j+1} = ε_j + T·ω0_j with the ω0 the drive *applies* in I_j, and the next command carries
  ε_{j+1}: the frame angle is continuous, piecewise linear;
* **every quantity is predicted for the interval it acts on** — the command computed at t_k
  acts on I_{k+d} (d = delay): ω̂ is predicted to that interval's midpoint through the
  intervals already committed (and, implicitly, through the interval's own current: the
  implicit midpoint rule, with kω pre-warped to e^{−kω·T}), the references (15) are evaluated
  at the midpoint, the load is the T_L(t_{k+d}) the dynamometer holds, and
  ω0 = ω̂ + αM·i_sq*/ψ* (15) is the midpoint frame speed;
* **the observer (16), (20) is integrated exactly over each interval** — in the frame of an
  interval the rotor-flux model (first three rows of (2)) with the applied current is
  linear time-invariant (rotor speed taken constant at its estimate), so ψ_r(τ), ∫ψ_r and
  ∫ψ_r×i have closed forms; the measured flux at the interval's end corrects the model's
  trajectory linearly;
* **the flux estimator** (24) integrates the stator flux with the average applied voltage
  and the integral of the current the drive applied (:class:`IntervalFluxEstimator`).

:class:`SampledController` is the current-fed law (15), (16), (20) (ideal or PI current-loop
drive, (d, q) or (a, b) setpoints); :class:`FullOrderSampledController` the full-order law
(25)–(27), (32) for a voltage-fed drive with (d, q) setpoints; :func:`make_controller`
picks the design named by ``ControllerConfig.discretisation``.

Interface: like :class:`~gateway.control.controller.Controller` — ``step(refs, sample) ->
Command`` once per cycle, ``coast()`` for a missed one — so the cycle code calls both the
same way. It needs the references at times other than the sample's: ``refs_at(t)`` (the
profile's ``at``) is given at construction; the controller counts its own cycles (t_k = k·T).
"""

from __future__ import annotations

import cmath
import math
from collections import deque
from collections.abc import Callable, Mapping
from dataclasses import replace
from typing import Any, NamedTuple

from dbc.modes import SetpointFrame
from gateway.control.commissioning import Commissioning
from gateway.control.controller import (
    PAPER_SIGNALS,
    TWO_PI,
    Controller,
    ControllerConfig,
    Discretisation,
    EstimatorKind,
    FluxSource,
    InertiaSource,
    Law,
    LoadSource,
    law_flux,
    paper_logged,
    untold,
    wrap_angle,
)
from gateway.control.estimator import IntervalFluxEstimator, IntervalRsAdaptiveFluxEstimator
from gateway.control.inertia_tracker import InertiaTracker, InertiaTuning
from gateway.control.interface import (
    Command,
    ControllerContext,
    DriveController,
    Sample,
    make_command,
)
from gateway.control.laws import Refs
from gateway.control.refwindow import ReferenceWindow
from gateway.reference.signals import References, with_flux


class Interval(NamedTuple):
    """What the drive applies over one interval, as the controller commanded it.

    i_dq: current setpoint in the interval's frame, A. u_dq: voltage setpoint, V.
    eps: frame angle at the interval's start, rad. w_0: frame speed, rad/s.
    i_ref0, i_ref1: full-order law: the current references (25) the command assumed at the
    interval's start and end (the current error (28) over the interval is taken against
    their linear interpolation).
    """

    i_dq: complex
    u_dq: complex
    eps: float
    w_0: float
    i_ref0: complex = 0j
    i_ref1: complex = 0j


def phi(s: complex, T: float) -> complex:
    """∫_0^T e^{sτ} dτ = (e^{sT} − 1)/s, continuous at s = 0 (series below |sT| = 1e-4)."""
    x = s * T
    if abs(x) < 1e-4:
        return T * (1.0 + x / 2.0 + x * x / 6.0)
    return (cmath.exp(x) - 1.0) / s


_PI = math.pi

#: Interval(…) with all six fields given, without NamedTuple's Python-level __new__
_new_tuple = tuple.__new__


def _same_number(x: float, y: float | None) -> bool:
    """x and y are the same float, bit for bit (two zeros only as the same object: their
    signs may differ)."""
    return x is y or (x == y and x != 0.0)


def phi_exp(s: complex, T: float) -> tuple[complex, complex]:
    """(:func:`phi` (s, T), e^{sT}): the two share the one exponential."""
    x = s * T
    e = cmath.exp(x)
    if abs(x) < 1e-4:
        return T * (1.0 + x / 2.0 + x * x / 6.0), e
    return (e - 1.0) / s, e


class SampledController:
    """The sampled-data current-fed controller (15), (16), (20) (see the module docstring);
    a :class:`gateway.control.interface.DriveController`.

    Speed (about 2.5× the plain expressions, the same numbers bit for bit): what depends
    only on the period (the pre-warped gain, the integrals of a constant current over an
    interval) is computed once, the motor's constants at each change of motor
    (:meth:`_set_motor`), the references at each instant once
    (:class:`~gateway.control.refwindow.ReferenceWindow`), each interval's exponentials once
    where several integrals use them; the model of the interval a step predicts is kept for
    the next step, which corrects the same model with the measurement (:meth:`_advance`),
    and the frame angle at t_k is the one the command for I_k carried. Every number is the
    one the plain expressions give (tests/test_fast_paths.py, tools/same_signals.py).
    """

    #: the pull of ω̂ towards the inertia filter's speed with the load observed, 1/s ((I4),
    #: docs/robustness.md §10)
    PULL_K_S = 500.0

    # slots: a step reads some forty of them; an instance dict of that size loses CPython's
    # fast attribute access (its shared keys hold 30). "__dict__": others may add their own.
    __slots__ = (
        "_J",
        "_M",
        "_R_s",
        "_T",
        "_T_hat",
        "__dict__",
        "_aM",
        "_a_int",
        "_ab",
        "_alpha",
        "_base",
        "_beta",
        "_cmd_refs",
        "_coasted_at",
        "_constant_current",
        "_d",
        "_di_prev",
        "_e_hat",
        "_exp_0",
        "_from_sample",
        "_g",
        "_gamma_1",
        "_half_T",
        "_hist",
        "_i_max2",
        "_i_prev_ab",
        "_inertia_off",
        "_int_psi",
        "_joined",
        "_joining",
        "_k",
        "_k_r",
        "_k_w",
        "_k_w_warped",
        "_kept",
        "_lag",
        "_load_at",
        "_load_filter",
        "_load_observed",
        "_load_watch",
        "_measured",
        "_mu",
        "_phi_0",
        "_psi_prev",
        "_refs",
        "_rho",
        "_rho_at",
        "_sigma",
        "_told_moved",
        "_true_flux",
        "_w_mid",
        "_w_prev",
        "_watch_stopped_at",
        "commissioning",
        "config",
        "eps_0",
        "estimator",
        "inertia",
        "motor",
        "refs_at",
        "w_hat",
    )
    signals = PAPER_SIGNALS
    #: reference instants n·T/2 a step reads, beyond 2(k − 1) … 2(k + d) + 1
    _lookahead = 0

    def __init__(
        self,
        motor,
        config: ControllerConfig,
        refs_at: Callable[[float], Refs],
        eps_0: float = 0.0,
        w_hat: float = 0.0,
    ) -> None:
        if config.law is not Law.CURRENT_FED:
            raise ValueError("SampledController implements the current-fed law only")
        self.config = config
        self.refs_at = refs_at
        T = self._T = config.sampling.period
        self._d = config.sampling.delay
        g = self._g = config.gains
        self._true_flux = config.flux is FluxSource.TRUE
        self._ab = config.sampling.setpoint_frame is SetpointFrame.AB
        self._lag = config.current_lag
        # the model of the applied current starts each interval from the measured one (a
        # current loop's rise; the full-order law's voltage drive): the drive does not hold
        # the current, the estimator's mismatch is zero at the interval's start and the
        # identification takes the interval's charge from the model
        self._from_sample = self._lag > 0.0
        # (d, q) setpoints from an ideal source: one constant term, i(τ) = I (_interval_dq)
        self._constant_current = not self._ab and self._lag == 0.0
        # J/J_true applied to (15), (16) (1: the motor file's J) and its tracker
        # (config.inertia; docs/robustness.md §9): the load known only (an untold or
        # observed one reads as inertia), and not with the R_s adaptation (its law moves
        # the flux estimate on the same mismatch the tracker reads: measured, it rejected
        # the file's J on the nominal motor and at zero speed), nor without the standstill
        # identification (R_s +10 %: J read 28–75 % high, and the run stopped)
        self._rho = 1.0
        self._rho_at: int | None = None  # the sample the tracker's ρ̂ was first applied
        self._inertia_off = (
            None if config.inertia is not InertiaSource.TRACKED
            else "the load is not told" if config.load is LoadSource.UNTOLD
            else "the R_s adaptation moves the flux it reads"
            if config.estimator is EstimatorKind.RS_ADAPTIVE
            else "no standstill identification: the flux it reads carries the motor file's "
                 "R_s error" if not config.identify and not self._true_flux else None)
        # the load observed (docs/robustness.md §10): ℓ = T_L/J a state of the same filter,
        # T̂_L = ℓ̂·J in (15), (16) in place of the profile's, ω̂ pulled towards its speed
        self._load_observed = config.load is LoadSource.OBSERVED  # (not with rs-adaptive)
        track_j = config.inertia is InertiaSource.TRACKED and self._inertia_off is None
        tuning = InertiaTuning(k_s=self.PULL_K_S)
        self.inertia = (InertiaTracker(tuning, T=T, load=self._load_observed, inertia=track_j)
                        if track_j or self._load_observed else None)
        # and where J is tracked too, the load the laws get is a second filter's, on the
        # same readings with the J they apply (ρ held at 1 there, (I6)): the first one's ρ̂,
        # which a load's steps and ramps leave uncertain, is its test of J alone
        self._load_filter = (InertiaTracker(tuning, T=T, load=True, inertia=False)
                             if track_j and self._load_observed else None)
        # the load told: once J is settled the filter watches the readings against it, and
        # observes the load from the reading that rejects it on ((I5), §10); on a drive that
        # holds the current only (the ideal source): on a PI current loop the load
        # observed (I4) it would hand over to is not robust (the untold-load plant stops
        # with it), and a sensor's gain error makes the speed ripple by up to 3 rad/s,
        # which the watch took for a load
        self._load_watch = (track_j and config.load is LoadSource.KNOWN
                            and not self._from_sample)
        self._load_at: int | None = None  # the sample the told load was rejected at
        self._told_moved = -(1 << 30)  # the last sample whose interval the told load moved in
        self._watch_stopped_at: int | None = None  # the sample (I5) stopped at (lost sample)
        self._coasted_at = -(1 << 29)  # the last sample whose interval was lost (coasted)
        self._T_hat = 0.0  # T̂_L, N·m (the load observed; else 0)
        self._w_mid = 0.0  # ω̂ at the midpoint of the interval the last _advance modelled
        self._a_int = 0.0  # and its mechanical copy's ∫dω̂/dt (without (20))
        self._e_hat = 0.0  # and the measured flux's reading of its error, (I1)
        self._int_psi = 0j  # and the model's ∫ψ dτ over it
        self._measured = False  # the last step's flux was measured (not a coast's model)
        self._set_motor(motor)
        # what depends on the period and the gains only
        self._half_T = 0.5 * T
        self._phi_0 = phi(0j, T)  # ∫_0^T e^{0·τ} dτ
        self._exp_0 = cmath.exp(0j * T)  # e^{0·T}
        self._k_w_warped = 2.0 / T * math.tanh(0.5 * g.k_w * T)  # kω pre-warped (_midpoint)
        self._k_w = g.k_w  # kω of (25) (the full-order law bounds kω·T)
        self._gamma_1 = g.gamma_1
        self._i_max2 = g.i_max * g.i_max
        self._refs = ReferenceWindow(refs_at, T, 2 * self._d + 4 + self._lookahead)
        # where the commanded interval I_{k+d}'s references sit in the window: its start,
        # midpoint (and end: the full-order law)
        self._cmd_refs = slice(2 * self._d + 2, 2 * self._d + 4 + self._lookahead)
        if config.estimator is EstimatorKind.RS_ADAPTIVE:  # docs/robustness.md
            self.estimator: IntervalFluxEstimator = IntervalRsAdaptiveFluxEstimator(motor)
        else:
            self.estimator = IntervalFluxEstimator(
                motor, config.w_c if config.estimator is EstimatorKind.DRIFT_FREE else 0.0)
        self._k = 0  # samples taken (t_k = k·T)
        self.eps_0 = wrap_angle(eps_0)
        self.w_hat = w_hat  # ω̂ at t_k
        zero = Interval(0j, 0j, self.eps_0, 0.0)
        # The decided commands for I_{k−1}, I_k, …, I_{k+d−1} at the start of step k (the
        # drive holds zero setpoints until the first command arrives; the frame is kept
        # continuous from the start).
        self._hist: deque[Interval] = deque([zero] * (self._d + 1))
        self._psi_prev: complex | None = None  # ψ_r at t_{k−1}, frame of I_{k−1}
        self._w_prev = w_hat  # ω̂ at t_{k−1}
        self._i_prev_ab = 0j  # measured current at t_{k−1}
        self._di_prev = 0j  # measured − modelled current at t_{k−1}, frame at t_{k−1}
        #: cycles coasted since the last step: the frame the drive held has drifted from
        #: the flux (the next command's frame is set on the flux again: step)
        self._coasted = False
        #: the command whose frame was set on the flux, until the step whose past interval
        #: ends where it starts (that interval's end is measured in its own frame)
        self._turned: Interval | None = None
        #: the command before the last step's (what the drive holds if that one is withheld)
        self._base: Interval | None = None
        self._joining = False  # the identification is applied at this step (_join)
        self._joined = False  # the flux references are the joined ones
        # the sensors in the fit where the model of the current within the period is the
        # drive's (the ideal source; the voltage drive, whose charge the fit takes from the
        # model: _commission), not on the PI current loop, modelled as a first-order rise:
        # there a dead time left by a motor file's correction read as a 6 mA offset
        self.commissioning = (Commissioning(motor, self._T, sensors=self._lag == 0.0)
                              if config.identify else None)

    def _commission(self, refs: Refs, sample: Sample, psi_hat_ab: complex,
                    i_model: complex | None = None) -> complex:
        """The standstill identification (``config.identify``): the flux the laws take
        (:meth:`Commissioning.apply`: the current model's while it is pending, the
        identified voltage model's at the sample that ends it), and from that sample the
        identified R_s and R_r. ``i_model``: the model's current at the sample, where the
        drive holds the current (the mismatch's noise: :attr:`Commissioning.NOISE_RMS`)."""
        c = self.commissioning
        if c is None:
            return psi_hat_ab
        # the charge of the past interval where the drive does not hold its current: the
        # estimator's (the model's ∫i with the trapezoid of the measured mismatch)
        charge = self.estimator.charge if self._from_sample else None
        ident, psi = c.apply(refs, sample.i_s_ab, sample.u_s_ab, self.estimator, psi_hat_ab,
                             charge, i_model)
        if ident is not None:
            self._set_motor(replace(self.motor, R_s=ident.R_s, R_r=ident.R_r, M=ident.M,
                                    L_s=ident.L_s, L_r=ident.L_r))
            self._joining = True  # the flux references join the motor's (_join)
            if self.inertia is not None and not math.isnan(ident.mismatch_rms):
                # the reading (I1) of the inertia filter: the flux's noise σ·(L_r/M)·n at
                # two samples over ∫ψ ≈ |ψ|·T, n the sensors' noise per axis (rms/√2)
                noise = self._sigma / self._k_r * ident.mismatch_rms / self._T
                self.inertia.expect_noise(noise * noise)
        assert psi is not None
        return psi

    def _end_frame(self, prev: Interval) -> complex:
        """e^{−jε} of the frame ``prev`` ends in, for the step whose next interval is the
        command :meth:`_on_flux` turned (the two frames differ by the turn): from then on
        the frames are continuous again."""
        self._turned = None
        return cmath.exp(-1j * wrap_angle(prev.eps + self._T * prev.w_0))

    @staticmethod
    def _on_flux(eps_app: float, psi: complex) -> tuple[float, complex, float]:
        """The first command after cycles without a sample: its frame ``eps_app`` turned
        onto the flux ``psi`` predicted for its start (docs/sampled-control.md, "Cycles
        without a sample"): (the frame, the flux in it, the turn)."""
        turn = cmath.phase(psi)
        return wrap_angle(eps_app + turn), complex(abs(psi), 0.0), turn

    def summary(self) -> dict[str, object] | None:
        """For summary.json's ``identification``: the standstill identification's result
        (``--identify``) and, under ``inertia``, what the inertia tracker found (J applied,
        the motor file's, ρ̂ = J_file/J with its standard deviation, and the time it was
        applied, None while the file's J stands)."""
        found = None if self.commissioning is None else dict(self.commissioning.describe())
        tracker = self.inertia
        if tracker is not None:
            found = found if found is not None else {}
            found["inertia"] = {
                "J": self._J, "J_file": self.motor.J, "applied": tracker.switched,
                "ratio": tracker.rho, "ratio_std": tracker.rho_std,
                "at": None if self._rho_at is None else self._rho_at * self._T,
                "settled": tracker.settled, "stopped": tracker.frozen and not tracker.settled}
            if self._load_observed:
                found["inertia"]["T_L_observed"] = self._T_hat
            if self._load_at is not None:
                found["inertia"]["load_rejected_at"] = self._load_at * self._T
            if self._watch_stopped_at is not None:
                found["inertia"]["load_watch_stopped_at"] = self._watch_stopped_at * self._T
        elif self._inertia_off is not None:
            found = found if found is not None else {}
            found["inertia"] = {"J": self._J, "J_file": self.motor.J, "applied": False,
                                "reason": f"not tracked: {self._inertia_off}"}
        return found

    def _join(self, e: float, k: int) -> None:
        """At the sample t_k that applies the standstill identification: the flux
        references the laws take from now on start from the flux the motor has, ψ* + e
        (``e`` the d-axis flux of the identified model less ψ*, Wb), and join the
        profile's at the rotor's own rate α̂ (docs/robustness.md §5):

            ψ*_j(t) = ψ*(t) + e·e^{−α̂(t − t_k)}, with its two derivatives.

        i_sd* of (9)/(15), ψ*_j/M + ψ̇*_j/(α̂M), is the profile's own: the motor's flux
        rises as it would; what changes is that (15), (16), (20) and the voltage
        feed-forward take the flux the motor has (a magnetisation with a wrong α leaves it
        off by 8 % with R_r +20 %, decaying with the rotor time constant over the
        profile's first speed step)."""
        self._joining = False
        if e == 0.0:
            return
        self._joined = True
        t_k, a = k * self._T, self._alpha
        refs_at = self.refs_at

        def joined(t: float) -> Refs:
            r = refs_at(t)
            x = e * math.exp(-a * (t - t_k)) if t >= t_k else e
            if type(r) is References:
                return with_flux(r, r.psi_ref + x, r.dpsi_ref - a * x, r.ddpsi_ref + a * a * x)
            return replace(r, psi_ref=r.psi_ref + x, dpsi_ref=r.dpsi_ref - a * x,
                           ddpsi_ref=r.ddpsi_ref + a * a * x)

        self._refs = ReferenceWindow(joined, self._T, self._refs._size)

    def _set_motor(self, motor) -> None:
        """The controller's motor from now on, and its constants (model (2)'s α, μ, σ, β,
        the products αM and β·σ = M/L_r), read once here instead of at every use."""
        self.motor = motor
        self._alpha = motor.alpha
        self._M = motor.M
        self._scale_inertia()
        self._R_s = motor.R_s
        self._sigma = motor.sigma
        self._beta = motor.beta
        self._aM = motor.alpha * motor.M
        self._k_r = motor.beta * motor.sigma  # M/L_r
        self._kept: tuple | None = None  # a model of the old motor: not for the next step

    def _scale_inertia(self) -> None:
        """J and μ of the laws with the applied ρ = J_file/J (1: the motor file's)."""
        self._J = self.motor.J / self._rho
        self._mu = self.motor.mu * self._rho

    def _track_inertia(self, psi_k: complex | None, eps_k: float = 0.0,
                       lost: bool = False) -> float | None:
        """The inertia tracker's step over the interval just ended (``psi_k``: the measured
        flux at its end in the frame of ``eps_k``, None where it is not a measurement of that
        interval; the model's ∫dω̂/dt over it is :attr:`_a_int`, with the applied J and the
        observed load :attr:`_T_hat`): applies its ρ and returns the speed ω̂ takes where the
        tracker has just rejected the file's J (else None). ``lost``: the controller coasted
        through the interval (a lost sample)."""
        tracker = self.inertia
        assert tracker is not None
        if tracker.frozen:  # a long coast, or ρ settled: nothing more to learn
            if self._load_watch and tracker.settled:  # but the told load is watched (I5)
                self._watch_load(psi_k, eps_k, lost)
            return None
        # the filter's model takes the told load only: A without the observed one
        T_hat = self._T_hat
        A = self._a_int + self._T * T_hat / self._J if T_hat else self._a_int
        rho_applied = self._rho
        lf = self._load_filter  # (I6): the same reading, A with the applied J
        if lf is not None and lf.frozen:
            lf = None
        if lost:
            if lf is not None:
                lf.coast(A)
            rho = tracker.coast(A / rho_applied)
        elif psi_k is None:
            if lf is not None:
                lf.update(0.0, 0.0, A, 0.0)
            rho = tracker.update(0.0, 0.0, A / rho_applied, 0.0)
        else:
            weight = psi_k.real * psi_k.real + psi_k.imag * psi_k.imag
            g = self._flux_error_gain(eps_k)
            if lf is not None:
                lf.update(self._w_mid, self._e_hat, A, weight, g)
            rho = tracker.update(self._w_mid, self._e_hat, A / rho_applied, weight, g)
            if tracker.reset:
                self._rho_at = self._k
        if rho != rho_applied:
            self._rho = rho
            self._scale_inertia()
            if self._load_filter is not None:  # its ℓ, T̂_L/J, against the applied J
                self._load_filter.rescale_load(rho / rho_applied)
        if tracker.reset:
            tracker.reset = False
            return tracker.speed
        return None

    def _flux_error_gain(self, eps_k: float) -> complex:
        """g of (I3) for the interval just read: a flux error D constant in (a, b),
        D·e^{−jε_k} in the frame, left by the model's own rotation over the interval, adds
        Im(g·D) to the reading (rad/s per Wb; 0 without the model's ∫ψ)."""
        int_psi = self._int_psi
        return (cmath.exp(-1j * eps_k) * (1.0 - cmath.exp(complex(-self._alpha, self._w_mid)
                                                          * self._T)) / int_psi
                if int_psi else 0j)

    def _note_told_move(self, win: list[Refs], k: int) -> None:
        """With (I5) watching: the told load moves over the interval ``win`` spans (its
        value at the ends differs, or it ramps at the midpoint): sample ``k`` is the last
        such."""
        if self._load_watch and (win[0].T_L != win[2].T_L or win[1].dT_L):
            self._told_moved = k

    def _watch_load(self, psi_k: complex | None, eps_k: float, lost: bool) -> None:
        """(I5): the settled filter's speed against the readings; where they reject the
        told load, the load the laws are not told is observed from the next sample on (T̂_L
        = ℓ̂·J added to the profile's in (15), (16), as with ``--load observed``)."""
        tracker = self.inertia
        A = self._a_int / self._rho
        if lost:
            self._coasted_at = self._k
        if (abs(self._told_moved - self._coasted_at) * self._T <= tracker.tuning.settle_told
                and tracker.watching):
            # A sample lost while the told load moved, or just before or after: the drive's
            # response to the step was never read, and the loop's transient after the coast
            # (at 5 ms it rang ±1.9 rad/s in (I1) for over 0.3 s: the emulated drive holds
            # the load sent with its setpoints, the model takes the profile's; see
            # docs/robustness.md §10) is, to the test, a load the laws are not told: the
            # told load was rejected and the run lost its precision (0.9 rad/s RMS). The
            # watch stops; the told load stands.
            tracker.stop_watch()
            self._watch_stopped_at = self._k
            return
        if lost or psi_k is None:
            tracker.watch(0.0, 0.0, A, 0.0, lost=lost)
            return
        g = self._flux_error_gain(eps_k)
        # the told load moving (or within settle_told of it): the drive's response to it
        # is not the model's to the period (a current loop's lag, a load applied within the
        # period): outliers then are not counted
        count = (self._k - self._told_moved) * self._T > tracker.tuning.settle_told
        if tracker.watch(self._w_mid, self._e_hat, A,
                         psi_k.real * psi_k.real + psi_k.imag * psi_k.imag, g, count=count):
            self._load_observed = True
            self._load_at = self._k

    # ------------------------------------------------------------------ the model

    def _terms(self, c: Interval, i0_ab: complex) -> list[tuple[complex, complex]]:
        """The applied current over interval ``c`` in its turning frame, Σ I_n·e^{s_n·τ}.

        (d, q) setpoints are constant in the frame; (a, b) setpoints are held, so in the frame
        they turn back, I·e^{−jω0τ}. A current loop (``current_lag`` τc > 0) reaches the
        setpoint from the current at the interval's start i0 as e^{−τ/τc}.
        """
        T = self._T
        if self._ab:
            i_ab = c.i_dq * cmath.exp(0.5j * c.w_0 * T)  # the held vector, frame at τ = 0
            terms = [(i_ab, complex(0.0, -c.w_0))]
        else:
            i_ab = c.i_dq
            terms = [(c.i_dq, 0j)]
        if self._lag > 0.0:
            s_ref = terms[0][1]
            delta = i0_ab * cmath.exp(-1j * c.eps) - i_ab
            terms.append((delta, s_ref - 1.0 / self._lag))
        return terms

    def _interval(self, c: Interval, psi0: complex, w_m: float,
                  terms: list[tuple[complex, complex]]
                  ) -> tuple[complex, complex, complex]:
        """The rotor-flux model over one interval, in its turning frame, from ψ0.

        With the rotor speed constant at w_m the first three rows of (2) are linear
        time-invariant in the frame: dψ/dτ = −a·ψ + αM·i(τ), a = α + j(ω0 − ω). For
        i(τ) = Σ I_n·e^{s_n·τ}: ψ(τ) = Σ P_n·e^{s_n·τ} + C·e^{−aτ}, P_n = αM·I_n/(a + s_n),
        C = ψ0 − Σ P_n. Returns (ψ(T), ∫ψ dτ, ∫conj(ψ)·i dτ).
        """
        T = self._T
        aM = self._aM
        a = complex(self._alpha, c.w_0 - w_m)
        ps = [(aM * big_i / (a + s_n), s_n) for big_i, s_n in terms]
        coef = psi0 - sum(p for p, _ in ps)
        phi_a, e_a = phi_exp(-a, T)
        psi_end = coef * e_a
        int_psi = coef * phi_a
        int_ci = 0j
        a_c = a.conjugate()
        for p, s_p in ps:
            phi_p, e_p = phi_exp(s_p, T)
            psi_end += p * e_p
            int_psi += p * phi_p
        for big_i, s_n in terms:
            int_ci += coef.conjugate() * big_i * phi(s_n - a_c, T)
            for p, s_p in ps:
                int_ci += p.conjugate() * big_i * phi(s_p.conjugate() + s_n, T)
        return psi_end, int_psi, int_ci

    def _interval_dq(self, i_dq: complex, w_0: float, psi0: complex, w_m: float
                     ) -> tuple[complex, complex, complex]:
        """:meth:`_interval` for a (d, q) setpoint from an ideal source: the one term
        i(τ) = I (s = 0), whose e^{0·T} and ∫e^{0·τ}dτ are the period's constants; the same
        operations in the same order, so the same numbers."""
        T = self._T
        a = complex(self._alpha, w_0 - w_m)
        p = self._aM * i_dq / (a + 0j)  # P = αM·I/(a + s), s = 0
        coef = psi0 - (0j + p)  # C = ψ0 − ΣP (sum() starts from 0)
        s = -a  # phi(−a, T) (inline), sharing e^{−aT}
        x = s * T
        e_a = cmath.exp(x)
        phi_a = T * (1.0 + x / 2.0 + x * x / 6.0) if abs(x) < 1e-4 else (e_a - 1.0) / s
        s = 0j - a.conjugate()  # phi(s − ā, T), s = 0 (inline)
        x = s * T
        phi_c = (T * (1.0 + x / 2.0 + x * x / 6.0) if abs(x) < 1e-4
                 else (cmath.exp(x) - 1.0) / s)
        psi_end = coef * e_a + p * self._exp_0
        int_psi = coef * phi_a + p * self._phi_0
        int_ci = 0j + coef.conjugate() * i_dq * phi_c + p.conjugate() * i_dq * self._phi_0
        return psi_end, int_psi, int_ci

    def _current(self, c: Interval, terms: list[tuple[complex, complex]]
                 ) -> tuple[complex, complex]:
        """(∫i_ab dt over the interval, i_ab at its end) of the applied current."""
        T = self._T
        rot0 = cmath.exp(1j * c.eps)
        jw = 1j * c.w_0
        int_i = 0j
        i_end = 0j
        for big_i, s_n in terms:
            int_i += big_i * phi(s_n + jw, T)
            i_end += big_i * cmath.exp(s_n * T)
        return rot0 * int_i, rot0 * cmath.exp(jw * T) * i_end

    def _current_dq(self, c: Interval) -> tuple[complex, complex]:
        """:meth:`_current` for a (d, q) setpoint from an ideal source (one term, s = 0).
        e^{jω0T} is taken from ∫e^{jω0τ}dτ's exponential: their arguments differ at most in
        the sign of a zero real part, which e^x does not see."""
        T = self._T
        rot0 = cmath.exp(1j * c.eps)
        s = 0j + 1j * c.w_0  # phi(s + jω0, T), s = 0 (inline)
        x = s * T
        e_w = cmath.exp(x)
        phi_w = T * (1.0 + x / 2.0 + x * x / 6.0) if abs(x) < 1e-4 else (e_w - 1.0) / s
        int_i = 0j + c.i_dq * phi_w
        i_end = 0j + c.i_dq * self._exp_0
        return rot0 * int_i, rot0 * e_w * i_end

    def _rate(self, psi: complex, i_dq: complex, r: Refs, T_L: float) -> float:
        """dω̂/dt of (16), (20) at one instant with the load T_L."""
        return (self._mu * (psi.real * i_dq.imag - psi.imag * i_dq.real) - T_L / self._J
                + r.psi_ref * psi.imag / self._gamma_1)

    def _advance(self, c: Interval, psi0: complex, w0: float, r_mid: Refs, T_L: float,
                 terms: list[tuple[complex, complex]] | None,
                 psi_end_meas: complex | None = None, di: complex = 0j, keep: bool = False,
                 adapt: bool = True) -> tuple[complex, float]:
        """ψ_r (frame at the end) and ω̂ at the end of interval ``c``, whose midpoint's
        references are ``r_mid`` and whose load (the one the timing contract applies over
        the interval: T_L at its start, held, docs/ARCHITECTURE.md) is ``T_L``.

        The rotor-flux model (:meth:`_interval`) runs at the speed of the interval's
        midpoint; ω̂ integrates (16), (20) over the interval exactly for the model:
        μ∫(ψ_rd i_sq − ψ_rq i_sd) − ∫T_L/J + ψ*∫ψ_rq/γ1, ψ* at the midpoint. With the
        measured flux at the end, the model's trajectory is corrected linearly, δ·τ/T;
        ``di`` is the mean difference between the measured and the modelled current over
        the interval (a drive that could not follow: voltage limit), added to the torque
        integral. ``terms``: the applied current (:meth:`_terms`); None for a constant
        (d, q) one (:meth:`_interval_dq`).

        Step k predicts I_k from (ψ_k, ω̂_k) (``keep``); step k + 1 models the same interval
        from the same start with the same references before it corrects the model with the
        measured end: it takes the prediction, kept in ``_kept`` (cleared when the motor
        changes).
        """
        kept = self._kept
        if adapt and kept is not None and kept[0] is c and kept[1] is psi0 and kept[2] is w0:
            psi_end, int_psi, int_ci = kept[3]
            self._w_mid = kept[4]
        else:
            i = c.i_dq  # the speed at the midpoint, with dω̂/dt of (16), (20) (_rate, inline)
            v = r_mid.psi_ref * psi0.imag / self._gamma_1 if adapt else 0.0
            w_m = w0 + self._half_T * (self._mu * (psi0.real * i.imag - psi0.imag * i.real)
                                       - T_L / self._J + v)
            model = (self._interval_dq(i, c.w_0, psi0, w_m) if terms is None
                     else self._interval(c, psi0, w_m, terms))
            if keep:
                self._kept = (c, psi0, w0, model, w_m)
            self._w_mid = w_m
            psi_end, int_psi, int_ci = model
        if psi_end_meas is not None:
            delta = psi_end_meas - psi_end
            if (self.inertia is not None and int_psi
                    and (not self.inertia.frozen or self._load_watch)):
                # (I1): the measured flux turned from the model's by −j(ω̂_m − ω)∫ψ
                self._e_hat = -(delta / int_psi).imag
                self._int_psi = int_psi
            int_psi += self._half_T * delta
            int_ci += self._half_T * delta.conjugate() * (c.i_dq if terms is None
                                                          else terms[0][0])
            psi_end = psi_end_meas
        if di:
            int_ci += int_psi.conjugate() * di
        w_end = self._mu * int_ci.imag - self._T * T_L / self._J
        self._a_int = w_end
        if adapt:
            w_end += r_mid.psi_ref * int_psi.imag / self._gamma_1
        return psi_end, w0 + w_end

    # ------------------------------------------------------------------ a cycle

    def step(self, refs: Refs, sample: Sample) -> Command:
        """One sample at t_k: ω̂ over I_{k−1} with the measured flux, predict to I_{k+d},
        command it."""
        T = self._T
        d = self._d
        self._k += 1
        k = self._k
        win = self._refs.starting(2 * k - 2)  # references at (2(k − 1) + i)·T/2: win[i]
        hist = self._hist
        prev = hist[0]  # I_{k−1}, ended at t_k
        # the drive's frame at t_k: ε_{k−1} + T·ω0, the angle the command for I_k carried
        eps_k = hist[1].eps if k > d > 0 else wrap_angle(prev.eps + T * prev.w_0)
        # flux at t_k: the stator flux integrated over I_{k−1} with the applied current
        constant = self._constant_current
        if constant:
            terms = None
            int_i_ab, i_end_ab = self._current_dq(prev)
        else:
            terms = self._terms(prev, self._i_prev_ab)
            int_i_ab, i_end_ab = self._current(prev, terms)
        psi_ab = self.estimator.update(sample.i_s_ab, sample.u_s_ab, T, int_i_ab, i_end_ab,
                                       eps_k, win[2].psi_ref if self._joined else refs.psi_ref,
                                       self._from_sample)
        if self.commissioning is not None:
            psi_ab = self._commission(refs, sample, psi_ab,
                                      None if self._from_sample else i_end_ab)
        if self._true_flux:
            psi_ab = law_flux(True, sample, psi_ab)
        to_k = cmath.exp(-1j * eps_k)
        psi_k = psi_ab * to_k
        # the flux at t_k measures I_{k−1} (the inertia tracker): not at the sample that
        # switches from the standstill's current model to the voltage model, nor while the
        # current model holds the frame, nor from a coast's modelled start
        measured = (self._measured and not self._joining
                    and (self.commissioning is None or not self.commissioning.pending))
        if self._joining:
            self._join(psi_k.real - refs.psi_ref, k)
        # ω̂ at t_k: (16), (20) integrated over I_{k−1}, model corrected by the measured end
        psi0 = self._psi_prev
        if psi0 is None:
            psi0 = psi_k * cmath.exp(1j * prev.w_0 * T)
        di_k = (sample.i_s_ab - i_end_ab) * to_k
        if self._turned is not None and hist[1] is self._turned:
            # the frame was set on the flux at I_k's start: I_{k−1} ends in its own frame
            to_end = self._end_frame(prev)
            psi_end, di_end = psi_ab * to_end, (sample.i_s_ab - i_end_ab) * to_end
            measured = False
        else:
            psi_end, di_end = psi_k, di_k
        di = 0.5 * (self._di_prev + di_end)
        self._di_prev = di_k
        T_hat = self._T_hat  # the load observed: the laws' T_L over I_{k−1}
        self._note_told_move(win, k)  # (I5) does not count these readings
        _, w_k = self._advance(prev, psi0, self._w_prev, win[1], win[0].T_L + T_hat, terms,
                               psi_end, di, False)
        if self.inertia is not None:
            w_reset = self._track_inertia(psi_k if measured else None, eps_k)
            if w_reset is not None:
                w_k = w_reset
            if self._load_observed and measured and not self.inertia.frozen:  # (I4)
                tracker = self._load_filter or self.inertia
                T_hat = self._T_hat = tracker.load * self._J
                w_k += min(tracker.tuning.k_s * T, 1.0) * (tracker.speed - w_k)
        self._measured = True
        self.w_hat = w_k
        # predict through the committed intervals I_k … I_{k+d−1}
        psi, w, i0 = psi_k, w_k, sample.i_s_ab
        for j in range(1, d + 1):
            c = hist[j]
            terms = None if constant else self._terms(c, i0)
            psi, w = self._advance(c, psi, w, win[2 * j + 1], win[2 * j].T_L + T_hat, terms,
                                   None, 0j, j == 1)
            if self._lag > 0.0:
                i0 = self._current(c, terms)[1]
        last = hist[-1]
        eps_app = wrap_angle(last.eps + T * last.w_0) if d else eps_k
        turned = False
        if self._coasted:
            # After cycles without a sample the frame the drive held at its ω0 has drifted
            # from the flux (the rotor's speed changed meanwhile): the frame of (15) is the
            # controller's own reference, and the command for I_{k+d} sets it on the flux
            # predicted for that interval's start, so that (20) does not read the drift as a
            # speed error (docs/sampled-control.md, "Cycles without a sample").
            self._coasted = False
            if d:
                eps_app, psi, _ = self._on_flux(eps_app, psi)
                turned = True
        # the command for I_{k+d}: references and ω̂ at its midpoint
        r0, r = win[self._cmd_refs]
        T_L = r0.T_L + T_hat  # the load the drive will apply (and the one observed)
        w_mid, i_sd, i_sq, limited = self._midpoint(psi, w, r, T_L)
        w_0 = w_mid + self._aM * i_sq / r.psi_ref  # (15) at the midpoint
        R_s, sigma, k_r = self._R_s, self._sigma, self._k_r
        u_sd = R_s * i_sd + k_r * r.dpsi_ref - w_0 * sigma * i_sq
        u_sq = R_s * i_sq + w_0 * (sigma * i_sd + k_r * r.psi_ref)
        i_dq = complex(i_sd, i_sq)
        u_dq = complex(u_sd, u_sq)
        self._base = last
        hist.append(_new_tuple(Interval, (i_dq, u_dq, eps_app, w_0, 0j, 0j)))
        hist.popleft()
        if turned:
            self._turned = hist[-1]
        self._psi_prev = psi_k
        self._w_prev = w_k
        self._i_prev_ab = sample.i_s_ab
        self.eps_0 = eps_k
        to_ab = cmath.exp(1j * (eps_app + self._half_T * w_0))
        return make_command(i_dq, u_dq, eps_app, w_0, i_dq * to_ab, u_dq * to_ab, limited,
                            paper_logged(w_k, psi_k))

    def _midpoint(self, psi: complex, w: float, r: Refs, T_L: float
                  ) -> tuple[float, float, float, bool]:
        """ω̂ at the midpoint of the commanded interval and the currents (15) for it.

        The interval's current acts on ω̂ itself, so the midpoint estimate is implicit:
        s = ω̂_mid − ω*_mid solves s = ω̂0 − ω*_mid + (T/2)·(c0 − c1·sat(s)) (Newton; the
        right-hand side is (16), (20) with i_sq* of (15), c1 = k′·ψ_rd/ψ*). That is the
        implicit midpoint rule for the speed-error dynamics ṡ = −kω·sat(s): stable for any
        kω·T. The gain is pre-warped, k′ = (2/T)·tanh(kω·T/2), so that in the linear range the
        error decays by e^{−kω·T} per period like the continuous loop (k′ → kω as T → 0).
        Returns (ω̂_mid, i_sd*, i_sq*, limited).
        """
        half_T = self._half_T
        psi_ref = r.psi_ref
        i_sd = psi_ref / self._M + r.dpsi_ref / self._aM
        k_w = self._k_w_warped
        load = T_L / self._J
        ff = load + r.dw_ref
        c1 = k_w * psi.real / psi_ref
        c0 = (psi.real * ff / psi_ref - self._mu * psi.imag * i_sd - load
              + psi_ref * psi.imag / self._gamma_1)
        b = w - r.w_ref + half_T * c0
        h = half_T * c1
        x = b / (1.0 + h) if h > -1.0 else b
        tanh = math.tanh  # four Newton steps on x + h·sat(x) − b = 0 (monotone for h > −1)
        th = tanh(x)
        x -= (x + h * th - b) / (1.0 + h * (1.0 - th * th))
        th = tanh(x)
        x -= (x + h * th - b) / (1.0 + h * (1.0 - th * th))
        th = tanh(x)
        x -= (x + h * th - b) / (1.0 + h * (1.0 - th * th))
        th = tanh(x)
        x -= (x + h * th - b) / (1.0 + h * (1.0 - th * th))
        i_sq = (-k_w * tanh(x) + ff) / (self._mu * psi_ref)
        q2 = self._i_max2 - i_sd * i_sd
        q_max = math.sqrt(q2) if q2 > 0.0 else 0.0
        limited = abs(i_sq) > q_max
        if limited:
            i_sq = math.copysign(q_max, i_sq)
            w_mid = w + half_T * self._rate(psi, complex(i_sd, i_sq), r, T_L)
        else:
            w_mid = r.w_ref + x
        return w_mid, i_sd, i_sq, limited

    def _currents(self, r: Refs, w_hat: float, T_L: float) -> tuple[float, float, bool]:
        """i_sd*, i_sq* of (15) with the current limit (as :mod:`gateway.control.laws`)."""
        psi_ref = r.psi_ref
        s = math.tanh(w_hat - r.w_ref)  # sat = tanh (laws.sat_tanh, §E7)
        i_sd = psi_ref / self._M + r.dpsi_ref / self._aM
        i_sq = (-self._k_w * s + T_L / self._J + r.dw_ref) / (self._mu * psi_ref)
        q2 = self._i_max2 - i_sd * i_sd
        q_max = math.sqrt(q2) if q2 > 0.0 else 0.0
        limited = abs(i_sq) > q_max
        if limited:
            i_sq = math.copysign(q_max, i_sq)
        return i_sd, i_sq, limited

    def _held(self, c: Interval) -> Interval:
        """The interval after ``c`` when no new command arrives: the drive holds ``c``'s
        setpoints and keeps turning their frame at its ω0 (full-order law: the current
        reference held at the one ``c`` ended with)."""
        return c._replace(eps=wrap_angle(c.eps + self._T * c.w_0), i_ref0=c.i_ref1)

    def withhold(self) -> None:
        """The command of the last :meth:`step` was not sent (it was ready only after the
        SYNC it was for: a late RPDO would be applied one period late, with a frame angle
        one period old). The drive holds the previous command instead, turning on, and the
        model of what it applies says so. Call once, right after the step."""
        if self._base is None:
            raise RuntimeError("withhold() follows a step(), once")
        if self._hist[-1] is self._turned:  # the frame set on the flux is not sent: again
            self._turned = None
            self._coasted = True
        self._hist[-1] = self._held(self._base)
        self._base = None

    def delayed(self, n: int) -> None:
        """The SYNC producer skipped ``n`` slots after the last step's sample: the drive,
        latching nothing without a SYNC, held its previous command through them (turning
        on) and latches this step's at the SYNC after them, as sent (its frame angle ``n``
        periods old). The model says so: the command withheld, ``n`` cycles coasted on the
        held one, and the interval after them this command. The controller's frame stays
        where it is (ε0 is its estimate of the flux angle, which the drive's late frame does
        not move): that interval is the command's current and voltage turned back by the
        angle the drive's frame lags, ``n``·T·ω0, in the frame of the held setpoints. Call
        once, right after the step, instead of ``n`` coasts."""
        if self._base is None:
            raise RuntimeError("delayed() follows a step(), once")
        sent = self._hist[-1]
        self.withhold()
        for _ in range(n):
            self.coast()
        frame = self._hist[-1]  # held (the full-order law: its current reference too)
        back = cmath.exp(1j * (sent.eps - frame.eps))
        self._hist[-1] = frame._replace(i_dq=sent.i_dq * back, u_dq=sent.u_dq * back,
                                        w_0=sent.w_0)

    def coast(self) -> None:
        """A cycle without measurements: the drive keeps the last setpoints, turning on.

        ω̂ and the rotor flux are carried over I_{k−1} by the model alone; the flux
        estimator takes the model's stator flux at t_k (that interval's voltage is never
        reported).
        """
        T = self._T
        self._k += 1
        if self.commissioning is not None:
            self.commissioning.gap()
        win = self._refs.starting(2 * self._k - 2)
        hist = self._hist
        prev = hist[0]
        psi0 = self._psi_prev if self._psi_prev is not None else 0j
        if self._constant_current:
            psi_k, w_k = self._advance(prev, psi0, self._w_prev, win[1],
                                       win[0].T_L + self._T_hat, None,
                                       adapt=False)
            i_end_ab = self._current_dq(prev)[1]
        else:
            terms = self._terms(prev, self._i_prev_ab)
            psi_k, w_k = self._advance(prev, psi0, self._w_prev, win[1],
                                       win[0].T_L + self._T_hat, terms,
                                       adapt=False)
            i_end_ab = self._current(prev, terms)[1]
        self._note_told_move(win, self._k)  # in the interval lost: (I5) stops
        if self.inertia is not None:
            self._track_inertia(None, lost=True)
        self._measured = False
        eps_k = wrap_angle(prev.eps + T * prev.w_0)
        self.estimator.set_rotor_flux(psi_k * cmath.exp(1j * eps_k), i_end_ab)
        self._i_prev_ab = i_end_ab
        self._coasted = True
        hist.append(self._held(hist[-1]))
        hist.popleft()
        self._base = None
        self._psi_prev = psi_k
        self._w_prev = w_k
        self.w_hat = w_k
        self.eps_0 = eps_k


Mat2 = tuple[complex, complex, complex, complex]


def expm2(a: Mat2, tau: float, det: complex | None = None, first_row: bool = False
          ) -> tuple[complex, ...]:
    """e^{A·τ} of a complex 2×2 matrix (row-major), by its two eigenvalues (Sylvester).
    ``det``: A's determinant a11·a22 − a12·a21 where the caller has it; ``first_row``: only
    (e11, e12)."""
    a11, a12, a21, a22 = a
    half_tr = 0.5 * (a11 + a22)
    if det is None:
        det = a11 * a22 - a12 * a21
    disc = cmath.sqrt(half_tr * half_tr - det)
    l1, l2 = half_tr + disc, half_tr - disc
    e1, e2 = cmath.exp(l1 * tau), cmath.exp(l2 * tau)
    gap = l1 - l2
    if abs(gap) * tau < 1e-9:  # (nearly) repeated eigenvalue: e^{λτ}(I + (A − λI)τ)
        if first_row:
            return e1 * (1 + (a11 - l1) * tau), e1 * a12 * tau
        return (e1 * (1 + (a11 - l1) * tau), e1 * a12 * tau, e1 * a21 * tau,
                e1 * (1 + (a22 - l1) * tau))
    f = (e1 - e2) / gap  # coefficient of A
    g = (l1 * e2 - l2 * e1) / gap  # coefficient of I
    if first_row:
        return g + f * a11, f * a12
    return (g + f * a11, f * a12, f * a21, g + f * a22)


class FullOrderSampledController(SampledController):
    """The sampled-data full-order law (25)–(27), (32) for a voltage-fed drive.

    Over an interval the drive holds u_dq in the frame turning at ω0; with the rotor speed
    at its estimate ω the stator-current and rotor-flux rows of (2) are linear time-invariant
    in that frame, x = (i_s, ψ_r): dx/dτ = A·x + (u/σ, 0), solved with e^{Aτ}, where
    A(ω0, ω) = [[−c1 − jω0, β(α − jω)], [αM, −α + j(ω − ω0)]], c1 = R_s/σ + β·αM. The voltage
    of the interval is the one that brings the modelled current error (28) at the
    interval's end to what (34) would give, e(T) = e^{−ke·T}·e(0) − (1 − e^{−ke·T})/ke·αM·ψ̃_rd
    (the unknown e_ω term dropped). ω0 is (26) at the midpoint; the observer (27) with w of
    (32) is integrated with Simpson's rule on the model's trajectory.
    """

    #: the pull (I4) on this law's ω̂: its readings carry the voltage drive's errors (the
    #: dead time's near the crossings), and (27) carries ω̂ between them; over 25 noise seeds
    #: of `real-drive` 200 s⁻¹ completed every one (500: one stop), docs/robustness.md §12
    PULL_K_S = 200.0

    _lookahead = 1  # the end of the commanded interval, 2(k + d) + 2
    __slots__ = ("_T_6", "_a21", "_c1", "_decay", "_decay_gain", "_eps_k", "_gamma_2", "_i_prev",
                 "_rot_k")

    def __init__(self, motor, config: ControllerConfig, refs_at: Callable[[float], Refs],
                 eps_0: float = 0.0, w_hat: float = 0.0) -> None:
        if config.law is not Law.FULL_ORDER:
            raise ValueError("FullOrderSampledController implements the full-order law only")
        # J tracked as the current-fed law's (docs/robustness.md §9), its reading from this
        # law's joint (i, ψ) interval model (_fo_track)
        SampledController.__init__(self, motor, replace(config, law=Law.CURRENT_FED),
                                   refs_at, eps_0, w_hat)
        self.config = config
        # (I5) as the current-fed law's (set above: this law's drive is not a PI current
        # loop): the told load watched once J has settled, and a load it leaves out observed
        # from the reading that rejects it on (docs/robustness.md §12)
        self._from_sample = True  # the voltage drive's trajectory from the measured current
        g = self._g
        if g.k_w * self._T > g.k_w_T_max:
            # the speed loop through the current loop (34): stable for kω·T < 1 only
            # (docs/robustness.md §11, (S1)–(S3))
            self._k_w = g.k_w_T_max / self._T
        self._gamma_2 = g.gamma_2
        self._decay = math.exp(-g.k_e * self._T)  # e^{−ke·T}
        self._decay_gain = (1.0 - self._decay) / g.k_e  # (1 − e^{−ke·T})/ke
        self._T_6 = self._T / 6.0  # Simpson's weight
        self._i_prev = 0j  # measured current at t_{k−1}, frame at t_{k−1}
        self._eps_k: float | None = None  # ε_k of the last step and its e^{−jε_k}
        self._rot_k = 1 + 0j

    def summary(self) -> dict[str, object] | None:
        """:meth:`SampledController.summary`, and under ``speed_gain`` the kω the law used
        where the period bounded it (``Gains.k_w_T_max``)."""
        found = SampledController.summary(self)
        g = self._g
        if self._k_w != g.k_w:
            found = found if found is not None else {}
            found["speed_gain"] = {"k_w": g.k_w, "applied": self._k_w,
                                   "k_w_T_max": g.k_w_T_max, "T": self._T}
        return found

    def _set_motor(self, motor) -> None:
        super()._set_motor(motor)
        self._c1 = motor.R_s / motor.sigma + motor.beta * self._aM
        self._a21 = complex(self._aM, 0.0)

    # ------------------------------------------------------------------ the model

    def _fo_rate(self, psi: complex, i: complex, i_ref: complex, r: Refs, T_L: float
                 ) -> float:
        """dω̂/dt of (27) with w of (32), the current error (28) against ``i_ref``.

        Over an interval the reference is the one the command aimed at (interpolated between
        its start and end), not i*(ω̂) re-evaluated with the updated ω̂: that would feed the
        observer's own prediction error back through kω/(μψ*) ≈ 6 A per rad/s and β·ψ/γ2,
        a loop gain near 1 per period at 1 ms (docs/paper.md §E10).
        """
        e_d, e_q = i.real - i_ref.real, i.imag - i_ref.imag
        w = (r.psi_ref * psi.imag + self._beta * (psi.imag * e_d - psi.real * e_q)
             ) / self._gamma_2
        return self._mu * (psi.real * i.imag - psi.imag * i.real) - T_L / self._J + w

    def _fo_model(self, c: Interval, i0: complex, psi0: complex, w0: float,
                  r0: Refs, rh: Refs, r1: Refs, f0: float | None = None):
        """The model over interval ``c`` from (i0, ψ0, ω̂0), the references at its start,
        middle and end ``r0``, ``rh``, ``r1``: the rate at the start (``f0`` where the
        caller has it) and (i, ψ) at the middle and the end, by e^{A·T/2} applied twice.
        The step after a prediction takes the predicted model of the same interval from
        the same start (``_kept``, as :meth:`SampledController._advance`)."""
        kept = self._kept  # the prediction of the step before
        if (kept is not None and kept[0] is c and kept[1] is i0 and kept[2] is psi0
                and kept[3] is w0):
            return kept[4]
        return self._fo_predict(c, i0, psi0, w0, r0, rh, r1, f0)

    def _fo_predict(self, c: Interval, i0: complex, psi0: complex, w0: float,
                    r0: Refs, rh: Refs, r1: Refs, f0: float | None = None,
                    T_L: float | None = None):
        """:meth:`_fo_model` computed (nothing kept looked at: a step's prediction, from
        the state it has just estimated); ``T_L``: the load over the interval (default
        the profile's, ``r0.T_L``; with the load observed the profile's plus T̂_L)."""
        if T_L is None:
            T_L = r0.T_L
        if f0 is None:
            f0 = self._fo_rate(psi0, i0, c.i_ref0, r0, T_L)
        w_m = w0 + self._half_T * f0
        # A(ω0, ω) at the midpoint's speed
        a11, a12, a21, a22 = (complex(-self._c1, -c.w_0), self._beta * complex(self._alpha, -w_m),
                              self._a21, complex(-self._alpha, w_m - c.w_0))
        det = a11 * a22 - a12 * a21
        b = c.u_dq / self._sigma
        i_ss, p_ss = -a22 * b / det, a21 * b / det
        # e^{A·T/2}: expm2(a, T/2, det) inline (the same operations)
        tau = self._half_T
        half_tr = 0.5 * (a11 + a22)
        disc = cmath.sqrt(half_tr * half_tr - det)
        l1, l2 = half_tr + disc, half_tr - disc
        gap = l1 - l2
        if abs(gap) * tau < 1e-9:  # (nearly) repeated eigenvalue
            e11, e12, e21, e22 = expm2((a11, a12, a21, a22), tau, det)
        else:
            e1, e2 = cmath.exp(l1 * tau), cmath.exp(l2 * tau)
            f = (e1 - e2) / gap  # coefficient of A
            g = (l1 * e2 - l2 * e1) / gap  # coefficient of I
            e11, e12, e21, e22 = g + f * a11, f * a12, f * a21, g + f * a22
        di, dp = i0 - i_ss, psi0 - p_ss
        di_h, dp_h = e11 * di + e12 * dp, e21 * di + e22 * dp
        di_1, dp_1 = e11 * di_h + e12 * dp_h, e21 * di_h + e22 * dp_h
        # for _fo_finish: the load over the interval (T_L/J) and the reference at the middle
        return (c, w0, T_L / self._J, 0.5 * (c.i_ref0 + c.i_ref1), rh, r1, f0,
                i_ss + di_h, p_ss + dp_h, i_ss + di_1, p_ss + dp_1)

    def _fo_finish(self, model, end: tuple[complex, complex] | None = None,
                   adapt: bool = True) -> tuple[complex, complex, float, float]:
        """(i, ψ, ω̂, dω̂/dt) at the end of the modelled interval; ``end``: the measured (i, ψ)
        at the end, which also correct the mid-point by half the end's mismatch. ω̂:
        Simpson's rule on the trajectory; dω̂/dt: (27), (32) at the end, against the
        interval's end reference ``i_ref1``. Without ``adapt`` (a coasted interval, the
        model's ``f0`` taken without it too) the rates are the mechanical copy alone, w of
        (32) left out (:meth:`SampledController.coast`)."""
        c, w0, load, i_ref, rh, r1, f0, i_h, p_h, i_1, p_1 = model
        if end is not None:
            i_h += 0.5 * (end[0] - i_1)
            p_h += 0.5 * (end[1] - p_1)
            i_1, p_1 = end
        # the rates of (27), (32) at the middle and the end (_fo_rate, inline)
        mu, beta, gamma_2 = self._mu, self._beta, self._gamma_2
        if not adapt:
            f_h = mu * (p_h.real * i_h.imag - p_h.imag * i_h.real) - load
            f_1 = mu * (p_1.real * i_1.imag - p_1.imag * i_1.real) - load
            return i_1, p_1, w0 + self._T_6 * (f0 + 4.0 * f_h + f_1), f_1
        e_d, e_q = i_h.real - i_ref.real, i_h.imag - i_ref.imag
        w = (rh.psi_ref * p_h.imag + beta * (p_h.imag * e_d - p_h.real * e_q)) / gamma_2
        f_h = mu * (p_h.real * i_h.imag - p_h.imag * i_h.real) - load + w
        i_ref = c.i_ref1
        e_d, e_q = i_1.real - i_ref.real, i_1.imag - i_ref.imag
        w = (r1.psi_ref * p_1.imag + beta * (p_1.imag * e_d - p_1.real * e_q)) / gamma_2
        f_1 = mu * (p_1.real * i_1.imag - p_1.imag * i_1.real) - load + w
        return i_1, p_1, w0 + self._T_6 * (f0 + 4.0 * f_h + f_1), f_1

    # ------------------------------------------------------------------ a cycle

    def _fo_measured(self, jumped: bool) -> bool:
        """The flux at t_k is a reading of the interval just ended for the inertia filter:
        not from a coast's modelled start, nor across a frame set on the flux; with the
        load observed not at the standstill either (the current-fed law's rule: with ℓ a
        free state, the readings of a flux of a few mWb against a real drive's offsets and
        noise ran its speed to −540 rad/s in 6 ms, and the pull (I4) took ω̂ with it)."""
        return (self._measured and self._psi_prev is not None and not jumped
                and not (self._load_observed and self.commissioning is not None
                         and self.commissioning.pending))

    def _fo_track(self, model, i_e: complex, psi_e: complex, psi_k: complex, eps_k: float,
                  measured: bool) -> float | None:
        """The inertia tracker over the interval just ended (docs/robustness.md §9): (I1)
        from the measured flux at its end against the model's, the model's mechanical
        ∫dω̂/dt by Simpson's rule on the trajectory corrected by the measured end. Unlike
        the current-fed law's, it reads from the first sample on, the standstill included
        (the current model's flux then: they hold the filter's ω and D at rest; measured,
        J × 2 0.011 rad/s RMS with them, 0.020 without). ``measured``: the flux at t_k is a
        reading of the interval (:meth:`_fo_measured`)."""
        if self.inertia.frozen and not (self._load_watch and self.inertia.settled):
            self._measured = True  # ρ settled (the told load not watched), or a long coast
            return None
        _, w0, tl_j, _, rh, r1, _, i_h, p_h, i_1, p_1 = model
        psi0, i0 = self._psi_prev, self._i_prev
        if (measured and tl_j == 0.0 and rh.w_ref == 0.0 and rh.dw_ref == 0.0
                and r1.w_ref == 0.0 and r1.dw_ref == 0.0):
            # no torque asked of the rotor over the interval: a reading of ω and D, not of J
            # (a 2 % gain error on phase b with the true flux: the model's spurious torque
            # had J rejected at 0.255 s of the magnetisation, and the run rang at 3.4 rad/s)
            self.inertia.hold_ratio()
        elif (measured and self._load_observed and not self.inertia.switched
              and rh.dw_ref == 0.0 and r1.dw_ref == 0.0):
            # the load observed, the file's J standing, and no acceleration asked over the
            # interval: the torque the law raises holds the speed against the load, ρ·A =
            # ℓ·T, and a reading cannot tell ρ from ℓ ((I4)); J is read on the speed
            # reference's ramps (a load step at constant speed, with readings as noisy as a
            # real drive's dead time makes them, had the file's J rejected at 0.52 s with
            # ρ̂ 0, and the run stopped; docs/robustness.md §12)
            self.inertia.hold_ratio()
        if measured:
            mu = self._mu
            int_psi = self._T_6 * (psi0 + 4.0 * p_h + p_1)
            delta = psi_e - p_1
            self._w_mid = w0 + self._half_T * model[6]
            if int_psi:
                self._e_hat = -(delta / int_psi).imag
                self._int_psi = int_psi
            i_h = i_h + 0.5 * (i_e - i_1)
            p_h = p_h + 0.5 * delta
            self._a_int = self._T_6 * (
                mu * (psi0.real * i0.imag - psi0.imag * i0.real)
                + 4.0 * mu * (p_h.real * i_h.imag - p_h.imag * i_h.real)
                + mu * (psi_e.real * i_e.imag - psi_e.imag * i_e.real)) - self._T * tl_j
        self._measured = True
        return self._track_inertia(psi_k if measured else None, eps_k)

    def step(self, refs: Refs, sample: Sample) -> Command:
        """One sample at t_k (see the class docstring)."""
        T = self._T
        d = self._d
        self._k += 1
        k = self._k
        win = self._refs.starting(2 * k - 2)  # references at (2(k − 1) + i)·T/2: win[i]
        hist = self._hist
        prev = hist[0]
        eps_k = hist[1].eps if k > d > 0 else wrap_angle(prev.eps + T * prev.w_0)
        rot_k = cmath.exp(-1j * eps_k)
        i_k = sample.i_s_ab * rot_k
        # the past interval by the model: the estimator's current integral, then ω̂
        psi0 = self._psi_prev if self._psi_prev is not None else 0j
        T_hat_before = self._T_hat  # the load observed over it (0 otherwise)
        self._note_told_move(win, k)  # (I5) does not count these readings
        kept = self._kept  # the last step's prediction of this interval (_fo_model, inline)
        if (kept is not None and kept[0] is prev and kept[1] is self._i_prev
                and kept[2] is psi0 and kept[3] is self._w_prev):
            model = kept[4]
        else:
            model = self._fo_predict(prev, self._i_prev, psi0, self._w_prev, win[0], win[1],
                                     win[2], None,
                                     win[0].T_L + T_hat_before if T_hat_before else None)
        i_h, i_1 = model[7], model[9]
        eps_s = prev.eps
        # e^{jε} of the last step's ε_k (the same float object, not a zero: its sign) is the
        # conjugate of that step's e^{−jε_k}
        rot_s = (self._rot_k.conjugate() if eps_s is self._eps_k and eps_s != 0.0
                 else cmath.exp(1j * eps_s))
        self._eps_k, self._rot_k = eps_k, rot_k
        turn_h = cmath.exp(0.5j * prev.w_0 * T)
        turn_1 = turn_h * turn_h
        int_i_ab = self._T_6 * rot_s * (self._i_prev + 4.0 * i_h * turn_h + i_1 * turn_1)
        psi_ab = self.estimator.update(sample.i_s_ab, sample.u_s_ab, T, int_i_ab,
                                       rot_s * turn_1 * i_1, eps_k, refs.psi_ref,
                                       self._from_sample)
        if self.commissioning is not None:
            psi_ab = self._commission(refs, sample, psi_ab)
        if self._true_flux:
            psi_ab = law_flux(True, sample, psi_ab)
        psi_k = psi_ab * rot_k
        # the frame set on the flux at I_k's start: I_{k−1} ends in its own frame
        jumped = self._turned is not None and hist[1] is self._turned
        if jumped:
            rot_end = self._end_frame(prev)
            i_e, psi_e = sample.i_s_ab * rot_end, psi_ab * rot_end
        else:
            i_e, psi_e = i_k, psi_k
        # ω̂ at t_k and the rate there: _fo_finish(model, (i_e, psi_e)) inline
        _, w_k, tl_j, i_ref, rh, r1, f0, i_h, p_h, i_1, p_1 = model
        i_h += 0.5 * (i_e - i_1)
        p_h += 0.5 * (psi_e - p_1)
        mu, beta, gamma_2, T_6 = self._mu, self._beta, self._gamma_2, self._T_6
        e_d, e_q = i_h.real - i_ref.real, i_h.imag - i_ref.imag
        w_o = (rh.psi_ref * p_h.imag + beta * (p_h.imag * e_d - p_h.real * e_q)) / gamma_2
        f_h = mu * (p_h.real * i_h.imag - p_h.imag * i_h.real) - tl_j + w_o  # (27), (32)
        i_ref = prev.i_ref1
        e_d, e_q = i_e.real - i_ref.real, i_e.imag - i_ref.imag
        w_o = (r1.psi_ref * psi_e.imag + beta * (psi_e.imag * e_d - psi_e.real * e_q)) / gamma_2
        f_end = mu * (psi_e.real * i_e.imag - psi_e.imag * i_e.real) - tl_j + w_o
        w_k = w_k + T_6 * (f0 + 4.0 * f_h + f_end)  # Simpson
        if self.inertia is not None:
            measured = self._fo_measured(jumped)
            w_reset = self._fo_track(model, i_e, psi_e, psi_k, eps_k, measured)
            if w_reset is not None:
                w_k = w_reset
            if self._load_observed and measured and not self.inertia.frozen:  # (I4)
                tracker = self._load_filter or self.inertia
                self._T_hat = tracker.load * self._J
                w_k += min(tracker.tuning.k_s * T, 1.0) * (tracker.speed - w_k)
        T_hat = self._T_hat  # the load observed (0 otherwise): added to the profile's
        self.w_hat = w_k
        # (27), (32) at the end of an interval, against its end reference, is the rate at
        # the start of the next against that one's start reference (the same reference
        # object) when the two intervals' loads are the same number: f_end is kept for it
        load_end = win[0].T_L  # the load of the interval f_end ended
        if T_hat_before:
            load_end = load_end + T_hat_before
        i, psi, w = i_k, psi_k, w_k
        for j in range(1, d + 1):
            c = hist[j]
            r0 = win[2 * j]
            load = r0.T_L + T_hat if T_hat else r0.T_L  # _same_number(load, load_end), inline
            model = self._fo_predict(c, i, psi, w, r0, win[2 * j + 1], win[2 * j + 2],
                                     f_end if (c.i_ref0 is hist[j - 1].i_ref1 and not jumped
                                               and (load is load_end
                                                    or (load == load_end and load != 0.0)))
                                     else None, load)
            if j == 1:  # the next step's model of its past interval
                self._kept = (c, i, psi, w, model)
            # (i, ψ, ω̂, dω̂/dt) at the interval's end: _fo_finish(model) inline
            _, w, tl_j, i_ref, rh, r1, f0, i_h, p_h, i, psi = model
            e_d, e_q = i_h.real - i_ref.real, i_h.imag - i_ref.imag
            w_o = (rh.psi_ref * p_h.imag + beta * (p_h.imag * e_d - p_h.real * e_q)) / gamma_2
            f_h = mu * (p_h.real * i_h.imag - p_h.imag * i_h.real) - tl_j + w_o
            i_ref = c.i_ref1
            e_d, e_q = i.real - i_ref.real, i.imag - i_ref.imag
            w_o = (r1.psi_ref * psi.imag + beta * (psi.imag * e_d - psi.real * e_q)) / gamma_2
            f_end = mu * (psi.real * i.imag - psi.imag * i.real) - tl_j + w_o
            w = w + T_6 * (f0 + 4.0 * f_h + f_end)
            load_end = load
        last = hist[-1]
        # wrap_angle(last.eps + T·last.w_0), inline
        eps_app = (last.eps + T * last.w_0 + _PI) % TWO_PI - _PI if d else eps_k
        turned = False
        if self._coasted:  # the frame set on the flux (SampledController.step)
            self._coasted = False
            if d:
                eps_app, psi_turned, turn = self._on_flux(eps_app, psi)
                # the held commands' current references were the stalled law's: the
                # current error (28) over them is the hold's, not the estimate's, and (32)
                # would read it as one; their references become the modelled current
                if d == 1:
                    hist[1] = hist[1]._replace(i_ref0=i_k, i_ref1=i)
                i *= cmath.exp(-1j * turn)
                psi = psi_turned
                turned = True
        # the command for I_{k+d} = (t0, t0 + T], t0 = (k + d)·T
        r0, rh, r1 = win[self._cmd_refs]
        T_L = r0.T_L + T_hat if T_hat else r0.T_L
        if self._k > d + 1:
            # i_ref0 = the end reference of I_{k+d−1} (the frame turned: the current), and
            # (27), (32) at t0 with it: the rate the model ended that interval with, when its
            # load is this one (the same number) and the frame did not turn
            i_ref0 = i if turned else last.i_ref1
            f0 = (f_end if not turned and (T_L is load_end
                                           or (load_end == T_L and T_L != 0.0))  # _same_number
                  else self._fo_rate(psi, i, i_ref0, r0, T_L))
        else:
            i_ref0 = complex(*self._currents(r0, w, T_L)[:2])
            f0 = self._fo_rate(psi, i, i_ref0, r0, T_L)
        # i_sd*, i_sq* of (25) at the end, ω̂ extrapolated: _currents(r1, w + T·f0, T_L) inline
        psi_ref = r1.psi_ref
        i_sd1 = psi_ref / self._M + r1.dpsi_ref / self._aM
        i_sq1 = ((-self._k_w * math.tanh(w + T * f0 - r1.w_ref) + T_L / self._J + r1.dw_ref)
                 / (self._mu * psi_ref))
        q2 = self._i_max2 - i_sd1 * i_sd1
        q_max = math.sqrt(q2) if q2 > 0.0 else 0.0
        limited = abs(i_sq1) > q_max
        if limited:
            i_sq1 = math.copysign(q_max, i_sq1)
        i_ref1 = complex(i_sd1, i_sq1)
        e0 = i - i_ref0
        e1 = self._decay * e0 - self._decay_gain * self._aM * (psi.real - r0.psi_ref)
        target = i_ref1 + e1
        w_mid = w + self._half_T * f0
        w_0 = w_mid + self._aM * 0.5 * (i.imag + target.imag) / rh.psi_ref  # (26)
        # A(ω0, ω̂_mid)
        a11, a12, a21, a22 = (complex(-self._c1, -w_0), self._beta * complex(self._alpha, -w_mid),
                              self._a21, complex(-self._alpha, w_mid - w_0))
        det = a11 * a22 - a12 * a21
        # the first row of e^{A·T}: expm2(a, T, det, True) inline (the same operations)
        half_tr = 0.5 * (a11 + a22)
        disc = cmath.sqrt(half_tr * half_tr - det)
        l1, l2 = half_tr + disc, half_tr - disc
        gap = l1 - l2
        if abs(gap) * T < 1e-9:  # (nearly) repeated eigenvalue
            e11, e12 = expm2((a11, a12, a21, a22), T, det, True)
        else:
            x1, x2 = cmath.exp(l1 * T), cmath.exp(l2 * T)
            f = (x1 - x2) / gap  # coefficient of A
            e11, e12 = (l1 * x2 - l2 * x1) / gap + f * a11, f * a12
        free = e11 * i + e12 * psi  # i(T) with u = 0
        # i(T) = free − (u/σ)·[(I − E)·A⁻¹·e1]_0, A⁻¹·e1 = (a22, −a21)/det
        gain = ((1.0 - e11) * a22 + e12 * a21) / det
        u = self._sigma * (free - target) / gain
        self._base = last
        hist.append(_new_tuple(Interval, (target, u, eps_app, w_0, i_ref0, i_ref1)))
        hist.popleft()
        if turned:
            self._turned = hist[-1]
        self._psi_prev = psi_k
        self._i_prev = i_k
        self._w_prev = w_k
        self._i_prev_ab = sample.i_s_ab
        self.eps_0 = eps_k
        to_ab = cmath.exp(1j * (eps_app + self._half_T * w_0))
        return make_command(target, u, eps_app, w_0, target * to_ab, u * to_ab, limited,
                            (w_k, abs(psi_k), psi_k.real, psi_k.imag))  # paper_logged

    def coast(self) -> None:
        """A cycle without measurements: the model carries (i, ψ, ω̂) over the interval."""
        T = self._T
        self._k += 1
        if self.commissioning is not None:
            self.commissioning.gap()
        win = self._refs.starting(2 * self._k - 2)
        hist = self._hist
        prev = hist[0]
        psi0 = self._psi_prev if self._psi_prev is not None else 0j
        i0 = self._i_prev
        T_L = win[0].T_L + self._T_hat if self._T_hat else win[0].T_L  # T̂_L added
        f0 = (self._mu * (psi0.real * i0.imag - psi0.imag * i0.real)
              - T_L / self._J)  # the mechanical copy of (27) alone
        self._note_told_move(win, self._k)  # in the interval lost: (I5) stops
        i_k, psi_k, w_k, _ = self._fo_finish(
            self._fo_predict(prev, i0, psi0, self._w_prev, win[0], win[1], win[2], f0, T_L),
            adapt=False)
        if self.inertia is not None:
            self._a_int = w_k - self._w_prev  # the mechanical copy's ∫dω̂/dt over it
            self._track_inertia(None, lost=True)
        self._measured = False
        eps_k = wrap_angle(prev.eps + T * prev.w_0)
        rot = cmath.exp(1j * eps_k)
        self.estimator.set_rotor_flux(psi_k * rot, i_k * rot)
        self._coasted = True
        hist.append(self._held(hist[-1]))
        hist.popleft()
        self._base = None
        self._psi_prev, self._i_prev, self._w_prev = psi_k, i_k, w_k
        self._i_prev_ab = i_k * rot
        self.w_hat = w_k
        self.eps_0 = eps_k


def _untold_at(refs_at: Callable[[float], Refs]) -> Callable[[float], Refs]:
    """``refs_at`` with the load removed (:func:`untold`)."""
    return lambda t: untold(refs_at(t))


def make_controller(motor, config: ControllerConfig, refs_at: Callable[[float], Refs],
                    eps_0: float = 0.0, w_hat: float = 0.0) -> DriveController:
    """The controller ``config.discretisation`` names: the Euler :class:`Controller` or the
    sampled-data design. Both have ``step(refs, sample) -> Command`` and ``coast()``.

    The sampled-data full-order law models a voltage-fed drive with (d, q) setpoints; with a
    current-loop drive or (a, b) setpoints the full-order law runs the Euler design. With
    ``config.load`` UNTOLD (or OBSERVED: the filter's T̂_L takes its place) the sampled-data
    design's references lose their load here; the Euler design drops it in its step (or its
    load observer replaces it).
    """
    if config.load is LoadSource.UNTOLD or (config.load is LoadSource.OBSERVED
                                            and config.discretisation is Discretisation.EXACT):
        refs_at = _untold_at(refs_at)  # no load told (observed: the filter's T̂_L instead)
    if config.discretisation is Discretisation.EXACT:
        if config.law is Law.CURRENT_FED:
            return SampledController(motor, config, refs_at, eps_0=eps_0, w_hat=w_hat)
        if config.sampled_dq:
            return FullOrderSampledController(motor, config, refs_at, eps_0=eps_0,
                                              w_hat=w_hat)
    return Controller(motor, config, eps_0=eps_0, w_hat=w_hat)


def paper_controller(context: ControllerContext, params: Mapping[str, Any]
                     ) -> DriveController:
    """The ``paper`` controller (the entry point of ``can_drive_hil.controllers``): the laws
    of Marino, Tomei & Verrelli with the command line's options (``context.paper``, a
    :class:`ControllerConfig`), in the design its discretisation names
    (:func:`make_controller`). Its options come from the command line, not from
    ``--controller-params``."""
    if params:
        raise ValueError(f"the paper's laws take their options from the command line (--law, "
                         f"--flux, --estimator, ...), not --controller-params: "
                         f"{', '.join(sorted(params))}")
    config = context.paper if context.paper is not None else ControllerConfig(
        sampling=context.sampling, discretisation=Discretisation.EXACT,
        current_lag=context.current_lag)
    return make_controller(context.motor, config, context.refs_at, eps_0=context.eps_0,
                           w_hat=context.w_hat_0)
