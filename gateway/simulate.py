"""The closed loop without CAN: continuous time (scipy) or sampled like the bus.

* Continuous: the paper's setting (section 6). The motor ODE and the controller's own
  states (ε0, ω̂, and the stator-flux integrator when the flux is estimated) are integrated
  together by ``scipy.integrate.solve_ivp``.
* Sampled: the drive model (:class:`plant.drive.Drive`, inner loop at its own rate) and the
  discrete controller exchange exactly what the CANopen PDOs carry, through the codec built
  from ``dbc/drive.dbc`` (INT16 quantisation), with zero-order hold and zero or one period
  of delay. The CANopen loop runs the same cycle code, so a lockstep run over the bus
  equals this simulation to the last bit. With a plant scenario's bus faults the PDOs go as
  frames over :mod:`gateway.faultlink`, where the faults act and the bus loop's own cycle
  (:class:`gateway.loop.CycleLoop`) reacts, as over the bus in lockstep.
"""

from __future__ import annotations

import cmath
import math
import threading
from collections.abc import Callable
from dataclasses import replace
from typing import Any

import numpy as np

from dbc.busfaults import Frame
from dbc.cia301 import Emcy, sync_counter, sync_periods
from dbc.cia402 import SW_INTERNAL_LIMIT, SW_REMOTE, OperationMode, State
from dbc.modes import DriveMode, SetpointFrame
from dbc.motor import MotorParams
from dbc.signals import SETPOINTS
from dbc.timing import Sampling, internal_rate
from gateway.control.controller import (
    PAPER_SIGNALS,
    FluxSource,
    Law,
    LoadSource,
    paper_logged,
    untold,
)
from gateway.control.interface import ControllerContext, DriveController, summary_of
from gateway.control.laws import current_fed, full_order
from gateway.cycle import ControlCycle, CycleRow, Truth
from gateway.drive_profile import EMULATOR, EMULATOR_STANDARD, DriveProfile, load_drive_profile
from gateway.guard import DivergenceWatch
from gateway.process_data import process_data
from gateway.reference import Profile
from gateway.report import Record
from gateway.spec import RunSpec
from plant.drive import Drive, Measurement, MotorState
from plant.motor import rhs_current_fed, rhs_full
from plant.params import DriveParams
from plant.rpdo import setpoints_from_rpdos, tpdo_signals
from plant.scenario import PlantScenario
from plant.servo import servo_for
from plant.timing import sync_cycle


def _plant(spec: RunSpec) -> PlantScenario:
    """The spec's plant scenario; the nominal plant when it names none."""
    return spec.plant if isinstance(spec.plant, PlantScenario) else PlantScenario()


def _initial(spec: RunSpec) -> MotorState:
    """The motor's state at t = 0; at rest when the spec names none."""
    return spec.initial if spec.initial is not None else MotorState()


def current_lag(drive: DriveMode, params: DriveParams) -> float:
    """The time constant the sampled-data controller assumes for the drive's current
    response: 1/bandwidth of the PI current loop, 0 for an ideal source (or voltage-fed)."""
    return 1.0 / params.current_loop_bw if drive is DriveMode.CURRENT_LOOP else 0.0


Progress = Callable[[float], None]


def emulator_rate() -> float:
    """The emulated drive's nominal internal rate (PWM/current loop), Hz."""
    return DriveParams().f_pwm


def run(profile: Profile, motor: MotorParams, spec: RunSpec,
        progress: Progress | None = None, stop: threading.Event | None = None,
        watch: DivergenceWatch | None = None,
        on_record: Callable[[Record], None] | None = None) -> Record:
    """Simulate the profile; the record holds one row per period (or record step).

    ``stop``: when set, the run ends after the current cycle (continuous time: the current
    solver step) and the record holds what was simulated so far. ``watch``: the divergence
    guard of the bus loop (:class:`gateway.guard.DivergenceWatch`); when it trips the record
    ends with the cycle (continuous time: the record step) that tripped it and
    ``watch.reason`` says why. None (the benchmarks): the run goes on whatever happens.
    ``on_record``: called with the record before its first row (a live scope reads it).
    """
    if spec.sampling is None:
        if _plant(spec).bus_faults:
            raise ValueError("bus faults act on the PDOs of a sampled run: choose a period "
                             "such as 1ms")
        return run_continuous(profile, motor, spec, progress, stop, watch, on_record)
    return run_sampled(profile, motor, spec, progress, stop, watch, on_record)


# --------------------------------------------------------------------------- sampled


class PdoLink:
    """What the PDOs do to the signals: the emulator's process data (INT16 quantisation of
    ``dbc/drive.dbc``; ``builtin``: the emulator profile, its vector or its standard modes),
    or nothing (quantize=False)."""

    def __init__(self, quantize: bool, frame: SetpointFrame, builtin: str = EMULATOR) -> None:
        self.pd = (process_data(load_drive_profile(None, builtin), frame=frame) if quantize
                   else None)

    def tpdos(self, meas: Measurement, sync_counter: int = 0) -> dict[str, float]:
        """The drive's role values as the gateway decodes them, for one measurement."""
        values = _sent(meas, sync_counter)
        return self.pd.quantize(values, tx=True) if self.pd else values

    def tpdo_frames(self, meas: Measurement, sync_counter: int) -> list[Frame]:
        """The drive's TPDO frames for one measurement, in the order it sends them."""
        assert self.pd is not None
        values = _sent(meas, sync_counter)
        return [Frame(p.cob_id, p.codec.encode(values)) for p in self.pd.tpdos]

    def rpdos(self, values: dict[str, float]) -> dict[str, float]:
        """The gateway's role values as the drive decodes them."""
        return self.pd.quantize(values, tx=False) if self.pd else dict(values)


def _sent(meas: Measurement, sync_counter: int) -> dict[str, float]:
    """What the drive's TPDOs carry for one measurement, in Operation enabled."""
    status = int(State.OPERATION_ENABLED) | SW_REMOTE | (
        SW_INTERNAL_LIMIT if meas.limit_active else 0)
    return tpdo_signals(meas, status, sync_counter)


def drive_params_for_period(params: DriveParams, T: float, mode: DriveMode) -> DriveParams:
    """The drive's parameters in ``mode`` with its internal rate raised, if needed, to a
    whole number of steps per period (:func:`dbc.timing.internal_rate`)."""
    return replace(params, mode=mode, f_pwm=internal_rate(params.f_pwm, T))


#: The roles of the (d, q) frame, and of any setpoint (the frame's or a reference).
_FRAME_ROLES = frozenset({"eps_0", "w_0"})
_SETPOINT_ROLES = _FRAME_ROLES | {r for roles in SETPOINTS.values() for r in roles}


class _SampledDrive:
    """The drive's side of the sampled loop, as the emulated device does it: the RPDO
    values received since the last latch become active at the latch (the vector setpoints,
    or a standard drive's target for its own control, :mod:`plant.servo`, stepped at every
    SYNC), and the model advances one period with the load torque latched."""

    def __init__(self, drive: Drive, mode: DriveMode, T: float) -> None:
        self.drive, self.T = drive, T
        self.servo = (servo_for(drive.motor, drive.params.i_trip, T, w_m=drive.state.w_m)
                      if mode.standard else None)
        self.op_mode = OperationMode(mode.mode_of_operation)
        #: the role of a standard drive's target, and its value
        self.target_role = mode.target or ""
        self.target = 0.0
        self.pending: dict[str, float] = {}
        #: the roles whose RPDOs came since the last latch (None: all of them, the PDO link
        #: without faults): setpoints are applied when some came, and restart the (d, q)
        #: frame when the frame's came, as the emulated device does
        self.fresh: set[str] | None = None
        self.T_L = 0.0

    def latch(self) -> None:
        pending, servo, fresh = self.pending, self.servo, self.fresh
        if pending:
            if servo is None:
                if fresh is None or fresh & _SETPOINT_ROLES:
                    sp = setpoints_from_rpdos(pending, pending)
                    if fresh is None or fresh & _FRAME_ROLES:
                        self.drive.set_setpoints(sp)
                    else:  # references alone: the frame runs on
                        self.drive.set_references(sp)
            else:
                self.target = pending.get(self.target_role, self.target)
            self.T_L = pending["T_L"]
            pending.clear()
            if fresh is not None:
                fresh.clear()
        if servo is not None:  # as the emulated device does at every SYNC
            self.drive.set_setpoints(servo.follow(self.op_mode, self.target))

    def advance(self, periods: int = 1) -> Measurement:
        """The model over ``periods`` periods (more where the SYNC counter skipped: the
        setpoints held), the last one's sample."""
        meas = self.drive.advance_held(periods, self.T, self.T_L)
        if self.servo is not None:
            self.servo.sample(meas.w_m)  # its encoder, as the emulated device counts it
        return meas


def _sampled_drive(profile: Profile, motor: MotorParams, spec: RunSpec, T: float
                   ) -> _SampledDrive:
    """The plant of a sampled run: the controller's motor × the spec's plant scenario, the
    drive in the spec's mode (a standard drive's own control over its current loop), at an
    internal rate that is a whole number of steps per period."""
    plant = _plant(spec)
    mode = DriveMode.CURRENT_LOOP if spec.drive_mode.standard else spec.drive_mode
    drive = Drive(plant.plant_motor(motor),
                  plant.drive_params(drive_params_for_period(DriveParams(), T, mode)),
                  _initial(spec), **plant.drive_options(lambda t: profile.load.at(t)[0]))
    drive.enable(True)
    return _SampledDrive(drive, spec.drive_mode, T)


def run_sampled(profile: Profile, motor: MotorParams, spec: RunSpec,
                progress: Progress | None = None, stop: threading.Event | None = None,
                watch: DivergenceWatch | None = None,
                on_record: Callable[[Record], None] | None = None) -> Record:
    """The sampled loop, cycle by cycle exactly as on the bus (docs/ARCHITECTURE.md): the
    drive's timing rule (:func:`plant.timing.sync_cycle`) and the gateway's cycle
    (:class:`gateway.cycle.ControlCycle`), with the PDO codec between them."""
    sampling = spec.sampling
    assert sampling is not None
    if _plant(spec).bus_faults:
        return _run_linked(profile, motor, spec, progress, stop, watch, on_record)
    T = sampling.period
    n_cycles = round((spec.duration or profile.duration) / T)
    side = _sampled_drive(profile, motor, spec, T)
    ctl = _controller(profile, motor, spec)
    if watch is not None:
        watch.envelope = watch.envelope.for_controller(ctl)
    cycle = ControlCycle(ctl, profile, sampling, emulated_drive(spec).modulator_dc_link_v)
    link = PdoLink(spec.quantize, sampling.setpoint_frame, _emulator(spec.drive_mode))
    rec = Record(cycle.row_type)
    if on_record is not None:
        on_record(rec)
    step_progress = max(1, n_cycles // 100)
    for k in range(1, n_cycles + 1):
        meas = sync_cycle(side.advance, side.latch, sampling.apply)
        measured = link.tpdos(meas, sync_counter(k))
        out = cycle.step(k, measured, truth=Truth(meas.w_m, meas.psi_r_ab, meas.T_e))
        side.pending.update(link.rpdos(out.setpoints))
        rec.append(out.row)
        if watch is not None and watch.check(out.row, k):
            break
        if progress is not None and k % step_progress == 0:
            progress(k / n_cycles)
        if stop is not None and stop.is_set():  # every cycle: a stop acts within one
            break
    rec.identification = summary_of(ctl)
    return rec


def _emulator(mode: DriveMode) -> str:
    """The built-in drive profile of the emulator in ``mode``: its vector modes, or its
    standard modes."""
    return EMULATOR_STANDARD if mode.standard else EMULATOR


def emulated_drive(spec: RunSpec) -> DriveProfile:
    """The built-in drive profile whose process data a sampled run's PDO link carries."""
    return load_drive_profile(None, _emulator(spec.drive_mode))


def _controller(profile: Profile, motor: MotorParams, spec: RunSpec) -> DriveController:
    """The spec's controller for a sampled run against the emulated drive."""
    assert spec.sampling is not None
    paper = spec.controller_config(current_lag(spec.drive_mode, DriveParams()))
    return spec.controller.make(ControllerContext(
        motor=motor, sampling=spec.sampling, refs_at=profile.at, drive_mode=spec.drive_mode,
        current_lag=paper.current_lag, paper=paper, eps_0=spec.eps_0, w_hat_0=spec.w_hat_0,
        correction=spec.correction))


class _LinkedDrive:
    """The sampled drive on frames (:mod:`gateway.faultlink`): an RPDO frame is decoded
    into what the drive latches at its next SYNC (with the values of the RPDOs it lacks
    from their last frames, as the device's dictionary keeps them), a SYNC runs one
    :func:`plant.timing.sync_cycle` and its TPDOs are encoded; its full-resolution state is
    recorded by its own cycle count, as the emulated device's ``on_sample`` does."""

    def __init__(self, side: _SampledDrive, link: PdoLink, sampling: Sampling,
                 heartbeat_every: int, truth: Callable[[int, Measurement], None]) -> None:
        assert link.pd is not None
        self.side, self.link, self.apply, self.truth = side, link, sampling.apply, truth
        self.heartbeat_every = heartbeat_every
        self._rpdos = {p.cob_id: p for p in link.pd.rpdos}
        self._received: dict[str, float] = {}
        self._m = 0
        self._last = 0  # the last SYNC counter received (0: none yet)
        side.fresh = set()

    def sync(self, counter: int) -> list[Frame]:
        """A SYNC received: as the emulated device, the periods its counter says passed
        since the last one (a SYNC the drive did not receive still took its period), the
        setpoints held through all but the last."""
        periods = (sync_periods(self._last, counter)
                   if counter and self._last else 1)
        self._last = counter
        side = self.side
        meas = sync_cycle(lambda: side.advance(periods), side.latch, self.apply)
        self._m += periods
        self.truth(self._m, meas)
        return self.link.tpdo_frames(meas, counter)

    def rpdo(self, frame: Frame) -> str:
        pdo = self._rpdos[frame.can_id]
        if len(frame.data) != pdo.length:  # the device faults, and says so by EMCY
            return f"EMCY 0x{Emcy.PDO_LENGTH:04X}: {Emcy.PDO_LENGTH.text}"
        values = pdo.codec.decode(frame.data)
        self._received.update(values)
        self.side.pending.update(self._received)
        assert self.side.fresh is not None
        self.side.fresh.update(values)
        return ""


def _run_linked(profile: Profile, motor: MotorParams, spec: RunSpec,
                progress: Progress | None, stop: threading.Event | None,
                watch: DivergenceWatch | None,
                on_record: Callable[[Record], None] | None) -> Record:
    """The sampled loop with the plant scenario's bus faults: the bus loop's cycle
    (lockstep) and the sampled drive exchange frames over :mod:`gateway.faultlink`, where
    the faults act as on a bus. The record has the bus loop's columns and
    :attr:`Record.link` its account."""
    from dbc.busfaults import FaultSchedule
    from gateway.faultlink import check_link_faults, run_link
    from gateway.loop import CycleLoop, LoopConfig
    from gateway.runner import guards
    from gateway.sim import TruthRecorder

    sampling = spec.sampling
    assert sampling is not None
    plant = _plant(spec)
    if not spec.quantize:
        raise ValueError("bus faults act on the PDOs' frames, which an unquantised run "
                         "has not")
    T = sampling.period
    check_link_faults(plant.bus_faults, plant.name)
    schedule = FaultSchedule(plant.bus_faults, T)
    drive_profile = emulated_drive(spec)
    codec = PdoLink(True, sampling.setpoint_frame, _emulator(spec.drive_mode))
    pd = codec.pd
    assert pd is not None
    # the bus loop's guards, as `sim` has them: the drive's plausibility limits and the
    # caller's divergence envelope (the loop watches it itself)
    plausibility, _ = guards(drive_profile, profile, motor, spec)
    cfg = LoopConfig(n_cycles=round((spec.duration or profile.duration) / T),
                     sampling=sampling, max_missed=spec.max_missed,
                     max_miss_rate=spec.max_miss_rate, plausibility=plausibility,
                     envelope=watch.envelope if watch is not None else None,
                     envelope_cycles=watch.cycles if watch is not None else 3)
    ctl = _controller(profile, motor, spec)

    def make_loop(carrier: Any) -> CycleLoop:
        return CycleLoop(carrier, carrier.subscribe, pd, ctl, profile, cfg,
                         fault=carrier.fault, fault_cause=carrier.fault_cause,
                         fault_marks=schedule.marks)

    truth = TruthRecorder()
    side = _LinkedDrive(_sampled_drive(profile, motor, spec, T), codec, sampling,
                        max(1, round(drive_profile.heartbeat_ms * 1e-3 / T)), truth)
    loop, account = run_link(make_loop, pd, schedule, side, drive_profile.node,
                             drive_profile.gateway_node, truth, progress, stop, on_record)
    rec = loop.record
    rec.identification = summary_of(ctl)
    rec.link = account
    return rec


# ------------------------------------------------------------------------ continuous


def run_continuous(profile: Profile, motor: MotorParams, spec: RunSpec,
                   progress: Progress | None = None, stop: threading.Event | None = None,
                   watch: DivergenceWatch | None = None,
                   on_record: Callable[[Record], None] | None = None) -> Record:
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

    duration = spec.duration or profile.duration
    h = spec.record_step
    t_eval = np.arange(round(duration / h) + 1) * h
    loop = _ContinuousLoop(profile, motor, spec, progress, duration)
    stopped = _stop_event(stop)
    sol = solve_ivp(loop.rhs, (0.0, t_eval[-1]), loop.x0(), method="LSODA", t_eval=t_eval,
                    rtol=1e-9, atol=1e-10, max_step=h,
                    events=stopped if stop is not None else None)
    if not sol.success:
        raise RuntimeError(f"continuous simulation failed: {sol.message}")
    rec = Record(CycleRow)
    if on_record is not None:
        on_record(rec)
    prev: tuple[complex, complex] | None = None
    for j, t in enumerate(sol.t):
        row, prev = loop.row(t, sol.y[:, j], prev, h)
        rec.append(row)
        if watch is not None and watch.check(row, j):
            break  # the rows after the trip are not kept (the solver ran on)
    return rec


def _stop_event(stop: threading.Event | None) -> Callable[[float, np.ndarray], float]:
    """solve_ivp's terminal event for ``stop``: +1 until it is seen, −1 from the time it
    was first seen (never at the start, which would leave no sign change: a stop requested
    before the integration begins ends it after the first step)."""
    t_stop: list[float] = []

    def stopped(t: float, x: np.ndarray) -> float:
        if not t_stop and stop is not None and stop.is_set() and t > 0.0:
            t_stop.append(t)
        return 1.0 if not t_stop or t < t_stop[0] else -1.0

    stopped.terminal = True  # type: ignore[attr-defined]
    return stopped


class _ContinuousLoop:
    """The paper's laws and the motor of (1) as one ODE (:func:`run_continuous`): the
    controller sees ``motor``, the plant is ``motor`` × the spec's plant scenario."""

    def __init__(self, profile: Profile, motor: MotorParams, spec: RunSpec,
                 progress: Progress | None, duration: float) -> None:
        plant = _plant(spec)
        self.profile, self.m, self.g, self.spec = profile, motor, spec.gains, spec
        self.pm = plant.plant_motor(motor)  # the plant's motor; m is the controller's
        self.load = plant.load_function(lambda t: profile.load.at(t)[0])
        self.k_r = motor.M / motor.L_r
        self.pk_r = self.pm.M / self.pm.L_r
        self.full = spec.law is Law.FULL_ORDER
        self.estimated = self.full and spec.flux is FluxSource.ESTIMATED
        self.eps_i, self.w_hat_i = (5, 6) if self.full else (3, 4)
        self.progress, self.duration, self._last = progress, duration, 0.0

    def x0(self) -> np.ndarray:
        """The state at t = 0: the motor's initial state, ε0 and ω̂ of the spec, and the
        stator-flux integrator from the true stator flux."""
        x0 = np.zeros((9 if self.estimated else 7) if self.full else 5)
        s0 = _initial(self.spec)
        x0[:3] = (s0.w_m, s0.psi_r_ab.real, s0.psi_r_ab.imag)
        x0[self.eps_i], x0[self.w_hat_i] = self.spec.eps_0, self.spec.w_hat_0
        if self.full:
            x0[3:5] = (s0.i_s_ab.real, s0.i_s_ab.imag)
        if self.estimated:
            psi_s0 = self.pm.sigma * s0.i_s_ab + self.pk_r * s0.psi_r_ab
            x0[7:9] = (psi_s0.real, psi_s0.imag)
        return x0

    def psi_r_used(self, x: np.ndarray) -> complex:
        """The rotor flux the laws use, α-β: (24), §E1, ψ_r = (L_r/M)(ψ_s − σ i_s), or
        the true flux."""
        if self.estimated:
            return (complex(x[7], x[8]) - self.m.sigma * complex(x[3], x[4])) / self.k_r
        return complex(x[1], x[2])

    def law(self, t: float, x: np.ndarray) -> tuple[Any, Any]:
        """The reference at t and the law's output (15)-(16),(20) or (25)-(27),(32)."""
        r = self.profile.at(t)  # the plant's load is the profile's; the laws' may be untold
        told = untold(r) if self.spec.load is LoadSource.UNTOLD else r
        to_dq = cmath.exp(-1j * x[self.eps_i])
        w_hat = x[self.w_hat_i]
        psi_dq = self.psi_r_used(x) * to_dq
        if self.full:
            i_dq = complex(x[3], x[4]) * to_dq
            return r, full_order(told, w_hat, psi_dq.real, psi_dq.imag, i_dq.real, i_dq.imag,
                                 self.m, self.g)
        return r, current_fed(told, w_hat, psi_dq.real, psi_dq.imag, self.m, self.g)

    def rhs(self, t: float, x: np.ndarray) -> list[float]:
        r, out = self.law(t, x)
        to_ab = cmath.exp(1j * x[self.eps_i])
        if self.progress is not None and t - self._last > self.duration / 100:
            self._last = t
            self.progress(min(t / self.duration, 1.0))
        T_L = r.T_L if self.load is None else self.load(t, r.T_L)
        if self.full:
            u = complex(out.u_sd_ref, out.u_sq_ref) * to_ab
            dx = rhs_full(t, x[:5], self.pm, u, T_L)
            dx += [out.w_0, out.dw_hat]
            if self.estimated:
                dx += [u.real - self.m.R_s * x[3], u.imag - self.m.R_s * x[4]]  # (24)
            return dx
        i = complex(out.i_sd_ref, out.i_sq_ref) * to_ab
        return [*rhs_current_fed(t, x[:3], self.pm, i, T_L), out.w_0, out.dw_hat]

    def row(self, t: float, x: np.ndarray, prev: tuple[complex, complex] | None, h: float
            ) -> tuple[CycleRow, tuple[complex, complex]]:
        """The record's row at t and (ψ_s, i_s) for the next row's average voltage."""
        r, out = self.law(t, x)
        pm = self.pm
        eps = x[self.eps_i]
        to_ab = cmath.exp(1j * eps)
        psi_r = complex(x[1], x[2])
        i = (complex(x[3], x[4]) if self.full
             else complex(out.i_sd_ref, out.i_sq_ref) * to_ab)
        psi_s = pm.sigma * i + self.pk_r * psi_r
        u = 0j if prev is None else (psi_s - prev[0]) / h + pm.R_s * 0.5 * (i + prev[1])
        psi_hat = self.psi_r_used(x) * cmath.exp(-1j * eps)
        T_e = pm.J * pm.mu * (psi_r.real * i.imag - psi_r.imag * i.real)
        row = CycleRow(
            t=t, w_ref=r.w_ref, psi_ref=r.psi_ref, T_L=r.T_L, w_m=x[0], psi_r_mod=abs(psi_r),
            i_sa=i.real, i_sb=i.imag, u_sa=u.real, u_sb=u.imag, i_sd_ref=out.i_sd_ref,
            i_sq_ref=out.i_sq_ref, u_sd_ref=out.u_sd_ref, u_sq_ref=out.u_sq_ref,
            eps_0=math.remainder(eps, 2 * math.pi), w_0=out.w_0, T_e=T_e,
            i_limited=float(out.i_limited), u_limit_active=0.0,
            **dict(zip(PAPER_SIGNALS, paper_logged(x[self.w_hat_i], psi_hat), strict=True)),
        )
        return row, (psi_s, i)
