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

from gateway.control.controller import (
    ESTIMATORS,
    FLUX_SOURCES,
    LAWS,
    LOADS,
    Controller,
    ControllerConfig,
)
from gateway.control.laws import Gains, current_fed, full_order
from gateway.control.load_observer import tuning as load_tuning
from gateway.control.profiles import Profile
from gateway.cycle import SETPOINT_FRAMES, rpdos_from_command, sample_from_tpdos, sync_counter
from gateway.errors import UserError
from gateway.report import BASE_COLUMNS, Record
from plant.cia402 import SW_INTERNAL_LIMIT, SW_REMOTE, State
from plant.drive import Drive, Measurement, MotorState
from plant.motor import rhs_current_fed, rhs_full
from plant.params import DriveParams, MotorParams
from plant.rpdo import setpoints_from_rpdos, tpdo_signals
from plant.scenario import PlantScenario

DRIVES: tuple[str, ...] = ("ideal", "current-loop", "voltage")
#: The drive each law is meant for when none is given.
DEFAULT_DRIVE = {"current-fed": "ideal", "full-order": "voltage"}
#: Which drives make sense with which law.
COMPATIBLE = {
    "current-fed": ("ideal", "current-loop"),
    "full-order": ("voltage", "current-loop"),
}

COLUMNS: tuple[str, ...] = (
    *BASE_COLUMNS, "psi_rd_hat", "psi_rq_hat", "T_e", "i_limited", "u_limit_active",
)


@dataclass(frozen=True)
class SimConfig:
    """One simulation's configuration.

    period: sampling period T in s, or None for continuous time.
    delay: 0 or 1 periods between a sample and the interval its setpoints act on.
    setpoint_frame: "dq" (the drive turns the frame) or "ab" (held in the fixed frame).
    quantize: pass the PDO signals through the INT16 codec of dbc/drive.dbc.
    record_step: sampling of the continuous-time record, s.
    initial: the motor's state at t = 0 (the paper: all zero).
    w_hat_0, eps_0: the controller's speed estimate and frame angle at t = 0.
    load: "known" (the paper) or "observed": the controller's T_L (issue 14).
    plant: how the plant differs from the controller's model (issue 14,
        :mod:`plant.scenario`); the default is the nominal plant. Continuous time takes the
        motor factors and the load only.
    """

    law: str = "current-fed"
    flux: str = "estimated"
    estimator: str = "open-loop"
    drive: str = "ideal"
    period: float | None = 1e-3
    delay: int = 1
    setpoint_frame: str = "dq"
    quantize: bool = True
    gains: Gains = field(default_factory=Gains)
    drive_params: DriveParams = field(default_factory=DriveParams)
    w_c: float = 2.0
    record_step: float = 1e-3
    duration: float | None = None
    initial: MotorState = field(default_factory=MotorState)
    w_hat_0: float = 0.0
    eps_0: float = 0.0
    plant: PlantScenario = field(default_factory=PlantScenario)
    load: str = "known"

    def __post_init__(self) -> None:
        checks = (("law", LAWS), ("flux", FLUX_SOURCES), ("estimator", ESTIMATORS), ("load", LOADS),
                  ("drive", DRIVES), ("setpoint_frame", SETPOINT_FRAMES))
        for name, allowed in checks:
            if getattr(self, name) not in allowed:
                raise UserError(f"unknown {name.replace('_', ' ')} {getattr(self, name)!r}: "
                                f"use one of {', '.join(allowed)}")
        if self.drive not in COMPATIBLE[self.law]:
            raise UserError(
                f"the {self.law} law does not drive a {self.drive!r} drive: use --drive "
                f"{' or '.join(COMPATIBLE[self.law])} (the current-fed law sends currents, "
                "the full-order law voltages)"
            )
        if self.period is None and self.drive == "current-loop":
            raise UserError("continuous time models the drive as ideal (current-fed law) or "
                            "voltage-fed (full-order law): choose --drive ideal or voltage, or "
                            "a sampling --period such as 1ms for the current-loop drive")
        if self.delay not in (0, 1):
            raise UserError(f"delay {self.delay!r}: use 0 or 1 periods")
        if self.load != "known":
            if self.period is None:
                raise UserError("the load observer is discrete-time: with the load observed "
                                "(--load observed, or a plant scenario with [load].known = "
                                "false) choose a sampling --period such as 1ms, or --load known")
            try:
                load_tuning(self.drive)
            except ValueError as exc:
                raise UserError(str(exc)) from None
        if self.period is None and not self.plant.continuous_time_ok:
            raise UserError(f"plant scenario {self.plant.source}: continuous time models the "
                            "motor factors and the load only (no sensors, inverter or drifts); "
                            "choose a sampling --period such as 1ms")

    def controller_config(self) -> ControllerConfig:
        """The controller's part of this configuration."""
        return ControllerConfig(
            law=self.law, flux=self.flux, estimator=self.estimator, w_c=self.w_c,  # type: ignore[arg-type]
            period=self.period or self.record_step, delay=self.delay, gains=self.gains,
            load=self.load, **_load_tuning(self.load, self.drive),
        )

    def describe(self) -> dict[str, Any]:
        """A JSON-able description (for summary.json)."""
        d = asdict(self)
        d["period"] = "continuous" if self.period is None else self.period
        d["initial"] = {k: (str(v) if isinstance(v, complex) else v)
                        for k, v in asdict(self.initial).items()}
        d["drive_params"] = {k: (str(v) if isinstance(v, complex) else v)
                             for k, v in asdict(self.drive_params).items()}
        del d["plant"]
        d["plant_scenario"] = self.plant.describe()
        return d


Progress = Callable[[float], None]


def _load_tuning(load: str, drive: str) -> dict[str, float]:
    """ControllerConfig's load-observer fields for the drive mode (issue 14)."""
    if load == "known":
        return {}
    p, k_s, rho = load_tuning(drive)
    return {"load_bandwidth": p, "load_speed_gain": k_s, "load_current_rise": rho}


def run(profile: Profile, motor: MotorParams, cfg: SimConfig,
        progress: Progress | None = None, stop: threading.Event | None = None) -> Record:
    """Simulate the profile; the record holds one row per period (or record step).

    ``stop`` (sampled runs): when set, the run ends after the current cycle and the record
    holds what was simulated so far.
    """
    if cfg.period is None:
        return run_continuous(profile, motor, cfg, progress)
    return run_sampled(profile, motor, cfg, progress, stop)


# --------------------------------------------------------------------------- sampled


class PdoLink:
    """What the PDOs do to the signals: the INT16 codec, or nothing (quantize=False)."""

    def __init__(self, quantize: bool) -> None:
        if quantize:
            from dbc import load_codec

            self.quantize = load_codec().quantize
        else:
            self.quantize = _identity

    def tpdos(self, meas: Measurement, sync_counter: int = 0) -> tuple[dict, dict, dict]:
        """TPDO1..3 signal values (decoded) for one measurement."""
        q = self.quantize
        status = int(State.OPERATION_ENABLED) | SW_REMOTE | (
            SW_INTERNAL_LIMIT if meas.limit_active else 0)
        values = tpdo_signals(meas, status, sync_counter)
        return q("TPDO1", values), q("TPDO2", values), q("TPDO3", values)


def drive_params_for_period(params: DriveParams, T: float, mode: str) -> DriveParams:
    """The drive's parameters with its internal rate raised, if needed, to a whole number
    of steps per period (250 µs at 10 kHz: 3 steps, 12 kHz)."""
    n = max(1, math.ceil(T * params.f_pwm - 1e-9))
    f_pwm = params.f_pwm if abs(n - T * params.f_pwm) < 1e-9 else n / T
    return replace(params, mode=mode, f_pwm=f_pwm)


def _identity(name: str, values: dict) -> dict:
    return dict(values)


def run_sampled(profile: Profile, motor: MotorParams, cfg: SimConfig,
                progress: Progress | None = None, stop: threading.Event | None = None
                ) -> Record:
    """The sampled loop, cycle by cycle exactly as on the bus (docs/ARCHITECTURE.md)."""
    T = cfg.period
    assert T is not None
    duration = cfg.duration or profile.duration
    n_cycles = round(duration / T)
    plant = cfg.plant  # issue 14: the plant is the controller's model × the scenario
    drive = Drive(plant.plant_motor(motor),
                  plant.drive_params(drive_params_for_period(cfg.drive_params, T, cfg.drive)),
                  cfg.initial, **plant.drive_options(lambda t: profile.load.at(t)[0]))
    drive.enable(True)
    ctl = Controller(motor, cfg.controller_config(), eps_0=cfg.eps_0, w_hat=cfg.w_hat_0)
    link = PdoLink(cfg.quantize)
    rec = Record(COLUMNS)
    delay = cfg.delay
    pending: dict[str, dict] | None = None
    T_L_active = 0.0
    step_progress = max(1, n_cycles // 100)

    def latch(msgs: dict[str, dict]) -> float:
        drive.set_setpoints(setpoints_from_rpdos(msgs["RPDO1"], _rpdo2(msgs)))
        return msgs["RPDO3"]["T_L"]

    for k in range(1, n_cycles + 1):
        if delay == 0 and pending is not None:
            T_L_active = latch(pending)
        meas = drive.advance(T, T_L_active)
        if delay == 1 and pending is not None:
            T_L_active = latch(pending)
        t = k * T
        tpdo1, tpdo2, tpdo3 = link.tpdos(meas, sync_counter(k))
        sample = sample_from_tpdos(tpdo1, tpdo2, tpdo3)
        refs = profile.at(t)
        cmd = ctl.step(refs, sample)
        T_L_cmd = profile.at(t + delay * T).T_L if delay else refs.T_L
        pending = {name: link.quantize(name, values) for name, values in
                   rpdos_from_command(cmd, T_L_cmd, cfg.setpoint_frame).items()}  # type: ignore[arg-type]
        psi_hat = cmd.psi_r_dq
        rec.append((
            t, refs.w_ref, refs.psi_ref, refs.T_L,
            meas.w_m, abs(meas.psi_r_ab), cmd.w_hat, abs(psi_hat),
            sample.i_s_ab.real, sample.i_s_ab.imag, sample.u_s_ab.real, sample.u_s_ab.imag,
            cmd.i_s_dq_ref.real, cmd.i_s_dq_ref.imag, cmd.u_s_dq_ref.real, cmd.u_s_dq_ref.imag,
            cmd.eps_0, cmd.w_0,
            psi_hat.real, psi_hat.imag, meas.T_e, float(cmd.i_limited), float(meas.limit_active),
        ))
        if k % step_progress == 0:
            if progress is not None:
                progress(k / n_cycles)
            if stop is not None and stop.is_set():
                break
    return rec


def _rpdo2(msgs: dict[str, dict]) -> dict:
    return msgs["RPDO2"] if "RPDO2" in msgs else msgs["RPDO2_AB"]


# ------------------------------------------------------------------------ continuous


def run_continuous(profile: Profile, motor: MotorParams, cfg: SimConfig,
                   progress: Progress | None = None) -> Record:
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
    pm = cfg.plant.plant_motor(motor)  # the plant's motor (issue 14); m is the controller's
    load = cfg.plant.load_function(lambda t: profile.load.at(t)[0])
    k_r = m.M / m.L_r
    pk_r = pm.M / pm.L_r
    full = cfg.law == "full-order"
    estimated = full and cfg.flux == "estimated"
    last = [0.0]

    def psi_r_used(x: np.ndarray) -> complex:
        if estimated:  # (24), ERRATA 1: ψ_r = (L_r/M)(ψ_s − σ i_s)
            return (complex(x[7], x[8]) - m.sigma * complex(x[3], x[4])) / k_r
        return complex(x[1], x[2])

    def law(t: float, x: np.ndarray):
        r = profile.at(t)
        to_dq = cmath.exp(-1j * x[5 if full else 3])
        w_hat = x[6 if full else 4]
        psi_dq = psi_r_used(x) * to_dq
        if full:
            i_dq = complex(x[3], x[4]) * to_dq
            return r, full_order(r, w_hat, psi_dq.real, psi_dq.imag, i_dq.real, i_dq.imag, m, g)
        return r, current_fed(r, w_hat, psi_dq.real, psi_dq.imag, m, g)

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
    sol = solve_ivp(rhs, (0.0, t_eval[-1]), x0, method="LSODA", t_eval=t_eval,
                    rtol=1e-9, atol=1e-10, max_step=h)
    if not sol.success:
        raise RuntimeError(f"continuous simulation failed: {sol.message}")
    rec = Record(COLUMNS)
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
        rec.append((
            t, r.w_ref, r.psi_ref, r.T_L, x[0], abs(psi_r), x[6 if full else 4], abs(psi_hat),
            i.real, i.imag, u.real, u.imag, out.i_sd_ref, out.i_sq_ref, out.u_sd_ref,
            out.u_sq_ref, math.remainder(eps, 2 * math.pi), out.w_0,
            psi_hat.real, psi_hat.imag, T_e, float(out.i_limited), 0.0,
        ))
    return rec
