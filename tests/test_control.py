"""The controller against the paper's claims: convergence, the Lyapunov function (18)/(21),
sampled → continuous as T → 0, the flux estimator (24) and its drift."""

from __future__ import annotations

import cmath
import math
import random
from dataclasses import dataclass

import numpy as np
import pytest

from dbc.motor import MotorParams
from dbc.timing import Sampling
from gateway.control.controller import Controller, ControllerConfig, Sample, wrap_angle
from gateway.control.estimator import DriftFreeFluxEstimator, OpenLoopFluxEstimator
from gateway.control.laws import Gains, current_fed, dsat_tanh, full_order, sat_tanh
from gateway.simulate import run
from gateway.spec import RunSpec
from plant.drive import Drive, MotorState, Setpoints
from plant.params import DriveParams

MOTOR = MotorParams.paper()


@dataclass(frozen=True)
class ConstRefs:
    """Constant references (all derivatives zero)."""

    w_ref: float = 100.0
    psi_ref: float = 1.16
    T_L: float = 0.0
    dw_ref: float = 0.0
    ddw_ref: float = 0.0
    dpsi_ref: float = 0.0
    ddpsi_ref: float = 0.0
    dT_L: float = 0.0


class ConstProfile:
    """A profile holding constant references, for runs from other initial conditions."""

    source = "<test>"
    name = "constant"

    def __init__(self, duration: float, **refs: float) -> None:
        self.duration = duration
        self._refs = ConstRefs(**refs)

    def at(self, t: float) -> ConstRefs:
        return self._refs


def lyapunov(sig: dict[str, np.ndarray], gamma_1: float) -> np.ndarray:
    """V of (18) from a record with the true flux in the controller's frame."""
    d = sig["psi_rd_hat"] - sig["psi_ref"]
    q = sig["psi_rq_hat"]
    e_w = sig["w_hat"] - sig["w_m"]
    return 0.5 * (d * d + q * q) + 0.5 * gamma_1 * e_w * e_w


# ------------------------------------------------------------------------------ laws


def test_sat_is_odd_bounded_with_unit_slope():
    xs = np.linspace(-50, 50, 1001)
    assert all(sat_tanh(-x) == -sat_tanh(x) for x in xs)
    assert all(abs(sat_tanh(x)) < 1.0 + 1e-15 for x in xs)
    assert dsat_tanh(0.0) == 1.0
    assert all(dsat_tanh(x) > 0.0 for x in np.linspace(-15, 15, 301))
    for x in (-2.0, -0.3, 0.0, 0.7, 3.0):
        fd = (sat_tanh(x + 1e-6) - sat_tanh(x - 1e-6)) / 2e-6
        assert dsat_tanh(x) == pytest.approx(fd, rel=1e-6, abs=1e-9)


def test_current_fed_law_open_loop_references():
    """At ω̂ = ω* and oriented flux, (15) reduces to (9)-(11)."""
    r = ConstRefs(w_ref=100.0, psi_ref=1.16, T_L=2.0)
    out = current_fed(r, 100.0, 1.16, 0.0, MOTOR, Gains())
    assert out.i_sd_ref == pytest.approx(1.16 / MOTOR.M)  # (9)
    assert out.i_sq_ref == pytest.approx((2.0 / MOTOR.J) / (MOTOR.mu * 1.16))  # (10)
    slip = MOTOR.alpha * MOTOR.M * out.i_sq_ref / 1.16
    assert out.w_0 == pytest.approx(100.0 + slip)  # (11)
    # the observer sees torque balance: dω̂/dt = 0
    assert out.dw_hat == pytest.approx(0.0, abs=1e-9)
    # a positive speed-estimate error lowers the torque current (speed loop sign)
    hi = current_fed(r, 101.0, 1.16, 0.0, MOTOR, Gains())
    assert hi.i_sq_ref < out.i_sq_ref
    # a positive ψ_rq raises dω̂/dt through v of (20) and lowers it through the torque
    q = current_fed(r, 100.0, 1.16, 0.01, MOTOR, Gains())
    assert q.dw_hat == pytest.approx(
        -MOTOR.mu * 0.01 * out.i_sd_ref + 1.16 * 0.01 / Gains().gamma_1, rel=1e-9)


def test_current_limit_keeps_magnetising_current():
    r = ConstRefs(w_ref=0.0, psi_ref=0.001)
    out = current_fed(r, 1.0, 0.001, 0.0, MOTOR, Gains(i_max=10.0))
    assert out.i_limited
    assert math.hypot(out.i_sd_ref, out.i_sq_ref) == pytest.approx(10.0)
    assert out.i_sq_ref < 0.0  # ω̂ > ω*: brake
    assert out.i_sd_ref == pytest.approx(0.001 / MOTOR.M)


def test_full_order_law_zeroes_current_error_dynamics():
    """With exact model and true states, (32) makes ė_d = −αMψ̃_rd − ke e_d − βψ_rq e_ω."""
    g = Gains()
    r = ConstRefs(w_ref=50.0, psi_ref=1.0, T_L=1.0)
    w_m, w_hat = 49.0, 49.5
    psi_rd, psi_rq, i_sd, i_sq = 0.95, 0.02, 3.1, 2.0
    out = full_order(r, w_hat, psi_rd, psi_rq, i_sd, i_sq, MOTOR, g)
    m = MOTOR
    # plant (2) in the frame turning at ω0
    di_sd = (-m.R_s / m.sigma * i_sd + out.u_sd_ref / m.sigma + out.w_0 * i_sq
             + m.beta * m.alpha * psi_rd + m.beta * w_m * psi_rq - m.beta * m.alpha * m.M * i_sd)
    e_d = i_sd - out.i_sd_ref
    e_w = w_hat - w_m
    expected = -m.alpha * m.M * (psi_rd - 1.0) - g.k_e * e_d - m.beta * psi_rq * e_w
    assert di_sd == pytest.approx(expected, rel=1e-9)  # i_sd* is constant here


# ----------------------------------------------------------------- continuous (paper)


@pytest.fixture(scope="module")
def paper_continuous():
    from gateway.reference import paper_profile

    rec = run(paper_profile(), MOTOR, RunSpec(flux="true", sampling=None, drive_mode="ideal"))
    return rec.arrays()


def test_paper_scenario_continuous_converges(paper_continuous):
    s = paper_continuous
    e_w = s["w_m"] - s["w_ref"]
    e_psi = s["psi_r_mod"] - s["psi_ref"]
    e_est = s["w_hat"] - s["w_m"]
    assert np.max(np.abs(e_w)) < 5e-3  # mrad/s range with true flux and T_L known
    assert abs(e_w[-1]) < 1e-4 and abs(e_psi[-1]) < 1e-5 and abs(e_est[-1]) < 1e-4
    # the flux starts at 0 against ψ*(0) = 0.001 and then tracks
    assert np.max(np.abs(e_psi[s["t"] > 0.1])) < 1e-3
    # the references were followed: 100 rad/s, then 200 rad/s and 0.5 Wb
    assert s["w_m"][np.searchsorted(s["t"], 1.2)] == pytest.approx(100.0, abs=0.01)
    assert s["w_m"][-1] == pytest.approx(200.0, abs=0.01)
    assert s["psi_r_mod"][-1] == pytest.approx(0.5, abs=1e-3)


def test_lyapunov_function_does_not_increase(paper_continuous):
    """(21): dV/dt = −α(ψ̃_rd² + ψ̃_rq²) ≤ 0 along the closed loop (22)."""
    V = lyapunov(paper_continuous, Gains().gamma_1)
    assert np.all(np.diff(V) <= 1e-12 + 1e-9 * V[:-1])
    assert V[-1] < 1e-3 * V[0]


def test_converges_from_other_initial_conditions():
    """ω(0) = 50 rad/s, ω̂(0) = 0, rotor flux at a random angle (§E12: slow modes)."""
    rng = random.Random(7)
    angle = rng.uniform(-math.pi, math.pi)
    cfg = RunSpec(
        flux="true", sampling=None, drive_mode="ideal", record_step=2e-3,
        initial=MotorState(w_m=50.0, psi_r_ab=0.8 * cmath.exp(1j * angle)),
    )
    s = run(ConstProfile(8.0, w_ref=100.0, psi_ref=1.16), MOTOR, cfg).arrays()
    V = lyapunov(s, Gains().gamma_1)
    assert V[0] > 1.0  # starts far off (e_ω = −50 rad/s)
    assert np.all(np.diff(V) <= 1e-12 + 1e-9 * V[:-1])
    assert abs(s["w_m"][-1] - 100.0) < 0.05
    assert abs(s["w_hat"][-1] - s["w_m"][-1]) < 0.05
    assert abs(s["psi_r_mod"][-1] - 1.16) < 1e-3


def test_full_order_continuous_with_estimated_flux_converges():
    from gateway.reference import paper_profile

    cfg = RunSpec(law="full-order", flux="estimated", drive_mode="voltage", sampling=None)
    s = run(paper_profile(), MOTOR, cfg).arrays()
    assert np.max(np.abs(s["w_m"] - s["w_ref"])) < 5e-3
    assert abs(s["w_m"][-1] - 200.0) < 1e-3
    assert abs(s["psi_r_mod"][-1] - 0.5) < 1e-4


# --------------------------------------------------------------------------- sampled


def test_sampled_approaches_continuous_as_period_shrinks():
    prof = ConstProfile(0.6, w_ref=100.0, psi_ref=1.16)
    init = MotorState(w_m=90.0, psi_r_ab=1.16 + 0j)
    common = dict(flux="true", drive_mode="ideal", initial=init, w_hat_0=90.0, quantize=False)
    ref = run(prof, MOTOR, RunSpec(sampling=None, record_step=1e-3, **common)).arrays()
    errs = []
    for T in (1e-3, 5e-4, 2.5e-4):
        s = run(prof, MOTOR, RunSpec(sampling=Sampling(T, delay=0), **common)).arrays()
        step = round(1e-3 / T)
        w = s["w_m"][step - 1::step]  # samples at the continuous record's times
        errs.append(np.max(np.abs(w - ref["w_m"][1:len(w) + 1])))
    assert errs[0] > errs[1] > errs[2]
    assert errs[2] < 0.35 * errs[0]  # roughly first order in T


def test_sampled_paper_run_shows_delay_and_frame_effects():
    """The forward-Euler design (tests/test_sampled.py covers the exact one, which removes
    these effects)."""
    from gateway.reference import paper_profile

    base = dict(flux="estimated", drive_mode="ideal", discretisation="euler")
    rms = {}
    for key, kw in {"dq0": dict(delay=0), "dq1": dict(delay=1),
                    "ab1": dict(delay=1, setpoint_frame="ab")}.items():
        s = run(paper_profile(), MOTOR, RunSpec(**base, sampling=Sampling(1e-3, **kw))).arrays()
        e = s["w_m"] - s["w_ref"]
        rms[key] = float(np.sqrt(np.mean(e * e)))
        assert abs(e[-1]) < 0.5  # converges in every case
    assert rms["dq0"] < 0.8 * rms["dq1"]  # the SYNC delay costs accuracy
    assert rms["dq1"] < 0.8 * rms["ab1"]  # so does holding (a, b) setpoints (§E9)


# ------------------------------------------------------------------------- estimator


def _run_estimator(estimator, offset: complex = 0j, seconds: float = 2.0, T: float = 1e-3):
    """Drive a current-loop drive with oriented setpoints; estimate the rotor flux.

    No load: the rotor accelerates to about 390 rad/s within 2 s.
    """
    params = DriveParams(mode="current-loop", i_offset_ab=offset)
    drive = Drive(MOTOR, params)
    drive.enable(True)
    eps, w_0 = 0.0, 0.0
    errors = []
    i_sd, i_sq = 1.16 / MOTOR.M, 2.0
    w = 0.0
    for k in range(round(seconds / T)):
        w_0 = w + MOTOR.alpha * MOTOR.M * i_sq / 1.16  # slip (11) at the true speed
        drive.set_setpoints(Setpoints("dq", complex(i_sd, i_sq), 0j, eps, w_0))
        meas = drive.advance(T, 0.0)
        eps = wrap_angle(eps + w_0 * T)
        w = meas.w_m
        psi_hat = estimator.update(meas.i_s_ab, meas.u_s_ab, T, eps, 1.16)
        errors.append(abs(psi_hat - meas.psi_r_ab))
        del k
    return np.asarray(errors)


def test_estimator_matches_true_flux_with_exact_sensors():
    err = _run_estimator(OpenLoopFluxEstimator(MOTOR))
    assert np.max(err) < 0.01  # Wb, against 1.16 Wb, up to ω·T = 0.4 rad per period
    fine = _run_estimator(OpenLoopFluxEstimator(MOTOR), T=2e-4)
    assert np.max(fine) < 1e-3  # the trapezoidal current integral converges as T → 0


def test_open_loop_estimator_drifts_with_offset_drift_free_does_not():
    offset = 0.05 + 0.0j  # A of current-sensor offset
    open_loop = _run_estimator(OpenLoopFluxEstimator(MOTOR), offset, seconds=4.0)
    drift_free = _run_estimator(DriftFreeFluxEstimator(MOTOR, w_c=2.0), offset, seconds=4.0)
    # the pure integrator's error grows about linearly: R_s·offset·t·L_r/M
    assert open_loop[-1] > 2.0 * open_loop[len(open_loop) // 2 - 1] * 0.9
    assert open_loop[-1] > 0.5
    assert np.max(drift_free[len(drift_free) // 2:]) < 0.2
    assert drift_free[-1] < 0.25 * open_loop[-1]


def test_controller_config_rejects_bad_values():
    with pytest.raises(ValueError, match="unknown law"):
        ControllerConfig(law="vector")  # type: ignore[arg-type]
    with pytest.raises(ValueError, match="delay"):
        ControllerConfig(sampling=Sampling(delay=2))
    with pytest.raises(ValueError, match="gain k_w"):
        Gains(k_w=-1.0)
    ctl = Controller(MOTOR, ControllerConfig(flux="true"))
    with pytest.raises(ValueError, match="true rotor flux"):
        ctl.step(ConstRefs(), Sample(0j, 0j, None))


def test_full_order_sampled_needs_larger_gamma_2():
    """§E10: γ2 = γ1 works in continuous time but not sampled at 1 ms with a delay."""
    from gateway.reference import paper_profile

    base = dict(law="full-order", drive_mode="voltage", sampling=Sampling(1e-3, delay=1))
    bad = run(paper_profile(), MOTOR, RunSpec(**base, gains=Gains(gamma_2=0.0008))).arrays()
    good = run(paper_profile(), MOTOR, RunSpec(**base)).arrays()
    e_bad = np.max(np.abs(bad["w_m"] - bad["w_ref"]))
    e_good = np.max(np.abs(good["w_m"] - good["w_ref"]))
    assert e_good < 2.0
    assert e_bad > 10.0 * e_good
