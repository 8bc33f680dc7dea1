"""The closed loop without CAN: continuous time (scipy) or sampled like the bus.

* Continuous: the paper's setting (section 6). The motor ODE and the controller's own
  states (ε0, ω̂, and the stator-flux integrator when the flux is estimated) are integrated
  together by ``scipy.integrate.solve_ivp``.
* Sampled: the drive model (:class:`plant.drive.Drive`, inner loop at its own rate) and the
  discrete controller exchange exactly what the CANopen PDOs carry, through the codec built
  from ``dbc/drive.dbc`` (INT16 quantisation), with zero-order hold and zero or one period
  of delay. The CANopen loop runs the same cycle code, so a lockstep run over the bus
  equals this simulation to the last bit.
"""

from __future__ import annotations

import cmath
import math
import threading
from collections.abc import Callable
from dataclasses import asdict, dataclass, field, replace
from typing import Any

import numpy as np

from dbc.cia301 import sync_counter
from dbc.cia402 import SW_INTERNAL_LIMIT, SW_REMOTE, State
from dbc.modes import DriveMode, SetpointFrame
from dbc.motor import MotorParams
from dbc.timing import Sampling, internal_rate
from gateway.control.controller import (
    PAPER_SIGNALS,
    ControllerConfig,
    Discretisation,
    EstimatorKind,
    FluxSource,
    Law,
    LoadSource,
    as_enum,
    euler_only,
    paper_logged,
    untold,
)
from gateway.control.interface import ControllerChoice, ControllerContext, summary_of
from gateway.control.laws import Gains, current_fed, full_order
from gateway.control.load_observer import load_config
from gateway.cycle import ControlCycle, CycleRow, Truth
from gateway.drive_profile import load_drive_profile
from gateway.errors import UserError
from gateway.guard import DivergenceWatch
from gateway.process_data import process_data
from gateway.reference import Profile
from gateway.report import Record
from plant.drive import Drive, Measurement, MotorState
from plant.motor import rhs_current_fed, rhs_full
from plant.params import DriveParams
from plant.rpdo import setpoints_from_rpdos, tpdo_signals
from plant.scenario import PlantScenario
from plant.timing import sync_cycle


@dataclass(frozen=True)
class SimConfig:
    """One simulation's configuration.

    law, flux, estimator: the controller's (:class:`Law`, :class:`FluxSource`,
        :class:`EstimatorKind`); drive_mode: the emulated drive's :class:`DriveMode`.
    sampling: period, delay and setpoint frame (:class:`dbc.timing.Sampling`), or None
        for continuous time.
    quantize: pass the PDO signals through the INT16 codec of dbc/drive.dbc.
    record_step: sampling of the continuous-time record, s.
    initial: the motor's state at t = 0 (the paper: all zero).
    w_hat_0, eps_0: the controller's speed estimate and frame angle at t = 0.
    discretisation: sampled runs only: "exact" (the sampled-data design,
        docs/sampled-control.md) or "euler" (the laws sampled with forward Euler).
    load: "known" (the paper), "observed" or "untold" (T_L = 0): the controller's T_L.
    identify: R_s and R_r identified during the standstill magnetisation (sampled runs;
        :mod:`gateway.control.commissioning`).
    plant: how the plant differs from the controller's model
        (:mod:`plant.scenario`); the default is the nominal plant. Continuous time takes the
        motor factors and the load only.
    """

    law: Law = Law.CURRENT_FED
    flux: FluxSource = FluxSource.ESTIMATED
    estimator: EstimatorKind = EstimatorKind.OPEN_LOOP
    drive_mode: DriveMode = DriveMode.IDEAL
    sampling: Sampling | None = field(default_factory=Sampling)
    quantize: bool = True
    gains: Gains = field(default_factory=Gains)
    drive_params: DriveParams = field(default_factory=DriveParams)
    w_c: float = 2.0
    record_step: float = 1e-3
    duration: float | None = None
    initial: MotorState = field(default_factory=MotorState)
    w_hat_0: float = 0.0
    eps_0: float = 0.0
    discretisation: Discretisation = Discretisation.EXACT
    plant: PlantScenario = field(default_factory=PlantScenario)
    load: LoadSource = LoadSource.KNOWN
    identify: bool = False
    controller: ControllerChoice = field(default_factory=ControllerChoice)

    @classmethod
    def from_words(cls, period: float | None = 1e-3, delay: int = 1,
                   setpoint_frame: str = "dq", drive: str | None = None,
                   **kw: Any) -> SimConfig:
        """A SimConfig from the command line's words: sampled with ``period`` (s; None:
        continuous time), ``delay`` periods of SYNC delay, the ``setpoint_frame``, and
        ``drive`` as the drive mode; the other keywords are fields."""
        if drive is not None:
            kw["drive_mode"] = drive
        sampling = None if period is None else Sampling(period, delay, setpoint_frame)
        return cls(sampling=sampling, **kw)

    def __post_init__(self) -> None:
        try:
            for name, enum, what in (("law", Law, "law"), ("flux", FluxSource, "flux source"),
                                     ("estimator", EstimatorKind, "estimator"),
                                     ("drive_mode", DriveMode, "drive mode"),
                                     ("discretisation", Discretisation, "discretisation"),
                                     ("load", LoadSource, "load mode")):
                object.__setattr__(self, name, as_enum(enum, getattr(self, name), what))
        except ValueError as exc:
            raise UserError(str(exc)) from None
        if self.sampling is None and not self.controller.is_paper:
            raise UserError(f"continuous time (--period continuous) integrates the paper's laws "
                            f"only; controller {self.controller.name!r} runs sampled: choose "
                            "a --period such as 1ms")
        if self.controller.is_paper and self.drive_mode not in self.law.drive_modes:
            raise UserError(
                f"the {self.law} law does not drive a '{self.drive_mode}' drive: use "
                f"--drive-mode {' or '.join(self.law.drive_modes)} (the current-fed law sends "
                "currents, the full-order law voltages)"
            )
        if self.drive_params.mode is not self.drive_mode:
            object.__setattr__(self, "drive_params", replace(self.drive_params,
                                                             mode=self.drive_mode))
        if self.sampling is None and self.drive_mode is DriveMode.CURRENT_LOOP:
            raise UserError("continuous time models the drive as ideal (current-fed law) or "
                            "voltage-fed (full-order law): choose --drive-mode ideal or "
                            "voltage, or a sampling --period such as 1ms for the current-loop "
                            "drive")
        try:
            euler_only(self.discretisation, self.load)
        except ValueError as exc:
            raise UserError(str(exc)) from None
        if self.identify and self.sampling is None:
            raise UserError("--identify runs in the sampled controller: choose a sampling "
                            "--period such as 1ms")
        if self.load is LoadSource.OBSERVED:
            if self.sampling is None:
                raise UserError("the load observer is discrete-time: with the load observed "
                                "(--load observed, or a plant scenario with [load].known = "
                                "false) choose a sampling --period such as 1ms, or --load known")
            try:
                load_config(self.load, self.drive_mode)
            except ValueError as exc:
                raise UserError(str(exc)) from None
        if self.sampling is None and not self.plant.continuous_time_ok:
            raise UserError(f"plant scenario {self.plant.source}: continuous time models the "
                            "motor factors and the load only (no sensors, inverter or drifts); "
                            "choose a sampling --period such as 1ms")

    def controller_config(self) -> ControllerConfig:
        """The controller's part of this configuration (continuous time: the record step
        stands in for the period, unused)."""
        return ControllerConfig(
            law=self.law, flux=self.flux, estimator=self.estimator, w_c=self.w_c,
            sampling=self.sampling or Sampling(self.record_step), gains=self.gains,
            discretisation=self.discretisation,
            current_lag=current_lag(self.drive_mode, self.drive_params),
            load=self.load, **load_config(self.load, self.drive_mode),
            identify=self.identify,
        )

    def describe(self) -> dict[str, Any]:
        """A JSON-able description (for summary.json)."""
        d = asdict(self)
        del d["sampling"]
        s = self.sampling
        d["period"] = "continuous" if s is None else s.period
        if s is not None:
            d["delay"], d["setpoint_frame"] = s.delay, s.setpoint_frame
        d["initial"] = {k: (str(v) if isinstance(v, complex) else v)
                        for k, v in asdict(self.initial).items()}
        d["drive_params"] = {k: (str(v) if isinstance(v, complex) else v)
                             for k, v in asdict(self.drive_params).items()}
        del d["plant"]
        d["plant_scenario"] = self.plant.describe()
        return d


def current_lag(drive: DriveMode, params: DriveParams) -> float:
    """The time constant the sampled-data controller assumes for the drive's current
    response: 1/bandwidth of the PI current loop, 0 for an ideal source (or voltage-fed)."""
    return 1.0 / params.current_loop_bw if drive is DriveMode.CURRENT_LOOP else 0.0


Progress = Callable[[float], None]


def emulator_rate() -> float:
    """The emulated drive's nominal internal rate (PWM/current loop), Hz."""
    return DriveParams().f_pwm


def run(profile: Profile, motor: MotorParams, cfg: SimConfig,
        progress: Progress | None = None, stop: threading.Event | None = None,
        watch: DivergenceWatch | None = None) -> Record:
    """Simulate the profile; the record holds one row per period (or record step).

    ``stop``: when set, the run ends after the current cycle (continuous time: the current
    solver step) and the record holds what was simulated so far. ``watch``: the divergence
    guard of the bus loop (:class:`gateway.guard.DivergenceWatch`); when it trips the record
    ends with the cycle (continuous time: the record step) that tripped it and
    ``watch.reason`` says why. None (the benchmarks): the run goes on whatever happens.
    """
    if cfg.sampling is None:
        return run_continuous(profile, motor, cfg, progress, stop, watch)
    return run_sampled(profile, motor, cfg, progress, stop, watch)


# --------------------------------------------------------------------------- sampled


class PdoLink:
    """What the PDOs do to the signals: the emulator's process data (INT16 quantisation of
    ``dbc/drive.dbc``), or nothing (quantize=False)."""

    def __init__(self, quantize: bool, frame: SetpointFrame) -> None:
        self.pd = (process_data(load_drive_profile(None), frame=frame) if quantize
                   else None)

    def tpdos(self, meas: Measurement, sync_counter: int = 0) -> dict[str, float]:
        """The drive's role values as the gateway decodes them, for one measurement."""
        status = int(State.OPERATION_ENABLED) | SW_REMOTE | (
            SW_INTERNAL_LIMIT if meas.limit_active else 0)
        values = tpdo_signals(meas, status, sync_counter)
        return self.pd.quantize(values, tx=True) if self.pd else values

    def rpdos(self, values: dict[str, float]) -> dict[str, float]:
        """The gateway's role values as the drive decodes them."""
        return self.pd.quantize(values, tx=False) if self.pd else dict(values)


def drive_params_for_period(params: DriveParams, T: float, mode: DriveMode) -> DriveParams:
    """The drive's parameters in ``mode`` with its internal rate raised, if needed, to a
    whole number of steps per period (:func:`dbc.timing.internal_rate`)."""
    return replace(params, mode=mode, f_pwm=internal_rate(params.f_pwm, T))


def run_sampled(profile: Profile, motor: MotorParams, cfg: SimConfig,
                progress: Progress | None = None, stop: threading.Event | None = None,
                watch: DivergenceWatch | None = None) -> Record:
    """The sampled loop, cycle by cycle exactly as on the bus (docs/ARCHITECTURE.md): the
    drive's timing rule (:func:`plant.timing.sync_cycle`) and the gateway's cycle
    (:class:`gateway.cycle.ControlCycle`), with the PDO codec between them."""
    sampling = cfg.sampling
    assert sampling is not None
    T = sampling.period
    duration = cfg.duration or profile.duration
    n_cycles = round(duration / T)
    plant = cfg.plant  # the plant is the controller's model × the scenario
    drive = Drive(plant.plant_motor(motor),
                  plant.drive_params(drive_params_for_period(cfg.drive_params, T,
                                                             cfg.drive_mode)),
                  cfg.initial, **plant.drive_options(lambda t: profile.load.at(t)[0]))
    drive.enable(True)
    paper = cfg.controller_config()
    ctl = cfg.controller.make(ControllerContext(
        motor=motor, sampling=sampling, refs_at=profile.at, drive_mode=cfg.drive_mode,
        current_lag=paper.current_lag, paper=paper, eps_0=cfg.eps_0, w_hat_0=cfg.w_hat_0))
    cycle = ControlCycle(ctl, profile, sampling)
    link = PdoLink(cfg.quantize, sampling.setpoint_frame)
    rec = Record(cycle.row_type)
    apply = sampling.apply
    pending: dict[str, float] = {}
    T_L_active = [0.0]
    step_progress = max(1, n_cycles // 100)

    def latch() -> None:
        if pending:
            drive.set_setpoints(setpoints_from_rpdos(pending, pending))
            T_L_active[0] = pending["T_L"]
            pending.clear()

    def advance() -> Measurement:
        return drive.advance(T, T_L_active[0])

    for k in range(1, n_cycles + 1):
        meas = sync_cycle(advance, latch, apply)
        measured = link.tpdos(meas, sync_counter(k))
        out = cycle.step(k, measured, truth=Truth(meas.w_m, meas.psi_r_ab, meas.T_e))
        pending.update(link.rpdos(out.setpoints))
        rec.append(out.row)
        if watch is not None and watch.check(out.row, k):
            break
        if progress is not None and k % step_progress == 0:
            progress(k / n_cycles)
        if stop is not None and stop.is_set():  # every cycle: a stop acts within one
            break
    rec.identification = summary_of(ctl)
    return rec


# ------------------------------------------------------------------------ continuous


def run_continuous(profile: Profile, motor: MotorParams, cfg: SimConfig,
                   progress: Progress | None = None, stop: threading.Event | None = None,
                   watch: DivergenceWatch | None = None) -> Record:
    """The paper's continuous-time closed loop, integrated by scipy (LSODA, tight tolerances).

    Current-fed law with an ideal current source: state (ω, ψ_ra, ψ_rb, ε0, ω̂); the
    currents are the law's setpoints rotated by ε0 (15), the motor is the first three
    equations of (1). With an ideal current source the stator flux is algebraic
    (σ·i_s + (M/L_r)·ψ_r), so integrating (24) from the true initial flux returns the true
    flux: "estimated" equals "true" here.
    Full-order law with a voltage-fed drive: state (ω, ψ_ra, ψ_rb, i_sa, i_sb, ε0, ω̂) and,
    with the estimated flux, the integrator state ψ_s_ab of (24).
    The record holds the state every ``record_step``; the average voltage of each record
    step is the stator-flux increment over it plus R_s times the mean current (trapezoid).
    """
    from scipy.integrate import solve_ivp

    duration = cfg.duration or profile.duration
    h = cfg.record_step
    n = round(duration / h)
    t_eval = np.arange(n + 1) * h
    m, g = motor, cfg.gains
    pm = cfg.plant.plant_motor(motor)  # the plant's motor; m is the controller's
    load = cfg.plant.load_function(lambda t: profile.load.at(t)[0])
    k_r = m.M / m.L_r
    pk_r = pm.M / pm.L_r
    full = cfg.law is Law.FULL_ORDER
    estimated = full and cfg.flux is FluxSource.ESTIMATED
    last = [0.0]

    def psi_r_used(x: np.ndarray) -> complex:
        if estimated:  # (24), §E1: ψ_r = (L_r/M)(ψ_s − σ i_s)
            return (complex(x[7], x[8]) - m.sigma * complex(x[3], x[4])) / k_r
        return complex(x[1], x[2])

    def law(t: float, x: np.ndarray):
        r = profile.at(t)  # the plant's load is the profile's; the laws' may be untold
        told = untold(r) if cfg.load is LoadSource.UNTOLD else r
        to_dq = cmath.exp(-1j * x[5 if full else 3])
        w_hat = x[6 if full else 4]
        psi_dq = psi_r_used(x) * to_dq
        if full:
            i_dq = complex(x[3], x[4]) * to_dq
            return r, full_order(told, w_hat, psi_dq.real, psi_dq.imag, i_dq.real, i_dq.imag,
                                 m, g)
        return r, current_fed(told, w_hat, psi_dq.real, psi_dq.imag, m, g)

    def rhs(t: float, x: np.ndarray) -> list[float]:
        r, out = law(t, x)
        to_ab = cmath.exp(1j * x[5 if full else 3])
        if progress is not None and t - last[0] > duration / 100:
            last[0] = t
            progress(min(t / duration, 1.0))
        T_L = r.T_L if load is None else load(t, r.T_L)
        if full:
            u = complex(out.u_sd_ref, out.u_sq_ref) * to_ab
            dx = rhs_full(t, x[:5], pm, u, T_L)
            dx += [out.w_0, out.dw_hat]
            if estimated:
                dx += [u.real - m.R_s * x[3], u.imag - m.R_s * x[4]]  # (24)
            return dx
        i = complex(out.i_sd_ref, out.i_sq_ref) * to_ab
        return [*rhs_current_fed(t, x[:3], pm, i, T_L), out.w_0, out.dw_hat]

    x0 = np.zeros((9 if estimated else 7) if full else 5)
    s0 = cfg.initial
    x0[:3] = (s0.w_m, s0.psi_r_ab.real, s0.psi_r_ab.imag)
    if full:
        x0[3:7] = (s0.i_s_ab.real, s0.i_s_ab.imag, cfg.eps_0, cfg.w_hat_0)
        if estimated:  # the integrator starts from the true stator flux
            psi_s0 = pm.sigma * s0.i_s_ab + pk_r * s0.psi_r_ab
            x0[7:9] = (psi_s0.real, psi_s0.imag)
    else:
        x0[3:5] = (cfg.eps_0, cfg.w_hat_0)
    t_stop: list[float] = []

    def stopped(t: float, x: np.ndarray) -> float:
        """Terminal event: +1 until ``stop`` is seen, −1 from the time it was first seen
        (never at the start, which would leave no sign change: a stop requested before the
        integration begins ends it after the first step)."""
        if not t_stop and stop is not None and stop.is_set() and t > 0.0:
            t_stop.append(t)
        return 1.0 if not t_stop or t < t_stop[0] else -1.0

    stopped.terminal = True  # type: ignore[attr-defined]
    sol = solve_ivp(rhs, (0.0, t_eval[-1]), x0, method="LSODA", t_eval=t_eval,
                    rtol=1e-9, atol=1e-10, max_step=h,
                    events=stopped if stop is not None else None)
    if not sol.success:
        raise RuntimeError(f"continuous simulation failed: {sol.message}")
    rec = Record(CycleRow)
    psi_s_prev = i_prev = None
    for j, t in enumerate(sol.t):
        x = sol.y[:, j]
        r, out = law(t, x)
        eps = x[5 if full else 3]
        to_ab = cmath.exp(1j * eps)
        psi_r = complex(x[1], x[2])
        i = complex(x[3], x[4]) if full else complex(out.i_sd_ref, out.i_sq_ref) * to_ab
        psi_s = pm.sigma * i + pk_r * psi_r
        if psi_s_prev is None:
            u = 0j
        else:
            u = (psi_s - psi_s_prev) / h + pm.R_s * 0.5 * (i + i_prev)
        psi_s_prev, i_prev = psi_s, i
        psi_hat = psi_r_used(x) * cmath.exp(-1j * eps)
        T_e = pm.J * pm.mu * (psi_r.real * i.imag - psi_r.imag * i.real)
        row = CycleRow(
            t=t, w_ref=r.w_ref, psi_ref=r.psi_ref, T_L=r.T_L, w_m=x[0], psi_r_mod=abs(psi_r),
            i_sa=i.real, i_sb=i.imag, u_sa=u.real, u_sb=u.imag, i_sd_ref=out.i_sd_ref,
            i_sq_ref=out.i_sq_ref, u_sd_ref=out.u_sd_ref, u_sq_ref=out.u_sq_ref,
            eps_0=math.remainder(eps, 2 * math.pi), w_0=out.w_0, T_e=T_e,
            i_limited=float(out.i_limited), u_limit_active=0.0,
            **dict(zip(PAPER_SIGNALS, paper_logged(x[6 if full else 4], psi_hat), strict=True)),
        )
        rec.append(row)
        if watch is not None and watch.check(row, j):
            break  # the rows after the trip are not kept (the solver ran on)
    return rec
