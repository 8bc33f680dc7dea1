"""Model (1) (plant/motor.py) and the parameters (plant/params.py)."""

from __future__ import annotations

import cmath
import math
import random

import numpy as np
import pytest
from scipy.integrate import solve_ivp

from dbc.motor import MotorParams, ParamsError
from plant.motor import (
    coeffs,
    derivs_full,
    magnetic_energy,
    rhs_current_fed,
    rhs_full,
    rk4_step_current_fed,
    rk4_step_full,
    rotor_current,
    stator_flux,
    torque,
)
from plant.params import DriveParams

MOTOR = MotorParams.paper()


# ---- parameters ---------------------------------------------------------------------------
def test_paper_motor_and_derived_parameters() -> None:
    m = MOTOR
    assert (m.J, m.R_s, m.R_r, m.L_s, m.L_r, m.M) == (0.0075, 5.3, 3.3, 0.365, 0.375, 0.34)
    # §E1: both forms of σ
    assert m.sigma == pytest.approx(m.L_s * (1.0 - m.M**2 / (m.L_s * m.L_r)), rel=1e-14)
    assert m.sigma == pytest.approx(0.0567333333, rel=1e-9)
    assert m.alpha == pytest.approx(3.3 / 0.375)
    assert m.beta == pytest.approx(0.34 / (m.sigma * 0.375))
    assert m.mu == pytest.approx(0.34 / (0.0075 * 0.375))
    assert m.R_eff == pytest.approx(5.3 + 3.3 * (0.34 / 0.375) ** 2)


def test_drive_params_defaults() -> None:
    d = DriveParams()
    assert d.f_pwm == 10e3 and d.h == pytest.approx(1e-4)
    assert d.u_lim == pytest.approx(560.0 / math.sqrt(3.0))
    assert d.i_trip == 25.0 and d.current_loop_bw == pytest.approx(2 * math.pi * 1500)


def test_motor_from_toml(tmp_path) -> None:
    path = tmp_path / "motor.toml"
    path.write_text("J = 0.01\nR_s = 4\n")
    m = MotorParams.from_toml(path)
    assert m.J == 0.01 and m.R_s == 4.0 and m.L_r == MOTOR.L_r
    path.write_text("[motor]\nM = 0.3\n")
    assert MotorParams.from_toml(path, table="motor").M == 0.3


@pytest.mark.parametrize(
    ("text", "words"),
    [
        ("Rs = 5.3\n", ["motor.toml", "'Rs'", "R_s", "spelling"]),
        ("R_r = -1.0\n", ["motor.toml", "R_r", "positive", "> 0"]),
        ("J = 0\n", ["motor.toml", "J", "positive"]),
        ("L_r = 'x'\n", ["motor.toml", "L_r", "not a number"]),
        ("M = 0.4\n", ["motor.toml", "M = 0.4", "M² ≥ L_s·L_r", "lower M"]),
        ("J = [\n", ["motor.toml", "TOML"]),
    ],
)
def test_motor_params_errors_name_file_key_and_fix(tmp_path, text: str, words: list[str]) -> None:
    path = tmp_path / "motor.toml"
    path.write_text(text)
    with pytest.raises(ParamsError) as exc:
        MotorParams.from_toml(path)
    for w in words:
        assert w in str(exc.value)


def test_motor_params_missing_file_and_table(tmp_path) -> None:
    with pytest.raises(ParamsError, match=r"nope\.toml: cannot read"):
        MotorParams.from_toml(tmp_path / "nope.toml")
    path = tmp_path / "m.toml"
    path.write_text("J = 0.01\n")
    with pytest.raises(ParamsError, match=r"no \[motor\] table"):
        MotorParams.from_toml(path, table="motor")
    with pytest.raises(ParamsError, match="MotorParams: M"):
        MotorParams(M=0.5)


@pytest.mark.parametrize(
    ("data", "key"),
    [
        ({"mode": "torch"}, "mode"),
        ({"f_pwm": 0}, "f_pwm"),
        ({"u_dc": -560}, "u_dc"),
        ({"i_trip": 0.0}, "i_trip"),
        ({"current_loop_bw": 40000.0}, "current_loop_bw"),
        ({"i_gain_error": -1.5}, "i_gain_error"),
        ({"i_noise_rms": -0.1}, "i_noise_rms"),
        ({"i_offset_ab": [1.0]}, "i_offset_ab"),
        ({"seed": 1.5}, "seed"),
        ({"f_pmw": 1e4}, "f_pmw"),
    ],
)
def test_drive_params_errors(data: dict, key: str) -> None:
    with pytest.raises(ParamsError) as exc:
        DriveParams.from_mapping(data, source="drive.toml")
    assert "drive.toml" in str(exc.value) and key in str(exc.value)


def test_drive_params_from_toml(tmp_path) -> None:
    path = tmp_path / "drive.toml"
    path.write_text('mode = "voltage"\nu_dc = 600\ni_offset_ab = [0.1, -0.2]\ni_trip = inf\n')
    d = DriveParams.from_toml(path)
    assert d.mode == "voltage" and d.u_dc == 600.0 and d.i_offset_ab == complex(0.1, -0.2)
    assert math.isinf(d.i_trip)


def _inductive_energy(m: MotorParams, psi: complex, i: complex) -> float:
    """½[i_s; i_r]ᵀ·[[L_s, M], [M, L_r]]·[i_s; i_r], J: from the inductance matrix."""
    i_r = rotor_current(m, psi, i)
    return 0.5 * (m.L_s * abs(i) ** 2 + 2 * m.M * (i * i_r.conjugate()).real
                  + m.L_r * abs(i_r) ** 2)


# ---- algebraic relations ------------------------------------------------------------------
def test_torque_flux_and_energy_relations() -> None:
    psi, i = 0.8 - 0.3j, 2.0 + 5.0j
    m = MOTOR
    # T_e = J·μ·(ψ_ra·i_sb − ψ_rb·i_sa)
    assert torque(m, psi, i) == pytest.approx(m.J * m.mu * (0.8 * 5.0 - (-0.3) * 2.0))
    assert torque(m, psi, i) > 0  # flux leading the current... i at +68°, ψ at −21°
    i_r = rotor_current(m, psi, i)
    assert psi == pytest.approx(m.L_r * i_r + m.M * i)
    assert stator_flux(m, psi, i) == pytest.approx(m.L_s * i + m.M * i_r)
    assert magnetic_energy(m, psi, i) == pytest.approx(_inductive_energy(m, psi, i), rel=1e-12)


def test_complex_form_matches_printed_rows() -> None:
    c = coeffs(MOTOR)
    rng = random.Random(1)
    for _ in range(20):
        w = rng.uniform(-300, 300)
        psi = complex(rng.uniform(-1, 1), rng.uniform(-1, 1))
        i = complex(rng.uniform(-10, 10), rng.uniform(-10, 10))
        u = complex(rng.uniform(-300, 300), rng.uniform(-300, 300))
        T_L = rng.uniform(-5, 5)
        dw, dpsi, di = derivs_full(c, w, psi, i, u, T_L)
        ref = rhs_full(0.0, [w, psi.real, psi.imag, i.real, i.imag], MOTOR, u, T_L)
        got = [dw, dpsi.real, dpsi.imag, di.real, di.imag]
        assert got == pytest.approx(ref, rel=1e-12, abs=1e-9)
        # rows 4–5 are dψ_s/dt = u − R_s·i_s (§E1)
        dpsi_s = c.sigma * di + c.M_over_L_r * dpsi
        assert dpsi_s == pytest.approx(u - MOTOR.R_s * i, rel=1e-12, abs=1e-9)


def test_current_fed_equilibrium_turns_at_frame_speed() -> None:
    """Slip relation (11): with ψ_r = M·i_sd on d and ω = ω0 − αM·i_sq/ψ_rd, T_e = T_L."""
    m = MOTOR
    i_dq, w_0, eps = 4.0 + 2.0j, 120.0, 0.7
    psi_rd = m.M * i_dq.real
    w_m = w_0 - m.alpha * m.M * i_dq.imag / psi_rd
    T_L = m.J * m.mu * psi_rd * i_dq.imag
    rot = cmath.exp(1j * eps)
    psi, i = psi_rd * rot, i_dq * rot
    d = rhs_current_fed(0.0, [w_m, psi.real, psi.imag], m, i, T_L)
    assert d[0] == pytest.approx(0.0, abs=1e-12)  # torque balance
    dpsi = 1j * w_0 * psi  # the flux vector turns with the frame, modulus constant
    assert d[1:] == pytest.approx([dpsi.real, dpsi.imag], rel=1e-12)
    assert torque(m, psi, i) == pytest.approx(T_L, rel=1e-12)


# ---- energy ----------------------------------------------------------------------------------
def _u_test(t: float) -> complex:
    return 250.0 * cmath.exp(1j * 2 * math.pi * 25.0 * t) + 30.0


def _augmented(t: float, x: np.ndarray, m: MotorParams, T_L: float) -> list[float]:
    u = _u_test(t)
    d = rhs_full(t, x[:5], m, u, T_L)
    w, i, psi = x[0], complex(x[3], x[4]), complex(x[1], x[2])
    i_r = rotor_current(m, psi, i)
    return [
        *d,
        (u * i.conjugate()).real,  # electrical input power u·i
        m.R_s * abs(i) ** 2,  # stator copper
        m.R_r * abs(i_r) ** 2,  # rotor copper
        T_L * w,  # mechanical power delivered to the load
    ]


def _stored(m: MotorParams, x: np.ndarray) -> float:
    psi, i = complex(x[1], x[2]), complex(x[3], x[4])
    return _inductive_energy(m, psi, i) + 0.5 * m.J * x[0] ** 2


def test_power_balance_along_a_trajectory() -> None:
    """∫u·i = ∫R_s|i_s|² + ∫R_r|i_r|² + ∫T_L·ω + Δ(magnetic + kinetic energy)."""
    m, T_L = MOTOR, 1.5
    x0 = np.array([20.0, 0.1, -0.2, 1.0, 0.5, 0, 0, 0, 0])
    sol = solve_ivp(_augmented, (0, 0.4), x0, args=(m, T_L), rtol=1e-11, atol=1e-12,
                    method="DOP853")
    x1 = sol.y[:, -1]
    e_in, cu_s, cu_r, mech = x1[5:]
    d_stored = _stored(m, x1) - _stored(m, x0)
    assert e_in > 50.0 and cu_r > 1.0 and abs(mech) > 1.0  # a non-trivial trajectory
    assert e_in == pytest.approx(cu_s + cu_r + mech + d_stored, rel=1e-8)


# ---- fixed-step RK4 vs scipy ----------------------------------------------------------------
X0 = (80.0, 0.6 - 0.4j, 3.0 + 1.0j)  # ω, ψ_r, i_s
U_DC, T_L_DC = 120.0 - 60.0j, 0.8


def _rk4_full(h: float, t_end: float) -> tuple[float, complex, complex]:
    c = coeffs(MOTOR)
    w, psi, i = X0
    for _ in range(round(t_end / h)):
        w, psi, i = rk4_step_full(c, w, psi, i, U_DC, T_L_DC, h)
    return w, psi, i


@pytest.fixture(scope="module")
def reference_full() -> np.ndarray:
    w, psi, i = X0
    sol = solve_ivp(rhs_full, (0, 0.1), [w, psi.real, psi.imag, i.real, i.imag],
                    args=(MOTOR, U_DC, T_L_DC), rtol=1e-10, atol=1e-12, method="DOP853")
    return sol.y[:, -1]


def _err(x: tuple[float, complex, complex], ref: np.ndarray) -> float:
    w, psi, i = x
    return float(np.max(np.abs(np.array([w, psi.real, psi.imag, i.real, i.imag]) - ref)))


def test_rk4_full_matches_solve_ivp(reference_full: np.ndarray) -> None:
    assert _err(_rk4_full(1e-4, 0.1), reference_full) < 1e-8
    # and the motion is not trivial: the state moved by much more than the tolerance
    assert abs(reference_full[0] - X0[0]) > 1.0


def test_rk4_full_is_fourth_order(reference_full: np.ndarray) -> None:
    e1 = _err(_rk4_full(2e-3, 0.1), reference_full)
    e2 = _err(_rk4_full(1e-3, 0.1), reference_full)
    e3 = _err(_rk4_full(5e-4, 0.1), reference_full)
    assert 12.0 < e1 / e2 < 20.0
    assert 12.0 < e2 / e3 < 20.0


def test_rk4_current_fed_matches_solve_ivp() -> None:
    """Turning current i_s(t) = i_amp·e^{jω0t} sampled by RK4 at start, midpoint and end."""
    c = coeffs(MOTOR)
    i_amp, w_0, T_L, h = 4.0 + 3.0j, 150.0, 1.0, 1e-4

    def i_s(t: float) -> complex:
        return i_amp * cmath.exp(1j * w_0 * t)

    sol = solve_ivp(lambda t, x: rhs_current_fed(t, x, MOTOR, i_s(t), T_L), (0, 0.2),
                    [50.0, 0.2, 0.1], rtol=1e-10, atol=1e-12, method="DOP853")
    w, psi = 50.0, 0.2 + 0.1j
    for k in range(2000):
        t = k * h
        w, psi = rk4_step_current_fed(c, w, psi, i_s(t), i_s(t + h / 2), i_s(t + h), T_L, h)
    assert [w, psi.real, psi.imag] == pytest.approx(list(sol.y[:, -1]), abs=1e-8)
    assert abs(w - 50.0) > 1.0
