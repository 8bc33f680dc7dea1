"""The discrete-time sensorless controller: one object, one step per sampling period.

It implements the laws of :mod:`gateway.control.laws` sampled with period T (§E9):
at each sample t_k it takes the measured currents i_s_ab(t_k), the average applied voltage
over (t_{k−1}, t_k] and, only in the comparison mode ``flux="true"``, the true rotor flux;
it returns the setpoints for the next interval and integrates its own states (frame angle
ε0, speed estimate ω̂, the flux estimator) with the forward-Euler rule, so they stay
consistent with what was sent.

Timing (docs/ARCHITECTURE.md): with ``delay = 0`` the setpoints act on (t_k, t_{k+1}],
with ``delay = 1`` (CANopen synchronous RPDO) on (t_{k+1}, t_{k+2}]. The command carries
the frame angle predicted for the start of that interval, ``eps_0``, with the frame speed
``w_0``; (a, b) setpoints are rotated with the angle of the interval's midpoint. With a
delay, the speed observer (16) integrates the torque of the currents acting on the motor
over the present period (the previous command), not of the one just computed.
"""

from __future__ import annotations

import cmath
import math
from collections import deque
from dataclasses import dataclass, field, replace
from enum import StrEnum

from dbc.modes import DriveMode, SetpointFrame
from dbc.timing import Sampling
from gateway.control.commissioning import Commissioning
from gateway.control.estimator import (
    DriftFreeFluxEstimator,
    OpenLoopFluxEstimator,
    RsAdaptiveFluxEstimator,
)
from gateway.control.interface import Command, Sample
from gateway.control.laws import Gains, Motor, Refs, current_fed, full_order
from gateway.control.load_observer import LoadObserver, RefsWithLoad


class Law(StrEnum):
    """CURRENT_FED: (15), (16), (20) for a current-fed drive; FULL_ORDER: (25)–(27), (32)
    for a voltage-fed drive."""

    CURRENT_FED = "current-fed"
    FULL_ORDER = "full-order"

    @property
    def drive_modes(self) -> tuple[DriveMode, ...]:
        """The drive modes the law can drive; the first is the default (the current-fed law
        sends currents, the full-order law voltages)."""
        if self is Law.CURRENT_FED:
            return (DriveMode.IDEAL, DriveMode.CURRENT_LOOP)
        return (DriveMode.VOLTAGE, DriveMode.CURRENT_LOOP)


class FluxSource(StrEnum):
    """ESTIMATED: sensorless, (24); TRUE: the emulator's true flux (the paper's "flux
    measurements available" comparison only)."""

    ESTIMATED = "estimated"
    TRUE = "true"


class EstimatorKind(StrEnum):
    """OPEN_LOOP: the paper's integrator (24); DRIFT_FREE: with a low-frequency correction;
    RS_ADAPTIVE: drift-free with on-line stator-resistance adaptation (docs/robustness.md)."""

    OPEN_LOOP = "open-loop"
    DRIFT_FREE = "drift-free"
    RS_ADAPTIVE = "rs-adaptive"


class LoadSource(StrEnum):
    """KNOWN: the laws get the profile's T_L, dT_L/dt (the paper); OBSERVED: T̂_L, dT̂_L/dt of
    :class:`gateway.control.load_observer.LoadObserver` instead; UNTOLD: neither, the laws
    assume no load (T_L = dT_L/dt = 0) — what a drive that cannot apply the profile's load
    gets by default (docs/robustness.md §2)."""

    KNOWN = "known"
    OBSERVED = "observed"
    UNTOLD = "untold"


class InertiaSource(StrEnum):
    """FILE: the laws take the motor file's J (the paper); TRACKED: the sampled-data design
    estimates J/J_true on line from the measured flux and applies it once the data reject
    the file's J (:mod:`gateway.control.inertia_tracker`, docs/robustness.md §9): the
    current-fed law, the load known only (an untold or observed load would read as
    inertia), not with the R_s adaptation. A run's default (:class:`gateway.spec.RunSpec`)
    is TRACKED; this config's is FILE, like its other paper defaults."""

    FILE = "file"
    TRACKED = "tracked"


def untold(refs: Refs) -> RefsWithLoad:
    """``refs`` with T_L = dT_L/dt = 0: what the laws get when they are not told the load."""
    return RefsWithLoad(refs.w_ref, refs.dw_ref, refs.ddw_ref, refs.psi_ref, refs.dpsi_ref,
                        refs.ddpsi_ref, 0.0, 0.0)


class Discretisation(StrEnum):
    """EULER: the laws sampled with forward Euler (:class:`Controller`); EXACT: the
    sampled-data design of :mod:`gateway.control.sampled` (docs/sampled-control.md)."""

    EULER = "euler"
    EXACT = "exact"


TWO_PI = 2.0 * math.pi


def as_enum(enum: type[StrEnum], value: object, what: str) -> StrEnum:
    """``value`` as a member of ``enum``; ValueError naming ``what`` and the choices."""
    try:
        return enum(value)
    except ValueError:
        raise ValueError(f"unknown {what} {value!r}; use one of "
                         f"{', '.join(m.value for m in enum)}") from None


@dataclass(frozen=True)
class ControllerConfig:
    """How the controller runs.

    law: :class:`Law`. flux: :class:`FluxSource`. estimator: :class:`EstimatorKind` (see
    :mod:`gateway.control.estimator`). w_c: corner of the drift-free estimator, rad/s.
    sampling: period T, the delay between the sample and the interval the setpoints act
    on, and the frame the drive receives its setpoints in (:class:`dbc.timing.Sampling`).
    gains: :class:`Gains`.
    discretisation: :class:`Discretisation` — EULER (this module's :class:`Controller`) or
        EXACT (:mod:`gateway.control.sampled`); pick the class with
        :func:`gateway.control.sampled.make_controller`.
    current_lag: time constant of the drive's current response to a setpoint step, s
        (0: ideal current source; only the exact design uses it).
    Strings are accepted for the enums (the command-line words) and converted.
    load: "known" (the laws get the profile's T_L, dT_L/dt: the paper, docs/paper.md §E6) or
        "observed" (T̂_L, dT̂_L/dt of :class:`LoadObserver` instead).
    load_bandwidth, load_speed_gain, load_current_rise: the load observer's tuning
        (p in rad/s, k_s in 1/s, ρ; see :mod:`gateway.control.load_observer`).
    identify: identify R_s and R_r during the standstill magnetisation and use them from the
        first sample the speed reference moves (:mod:`gateway.control.commissioning`).
    inertia: :class:`InertiaSource` (the current-fed law's exact design; the other designs
        take the file's J).
    """

    law: Law = Law.CURRENT_FED
    flux: FluxSource = FluxSource.ESTIMATED
    estimator: EstimatorKind = EstimatorKind.OPEN_LOOP
    w_c: float = 2.0
    sampling: Sampling = field(default_factory=Sampling)
    gains: Gains = field(default_factory=Gains)
    discretisation: Discretisation = Discretisation.EULER
    current_lag: float = 0.0
    load: LoadSource = LoadSource.KNOWN
    load_bandwidth: float = 300.0
    load_speed_gain: float = 300.0
    load_current_rise: float = 0.0
    identify: bool = False
    inertia: InertiaSource = InertiaSource.FILE

    def __post_init__(self) -> None:
        object.__setattr__(self, "law", as_enum(Law, self.law, "law"))
        object.__setattr__(self, "flux", as_enum(FluxSource, self.flux, "flux source"))
        object.__setattr__(self, "estimator",
                           as_enum(EstimatorKind, self.estimator, "estimator"))
        object.__setattr__(self, "discretisation",
                           as_enum(Discretisation, self.discretisation, "discretisation"))
        object.__setattr__(self, "load", as_enum(LoadSource, self.load, "load mode"))
        object.__setattr__(self, "inertia", as_enum(InertiaSource, self.inertia, "inertia"))
        if not self.current_lag >= 0.0:
            raise ValueError(f"current_lag {self.current_lag!r} s must be >= 0")
        if (self.load is LoadSource.OBSERVED and self.law is Law.FULL_ORDER
                and not self.sampled_dq):
            # the sampled-data full-order law observes it through the inertia filter
            # (docs/robustness.md §10); its Euler design has no observer found stable
            raise ValueError("the full-order law observes the load in the sampled-data "
                             "design on a voltage drive with (d, q) setpoints only "
                             "(--discretisation exact --setpoint-frame dq): use those, or "
                             "--load known or untold")
        if (self.load is LoadSource.OBSERVED and self.discretisation is Discretisation.EXACT
                and self.estimator is EstimatorKind.RS_ADAPTIVE):
            raise ValueError("--load observed in the sampled-data design reads the flux the "
                             "R_s adaptation moves: use --estimator open-loop or drift-free "
                             "(the identification takes R_s), or --discretisation euler")

    @property
    def sampled_dq(self) -> bool:
        """The sampled-data design with (d, q) setpoints and a drive that has no current lag:
        where the full-order law runs its own sampled design (else its Euler design)."""
        return (self.discretisation is Discretisation.EXACT and self.current_lag == 0.0
                and self.sampling.setpoint_frame is SetpointFrame.DQ)

    @property
    def holds_current(self) -> bool:
        """The drive holds the current-fed law's setpoints over the period (an ideal
        current source): the standstill identification's model of the current. Where it
        does not, the sampled-data design gives the identification each period's charge
        from its model of the current; the Euler design has none, and fits the current
        sensors' errors (:class:`Commissioning`'s ``sensors``) only where this holds."""
        return self.law is Law.CURRENT_FED and self.current_lag == 0.0


#: The signals the paper's controllers log (their :attr:`Command.logged`, in order): the speed
#: estimate ω̂ (16)/(27), rad/s, and the rotor flux the law used in the frame at t_k, Wb:
#: its modulus and its (d, q) components.
PAPER_SIGNALS = ("w_hat", "psi_r_mod_hat", "psi_rd_hat", "psi_rq_hat")


def paper_logged(w_hat: float, psi_r_dq: complex) -> tuple[float, float, float, float]:
    """The values of :data:`PAPER_SIGNALS`."""
    return (w_hat, abs(psi_r_dq), psi_r_dq.real, psi_r_dq.imag)


def law_flux(true_flux: bool, sample: Sample, psi_hat_ab: complex | None) -> complex:
    """The rotor flux the law uses, Wb: the estimate ``psi_hat_ab``, or with ``--flux true``
    (the paper's comparison with flux measurements) the drive's true flux."""
    if not true_flux:
        assert psi_hat_ab is not None
        return psi_hat_ab
    if sample.psi_r_ab is None:
        raise ValueError("flux='true' needs the true rotor flux in the sample")
    return sample.psi_r_ab


def wrap_angle(x: float) -> float:
    """Angle wrapped to [−π, π), rad."""
    return (x + math.pi) % TWO_PI - math.pi


class Controller:
    """The sampled Marino–Tomei–Verrelli controller (current-fed or full-order), Euler
    design; a :class:`gateway.control.interface.DriveController`."""

    signals = PAPER_SIGNALS

    def __init__(
        self,
        motor: Motor,
        config: ControllerConfig | None = None,
        eps_0: float = 0.0,
        w_hat: float = 0.0,
    ) -> None:
        self.motor = motor
        self.config = config or ControllerConfig()
        self._T = self.config.sampling.period
        self._delay = self.config.sampling.delay
        self._full = self.config.law is Law.FULL_ORDER
        self._true_flux = self.config.flux is FluxSource.TRUE
        self._gains = self.config.gains
        if self.config.estimator is EstimatorKind.RS_ADAPTIVE:  # docs/robustness.md
            self.estimator = RsAdaptiveFluxEstimator(motor)  # its own ω_c, γ_R
        elif self.config.estimator is EstimatorKind.DRIFT_FREE:
            self.estimator: OpenLoopFluxEstimator = DriftFreeFluxEstimator(motor, self.config.w_c)
        else:
            self.estimator = OpenLoopFluxEstimator(motor)
        self.eps_0 = wrap_angle(eps_0)
        self.w_hat = w_hat
        # Currents acting on the motor over the present period, per the delay: a queue of
        # the commands in flight (the drive holds zero before it receives anything).
        self._in_flight: deque[tuple[float, float]] = deque([(0.0, 0.0)] * self._delay)
        self._last = (0.0, 0.0)  # (ω0, dω̂/dt) of the last step, for coast()
        self._held: tuple[float, float] | None = None  # the drive's command, for withhold()
        # the load torque estimated instead of known (None: known)
        c = self.config
        self.load_observer = (LoadObserver(motor, self._T, c.load_bandwidth, c.load_speed_gain,
                                           c.load_current_rise)
                              if c.load is LoadSource.OBSERVED else None)
        self._untold = c.load is LoadSource.UNTOLD
        self.commissioning = (Commissioning(motor, self._T, sensors=c.holds_current)
                              if c.identify else None)

    def step(self, refs: Refs, sample: Sample) -> Command:
        """One sampling instant: flux, law, output; then ε0 and ω̂ advance by T."""
        T = self._T
        eps_0 = self.eps_0
        psi_hat_ab = (None if self._true_flux else
                      self.estimator.update(sample.i_s_ab, sample.u_s_ab, T, eps_0,
                                            refs.psi_ref))
        if self.commissioning is not None:
            ident, psi_hat_ab = self.commissioning.apply(refs, sample.i_s_ab, sample.u_s_ab,
                                                         self.estimator, psi_hat_ab)
            if ident is not None:
                self.motor = replace(self.motor, R_s=ident.R_s, R_r=ident.R_r, M=ident.M,
                                     L_s=ident.L_s, L_r=ident.L_r)
        psi_r_ab = law_flux(self._true_flux, sample, psi_hat_ab)
        if self.load_observer is not None:  # T_L not known: the laws get T̂_L, dT̂_L/dt
            refs = self.load_observer.refs(refs, sample.i_s_ab, sample.u_s_ab, eps_0)
        elif self._untold:
            refs = untold(refs)
        to_dq = cmath.exp(-1j * eps_0)
        psi_r_dq = psi_r_ab * to_dq
        if self._full:
            i_s_dq = sample.i_s_ab * to_dq
            out = full_order(
                refs, self.w_hat, psi_r_dq.real, psi_r_dq.imag, i_s_dq.real, i_s_dq.imag,
                self.motor, self._gains,
            )
        else:
            applied = None
            if self._delay:
                self._in_flight.append((0.0, 0.0))  # placeholder, replaced below
                applied = self._in_flight.popleft()
                self._held = applied
            out = current_fed(
                refs, self.w_hat, psi_r_dq.real, psi_r_dq.imag, self.motor, self._gains, applied
            )
            if self._delay:
                self._in_flight[-1] = (out.i_sd_ref, out.i_sq_ref)
        w_0 = out.w_0
        eps_app = wrap_angle(eps_0 + self._delay * T * w_0)
        to_ab = cmath.exp(1j * (eps_app + 0.5 * T * w_0))
        i_s_dq_ref = complex(out.i_sd_ref, out.i_sq_ref)
        u_s_dq_ref = complex(out.u_sd_ref, out.u_sq_ref)
        cmd = Command(
            i_s_dq_ref=i_s_dq_ref,
            u_s_dq_ref=u_s_dq_ref,
            eps_0=eps_app,
            w_0=w_0,
            i_s_ab_ref=i_s_dq_ref * to_ab,
            u_s_ab_ref=u_s_dq_ref * to_ab,
            i_limited=out.i_limited,
            logged=paper_logged(self.w_hat, psi_r_dq),
        )
        dw_hat = out.dw_hat
        if self.load_observer is not None:  # ω̂ also pulled to the observer's ω̂_m
            dw_hat += self.load_observer.speed_injection(self.w_hat)
        self.w_hat += T * dw_hat  # (16)/(27), forward Euler
        self.eps_0 = wrap_angle(eps_0 + T * w_0)  # (15)/(26): dε0/dt = ω0
        self._last = (w_0, dw_hat)
        return cmd

    def summary(self) -> dict[str, object] | None:
        """The standstill identification's result (``--identify``) for summary.json."""
        return None if self.commissioning is None else self.commissioning.describe()

    def withhold(self) -> None:
        """The command of the last :meth:`step` was not sent (ready only after the SYNC it
        was for): with a delay, the currents in flight are the drive's present ones, which
        it holds (the frame angle of the next command puts the frame back on time)."""
        if self._delay and self._held is not None:
            self._in_flight[-1] = self._held
        self._held = None

    def coast(self) -> None:
        """A period without measurements (a missed cycle on the bus).

        The drive holds the last setpoints and keeps turning their frame at ω0, so the
        controller's frame angle advances with the same ω0 and ω̂ is extrapolated with the last
        dω̂/dt; the flux estimator cannot integrate the missing voltage and turns its stator
        flux with the frame instead (:meth:`OpenLoopFluxEstimator.coast`). With a delay, the
        command in flight is repeated (the drive holds it).
        """
        w_0, dw_hat = self._last
        T = self._T
        if self.commissioning is not None:
            self.commissioning.gap()
        self.w_hat += T * dw_hat
        self.eps_0 = wrap_angle(self.eps_0 + T * w_0)
        self.estimator.coast(w_0, T)
        if self._delay and self._in_flight:
            self._in_flight.append(self._in_flight[-1])
            self._in_flight.popleft()
        if self.load_observer is not None:
            self.load_observer.coast(w_0, T)
