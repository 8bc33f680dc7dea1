"""The emulated drive (plant/drive.py): modes, frames, limits, power stage, sensors."""

from __future__ import annotations

import cmath
import itertools
import math
import statistics

import pytest
from scipy.integrate import solve_ivp

from dbc.motor import MotorParams
from plant.drive import Drive, Measurement, MotorState, Setpoints, pi_gains
from plant.motor import rhs_full, stator_flux, torque
from plant.params import DriveParams

MOTOR = MotorParams.paper()
H = 1e-4  # internal step at the default f_pwm = 10 kHz


def steady_state(i_s_dq: complex, w_0: float, eps_0: float) -> tuple[MotorState, float, complex]:
    """The field-oriented steady state under constant (d, q) currents (section 3).

    ψ_rd = M·i_sd, ψ_rq = 0, ω = ω0 − αM·i_sq/ψ_rd (slip relation (11)), T_L = J·μ·ψ_rd·i_sq.
    Returns (state at angle eps_0, load torque, steady (d, q) voltage u = R_s·i + jω0·ψ_s).
    """
    m = MOTOR
    psi_rd = m.M * i_s_dq.real
    w_m = w_0 - m.alpha * m.M * i_s_dq.imag / psi_rd
    T_L = m.J * m.mu * psi_rd * i_s_dq.imag
    rot = cmath.exp(1j * eps_0)
    u_s_dq = m.R_s * i_s_dq + 1j * w_0 * stator_flux(m, psi_rd, i_s_dq)
    return MotorState(w_m, psi_rd * rot, i_s_dq * rot), T_L, u_s_dq


def make_drive(mode: str, state: MotorState | None = None, load=None, motor_drift=None,
               **kw: object) -> Drive:
    d = Drive(MOTOR, DriveParams(mode=mode, **kw), state,  # type: ignore[arg-type]
              load=load, motor_drift=motor_drift)
    d.enable(True)
    return d


def run(d: Drive, n: int, T: float, T_L: float) -> list[Measurement]:
    return [d.advance(T, T_L) for _ in range(n)]


# ---- timing -------------------------------------------------------------------------------------
@pytest.mark.parametrize("T", [1.5e-4, 0.0, -1e-3, 1e-3 + 3e-5])
def test_period_must_be_whole_steps(T: float) -> None:
    d = make_drive("ideal")
    with pytest.raises(ValueError, match="whole number of internal steps"):
        d.advance(T, 0.0)
    assert d.t == 0.0


def test_time_counts_whole_steps() -> None:
    d = make_drive("current-loop")
    for _ in range(1000):
        d.advance(1e-3, 0.0)
    assert d.t == pytest.approx(1.0, abs=1e-12)


def test_setpoints_validate_frame() -> None:
    with pytest.raises(ValueError, match="frame"):
        Setpoints(frame="xy")  # type: ignore[arg-type]
    with pytest.raises(ValueError, match="not finite"):
        Setpoints(i_s_ref=complex(math.nan, 0))


# ---- ideal mode: physics and the average voltage ------------------------------------------------
def test_ideal_rotor_settles_at_slip_speed_with_torque_balance() -> None:
    """Constant (d, q) currents, frame at ω0: the rotor settles where T_e = T_L, at (11)."""
    i_dq, w_0 = 4.0 + 2.0j, 100.0
    state, T_L, _ = steady_state(i_dq, w_0, 0.0)
    w_expected = state.w_m
    # start 3 rad/s too fast: the rotor must slow down to the slip speed by itself
    d = make_drive("ideal", MotorState(w_expected + 3.0, state.psi_r_ab, state.i_s_ab))
    d.set_setpoints(Setpoints("dq", i_dq, 0j, 0.0, w_0))
    meas = run(d, 300, 1e-2, T_L)[-1]
    eps = w_0 * d.t
    psi_r_dq = meas.psi_r_ab * cmath.exp(-1j * eps)
    assert meas.w_m == pytest.approx(w_expected, abs=1e-4)  # slip ω0 − ω = αM·i_sq/ψ_rd
    assert w_0 - meas.w_m == pytest.approx(MOTOR.alpha * i_dq.imag / i_dq.real, rel=1e-4)
    assert abs(psi_r_dq) == pytest.approx(MOTOR.M * i_dq.real, rel=1e-6)  # |ψ_r| = M·i_sd
    assert abs(psi_r_dq.imag) < 1e-6  # field orientation: ψ_rq = 0
    assert meas.T_e == pytest.approx(T_L, rel=1e-5)  # J·μ·ψ_rd·i_sq = T_L
    assert meas.T_e == pytest.approx(torque(MOTOR, meas.psi_r_ab, meas.i_s_ab), rel=1e-12)


def test_ideal_average_voltage_in_steady_state_is_exact() -> None:
    """u_s_ab = mean over the period of u_dq·e^{jε(t)}, u_dq = R_s·i + jω0·ψ_s (steady)."""
    i_dq, w_0, eps_0, T = 5.0 + 3.0j, 180.0, 0.9, 1e-3
    state, T_L, u_dq = steady_state(i_dq, w_0, eps_0)
    d = make_drive("ideal", state)
    for k in range(5):
        eps_k = eps_0 + w_0 * k * T
        d.set_setpoints(Setpoints("dq", i_dq, 0j, eps_k, w_0))
        meas = d.advance(T, T_L)
        x = w_0 * T
        expected = u_dq * cmath.exp(1j * eps_k) * (cmath.exp(1j * x) - 1) / (1j * x)
        assert meas.u_s_ab == pytest.approx(expected, rel=1e-8)
        assert not meas.limit_active
    assert abs(u_dq) > 100.0


def test_ideal_voltage_integrates_to_stator_flux_including_current_jumps() -> None:
    """Σ u·T = ψ_s(t_N) − ψ_s(0) + R_s·∫i_s dt, with the setpoint jumps counted."""
    d = make_drive("ideal")
    T = 1e-3
    total, int_i = 0j, 0j
    for k, i_ref in enumerate([5.0 + 0j, 5.0 + 0j, 3.0 - 4.0j, 0j, 2.0 + 2.0j]):
        d.set_setpoints(Setpoints("ab", i_ref))
        meas = d.advance(T, 0.3)
        total += meas.u_s_ab * T
        int_i += i_ref * T
        assert meas.i_s_ab == i_ref, k
    s = d.state
    psi_s = stator_flux(MOTOR, s.psi_r_ab, s.i_s_ab)
    assert total == pytest.approx(psi_s + MOTOR.R_s * int_i, rel=1e-12)
    # the first period holds the step's impulse: σ·5 A / 1 ms ≈ 284 V on top of R_s·5 A
    d.reset()
    d.enable(True)
    d.set_setpoints(Setpoints("ab", 5.0))
    assert d.advance(T, 0.0).u_s_ab.real > MOTOR.sigma * 5.0 / T


def test_dq_frame_turns_while_ab_setpoints_lag() -> None:
    """§E9: (a, b) setpoints held over T lag the frame by ω0·T/2 at the sample."""
    i_dq, w_0, eps_0, T = 4.0 + 2.0j, 200.0, 0.3, 1e-3
    state, T_L, _ = steady_state(i_dq, w_0, eps_0)
    eps_end = eps_0 + w_0 * T
    d = make_drive("ideal", state)
    d.set_setpoints(Setpoints("dq", i_dq, 0j, eps_0, w_0))
    lag_dq = cmath.phase(d.advance(T, T_L).i_s_ab * cmath.exp(-1j * eps_end) / i_dq)
    d = make_drive("ideal", state)
    d.set_setpoints(Setpoints("ab", i_dq * cmath.exp(1j * (eps_0 + w_0 * T / 2))))
    lag_ab = cmath.phase(d.advance(T, T_L).i_s_ab * cmath.exp(-1j * eps_end) / i_dq)
    assert lag_dq == pytest.approx(0.0, abs=1e-12)
    assert lag_ab == pytest.approx(-w_0 * T / 2, rel=1e-9)  # lags, by 0.1 rad


def test_frame_keeps_turning_without_new_setpoints() -> None:
    sp = Setpoints("dq", 4.0 + 1.0j, 0j, 0.4, 150.0)
    a, b, c = make_drive("ideal"), make_drive("ideal"), make_drive("current-loop")
    a.set_setpoints(sp)
    a.advance(2e-3, 0.5)
    b.set_setpoints(sp)
    b.advance(1e-3, 0.5)
    b.advance(1e-3, 0.5)
    assert b.state.psi_r_ab == pytest.approx(a.state.psi_r_ab, rel=1e-12)
    assert b.state.i_s_ab == pytest.approx(a.state.i_s_ab, rel=1e-12)
    assert b.state.i_s_ab == pytest.approx(sp.i_s_ref * cmath.exp(1j * (0.4 + 150.0 * 2e-3)))
    # a re-sent setpoint with the advanced angle continues the same frame
    c.set_setpoints(sp)
    c.advance(1e-3, 0.5)
    c.set_setpoints(Setpoints("dq", sp.i_s_ref, 0j, 0.4 + 150.0 * 1e-3, 150.0))
    c.advance(1e-3, 0.5)
    c2 = make_drive("current-loop")
    c2.set_setpoints(sp)
    c2.advance(2e-3, 0.5)
    assert c.state.i_s_ab == pytest.approx(c2.state.i_s_ab, rel=1e-9)


def test_ideal_disabled_means_zero_current() -> None:
    state, T_L, _ = steady_state(4.0 + 2.0j, 100.0, 0.0)
    d = Drive(MOTOR, DriveParams(mode="ideal"), state)  # disabled
    d.set_setpoints(Setpoints("dq", 4.0 + 2.0j, 0j, 0.0, 100.0))
    meas = d.advance(1e-2, T_L)
    assert meas.i_s_ab == 0j and meas.T_e == 0.0
    assert abs(meas.psi_r_ab) == pytest.approx(abs(state.psi_r_ab) * math.exp(-MOTOR.alpha * 1e-2))
    assert meas.w_m == pytest.approx(state.w_m - T_L / MOTOR.J * 1e-2)


# ---- voltage mode -----------------------------------------------------------------------------
def test_voltage_mode_matches_solve_ivp() -> None:
    x0 = MotorState(60.0, 0.5 + 0.2j, 1.0 - 2.0j)
    u, T_L = 150.0 + 80.0j, 1.2
    d = make_drive("voltage", x0)
    d.set_setpoints(Setpoints("ab", 0j, u))
    run(d, 20, 1e-3, T_L)
    sol = solve_ivp(rhs_full, (0, 0.02), [60.0, 0.5, 0.2, 1.0, -2.0], args=(MOTOR, u, T_L),
                    rtol=1e-10, atol=1e-12, method="DOP853")
    s = d.state
    got = [s.w_m, s.psi_r_ab.real, s.psi_r_ab.imag, s.i_s_ab.real, s.i_s_ab.imag]
    assert got == pytest.approx(list(sol.y[:, -1]), abs=1e-8)
    assert abs(s.i_s_ab - x0.i_s_ab) > 1.0


def test_voltage_limit_is_circular_and_reported() -> None:
    u_lim = DriveParams().u_lim
    d = make_drive("voltage")
    d.set_setpoints(Setpoints("ab", 0j, 1000.0 * cmath.exp(0.3j)))
    meas = d.advance(1e-4, 0.0)
    assert meas.limit_active
    assert meas.u_s_ab == pytest.approx(u_lim * cmath.exp(0.3j), rel=1e-12)
    d.set_setpoints(Setpoints("ab", 0j, 100.0 - 50.0j))
    meas = d.advance(1e-3, 0.0)
    assert not meas.limit_active
    assert meas.u_s_ab == pytest.approx(100.0 - 50.0j, rel=1e-12)


def test_voltage_mode_turns_dq_voltage() -> None:
    u_dq, eps_0, w_0, T = 200.0 + 50.0j, 1.1, 300.0, 1e-3
    d = make_drive("voltage")
    d.set_setpoints(Setpoints("dq", 0j, u_dq, eps_0, w_0))
    meas = d.advance(T, 0.0)
    x = w_0 * T
    continuous = u_dq * cmath.exp(1j * eps_0) * (cmath.exp(1j * x) - 1) / (1j * x)
    assert meas.u_s_ab == pytest.approx(continuous, rel=1e-4)
    # exactly: each step holds the vector at the step's midpoint angle
    n = round(T / H)
    zoh = sum(cmath.exp(1j * (eps_0 + w_0 * H * (k + 0.5))) for k in range(n)) / n
    assert meas.u_s_ab == pytest.approx(u_dq * zoh, rel=1e-12)


# ---- current loop ----------------------------------------------------------------------------
def test_pi_gains() -> None:
    K_p, K_i = pi_gains(MOTOR, DriveParams())
    bw = 2 * math.pi * 1500
    assert K_p == pytest.approx(MOTOR.sigma * (1 - math.exp(-bw * H)) / H)
    assert K_i / K_p == pytest.approx(MOTOR.R_eff / MOTOR.sigma)


def test_current_loop_step_bandwidth_above_1kHz() -> None:
    """Small-signal step (K_p·0.4 A ≈ 140 V: below the voltage limit)."""
    d = make_drive("current-loop")
    d.set_setpoints(Setpoints("dq", 0.4 + 0j, 0j, 0.0, 0.0))
    meas = run(d, 20, H, 0.0)
    i = [m.i_s_ab for m in meas]
    assert not any(m.limit_active for m in meas)
    assert i[1].real >= 0.63 * 0.4  # 63 % within 0.2 ms: bandwidth ≥ 1 kHz
    assert 0.5 * 0.4 < i[0].real < 0.7 * 0.4  # 1 − e^{−ω_bw·h} = 0.61 after one step
    assert max(x.real for x in i) < 1.01 * 0.4  # no overshoot
    assert i[-1] == pytest.approx(0.4, abs=0.002)
    assert max(abs(x.imag) for x in i) < 0.004


def test_current_loop_tracks_turning_setpoints_at_speed() -> None:
    """At 100 rad/s in steady state the loop holds the (d, q) currents, with and without
    the voltage feedforward (the integrator then supplies the back-EMF)."""
    i_dq, w_0, T = 4.0 + 3.0j, 120.0, 1e-3
    state, T_L, u_dq = steady_state(i_dq, w_0, 0.0)
    # with the exact feedforward the loop has nothing to correct: this checks the ZOH
    # voltage is rotated with the step's midpoint angle (the start angle gives ~1e-3)
    for u_ff, n_settle, tol in [(u_dq, 0, 1e-4), (0j, 40, 0.005)]:
        d = make_drive("current-loop", state)
        errs = []
        for k in range(60):
            d.set_setpoints(Setpoints("dq", i_dq, u_ff, w_0 * k * T, w_0))
            meas = d.advance(T, T_L)
            errs.append(abs(meas.i_s_ab * cmath.exp(-1j * w_0 * (k + 1) * T) - i_dq))
        assert max(errs[n_settle:]) < tol * abs(i_dq)
        assert not meas.limit_active
        # the applied voltage matches the exact ideal-mode average within 1 %
        d_ideal = make_drive("ideal", d.state)
        d_ideal.set_setpoints(Setpoints("dq", i_dq, 0j, w_0 * 60 * T, w_0))
        ideal = d_ideal.advance(T, T_L)
        d.set_setpoints(Setpoints("dq", i_dq, u_ff, w_0 * 60 * T, w_0))
        assert d.advance(T, T_L).u_s_ab == pytest.approx(ideal.u_s_ab, rel=0.01)
    assert errs[0] > 0.05 * abs(i_dq)  # without feedforward the integrator had work to do


def test_current_loop_saturates_without_windup() -> None:
    """A 20 A step from rest needs ~3 ms at the limit; afterwards no overshoot."""
    u_lim = DriveParams().u_lim
    d = make_drive("current-loop")
    d.set_setpoints(Setpoints("dq", 20.0 + 0j, 0j, 0.0, 0.0))
    meas = run(d, 150, H, 0.0)
    assert meas[0].limit_active and meas[10].limit_active
    assert all(abs(m.u_s_ab) <= u_lim * (1 + 1e-12) for m in meas)
    n_sat = max(k for k, m in enumerate(meas) if m.limit_active)
    assert 15 < n_sat < 60
    i_d = [m.i_s_ab.real for m in meas]
    assert max(i_d) < 20.0 * 1.02  # anti-windup: no large overshoot after saturation
    assert i_d[-1] == pytest.approx(20.0, abs=0.02)
    assert not meas[-1].limit_active and not d.tripped


# ---- disabled power stage and trip ---------------------------------------------------------
def test_disabled_stage_freewheels_to_zero_then_coasts() -> None:
    i_dq, w_0 = 6.0 + 4.0j, 150.0
    state, T_L, _ = steady_state(i_dq, w_0, 0.0)
    d = Drive(MOTOR, DriveParams(mode="current-loop"), state)  # disabled
    i_0 = state.i_s_ab
    meas = run(d, 40, H, T_L)
    seq = [i_0] + [m.i_s_ab for m in meas]
    # the diodes apply −u_lim·i/|i|: the current falls, never reverses, stops at 0
    assert all(abs(b) <= abs(a) + 1e-12 for a, b in itertools.pairwise(seq))
    assert all((b * a.conjugate()).real >= 0.0 for a, b in itertools.pairwise(seq))
    first = meas[0]
    assert (first.u_s_ab * i_0.conjugate()).real < -0.99 * abs(first.u_s_ab) * abs(i_0)
    assert abs(first.u_s_ab) == pytest.approx(DriveParams().u_lim, rel=1e-9)
    k0 = next(k for k, m in enumerate(meas) if m.i_s_ab == 0j)
    assert 5 < k0 < 30
    assert all(m.i_s_ab == 0j for m in meas[k0:])
    # open stator: the flux decays with α, the rotor coasts under T_L
    a, b = meas[k0], meas[-1]
    dt = (len(meas) - 1 - k0) * H
    assert abs(b.psi_r_ab) == pytest.approx(abs(a.psi_r_ab) * math.exp(-MOTOR.alpha * dt))
    assert b.w_m == pytest.approx(a.w_m - T_L / MOTOR.J * dt)
    assert b.T_e == 0.0
    # the reported voltage is the back-EMF (M/L_r)·dψ_r/dt of the open stator
    emf = (MOTOR.M / MOTOR.L_r) * (b.psi_r_ab - meas[-2].psi_r_ab) / H
    assert b.u_s_ab == pytest.approx(emf, rel=1e-9)


def test_over_current_trips_the_stage() -> None:
    d = make_drive("voltage")
    d.set_setpoints(Setpoints("ab", 0j, 300.0))  # 300 V / 5.3 Ω ≫ 25 A
    meas = run(d, 30, 1e-3, 0.0)
    assert d.tripped and not d.enabled
    assert max(abs(m.i_s_ab) for m in meas) < 25.0 + 1.0
    assert meas[-1].i_s_ab == 0j
    d.enable(True)
    assert not d.tripped and d.enabled


def test_ideal_over_current_setpoint_trips() -> None:
    d = make_drive("ideal")
    d.set_setpoints(Setpoints("dq", 30.0 + 0j))
    assert d.advance(1e-3, 0.0).i_s_ab == 0j
    assert d.tripped


# ---- sensors --------------------------------------------------------------------------------
def test_ideal_current_source_regulates_the_measured_current() -> None:
    """A perfect current loop makes the *measured* current equal the setpoint, so
    the sensor errors land in the true current (before: in the measurement only)."""
    p = {"i_offset_ab": 0.2 - 0.1j, "i_gain_error": 0.03}
    d = make_drive("ideal", **p)
    d.set_setpoints(Setpoints("ab", 4.0 - 2.0j))
    meas = d.advance(1e-3, 0.0)
    assert meas.i_s_ab == pytest.approx(4.0 - 2.0j, rel=1e-12)
    assert d.state.i_s_ab == pytest.approx((4.0 - 2.0j - (0.2 - 0.1j)) / 1.03, rel=1e-12)


@pytest.mark.parametrize("mode", ["ideal", "current-loop"])
def test_phase_sensor_gain_and_offset_in_measured_and_true_current(mode: str) -> None:
    """Phase-b sensor 2 % high, phase-a offset: measured = S·true + offset (three-phase
    sensors, Clarke), and the current control regulates the measured value."""
    off = complex(0.01, 0.01 / math.sqrt(3.0))  # 10 mA on the phase-a sensor, in (a, b)
    d = make_drive(mode, i_offset_ab=off, i_gain_phase=(0.0, 0.02))
    d.set_setpoints(Setpoints("ab", 3.0 + 1.0j, (3.0 + 1.0j) * MOTOR.R_s))
    for _ in range(50):
        meas = d.advance(1e-3, 0.0)
    i = d.state.i_s_ab
    i_a, i_b = i.real, -0.5 * i.real + 0.5 * math.sqrt(3.0) * i.imag
    m_a, m_b = i_a + 0.01, 1.02 * i_b
    expected = complex(m_a, (m_a + 2.0 * m_b) / math.sqrt(3.0))
    assert meas.i_s_ab == pytest.approx(expected + (off - 0.01 * (1 + 1j / math.sqrt(3.0))),
                                        abs=1e-9)
    assert meas.i_s_ab == pytest.approx(3.0 + 1.0j, abs=2e-3)  # regulated: measured = setpoint
    assert abs(i - (3.0 + 1.0j)) > 0.01  # the true current carries the sensor error


def test_sensor_errors_leave_exact_sensors_bit_identical() -> None:
    """Zero sensor and inverter errors take the original path: identical results."""
    state, T_L, u_dq = steady_state(4.0 + 2.0j, 100.0, 0.2)
    a = make_drive("current-loop", state)
    b = make_drive("current-loop", state, i_gain_phase=(0.0, 0.0), dead_time=0.0)
    for d in (a, b):
        d.set_setpoints(Setpoints("dq", 4.5 + 2.0j, u_dq, 0.2, 100.0))
    assert run(a, 20, 1e-3, T_L) == run(b, 20, 1e-3, T_L)


def test_dead_time_and_ripple_change_the_applied_not_the_reported_voltage() -> None:
    d0 = make_drive("voltage")
    d1 = make_drive("voltage", dead_time=2e-6, u_dc_ripple=0.05)
    for d in (d0, d1):
        d.set_setpoints(Setpoints("ab", 0j, 30.0 + 0j))
    m0, m1 = run(d0, 1000, 1e-3, 0.0)[-1], run(d1, 1000, 1e-3, 0.0)[-1]
    assert m1.u_s_ab == m0.u_s_ab  # the drive reports its commanded voltage
    du = 2e-6 * 10e3 * 560.0  # 11.2 V per phase; current along +a: i_a > 0, i_b = i_c < 0
    # steady state: (30 − (4/3)·du·…)/R_s; the a-axis error is −(2/3)(du + du/2 + du/2)
    assert m1.i_s_ab.real == pytest.approx((30.0 - 4.0 / 3.0 * du) / MOTOR.R_s, rel=0.01)
    assert m0.i_s_ab.real == pytest.approx(30.0 / MOTOR.R_s, rel=2e-3)


def test_load_function_is_applied_within_the_period() -> None:
    """A dynamometer torque that ramps within the period is integrated at the internal rate,
    not held: with T_L(t) = 100·t N·m over 10 ms, ω falls by ∫T_L/J."""
    d = make_drive("ideal", load=None)
    d.load = lambda t, T_L: 100.0 * t
    d.advance(1e-2, 0.0)
    assert d.state.w_m == pytest.approx(-0.5 * 100.0 * 1e-4 / MOTOR.J, rel=1e-9)
    held = make_drive("ideal")
    held.advance(1e-2, 0.5)  # the held mean torque gives the same end speed ...
    assert held.state.w_m == pytest.approx(d.state.w_m, rel=1e-9)


def test_motor_drift_changes_the_plant_over_time() -> None:
    d = make_drive("voltage", motor_drift={"R_s": 0.5})
    d0 = make_drive("voltage")
    for x in (d, d0):
        x.set_setpoints(Setpoints("ab", 0j, 30.0 + 0j))
    m, m0 = run(d, 1000, 1e-3, 0.0)[-1], run(d0, 1000, 1e-3, 0.0)[-1]
    # R_s × 1.5 at 1 s; the current lags the drifting resistance by the stator time constant
    assert m.i_s_ab.real == pytest.approx(30.0 / (1.5 * MOTOR.R_s), rel=0.03)
    assert m0.i_s_ab.real == pytest.approx(30.0 / MOTOR.R_s, rel=2e-3)


def test_sensor_noise_statistics_and_seed() -> None:
    d = make_drive("ideal", i_noise_rms=0.1, seed=7)
    d.set_setpoints(Setpoints("ab", 2.0 + 1.0j))
    noise = [m.i_s_ab - (2.0 + 1.0j) for m in run(d, 2000, 1e-4, 0.0)]
    for part in ([z.real for z in noise], [z.imag for z in noise]):
        assert statistics.pstdev(part) == pytest.approx(0.1, rel=0.08)
        assert abs(statistics.fmean(part)) < 0.01
    d.reset()
    d.enable(True)
    d.set_setpoints(Setpoints("ab", 2.0 + 1.0j))
    assert d.advance(1e-4, 0.0).i_s_ab - (2.0 + 1.0j) == noise[0]  # reset re-seeds
    other = make_drive("ideal", i_noise_rms=0.1, seed=8)
    other.set_setpoints(Setpoints("ab", 2.0 + 1.0j))
    assert other.advance(1e-4, 0.0).i_s_ab - (2.0 + 1.0j) != noise[0]


def test_measurement_carries_truth() -> None:
    state, T_L, u_dq = steady_state(4.0 + 2.0j, 100.0, 0.2)
    d = make_drive("current-loop", state, u_dc=600.0, i_offset_ab=0.5)
    d.set_setpoints(Setpoints("dq", 4.0 + 2.0j, u_dq, 0.2, 100.0))
    meas = d.advance(1e-3, T_L)
    s = d.state
    assert meas.u_dc == 600.0
    assert (meas.w_m, meas.psi_r_ab) == (s.w_m, s.psi_r_ab)
    assert meas.T_e == pytest.approx(torque(MOTOR, s.psi_r_ab, s.i_s_ab), rel=1e-12)
    # the measurement carries the 0.5 A offset; the current loop regulates the measured value
    # (a sensor error), so the true current is off by −0.5 A and T_e ≠ T_L
    assert meas.i_s_ab - s.i_s_ab == pytest.approx(0.5, abs=1e-12)
