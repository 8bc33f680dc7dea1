"""The controller's, the references' and the drive model's fast paths give the plain
expressions' numbers, bit for bit (signed zeros included: compared by repr): the (d, q)
interval model against the general one, the model kept from a step's prediction against the
one computed again, the references' constant stretches against the signals' own evaluation,
the reference window against the profile, a Command built through its slots against its
constructor; the drive's fused internal steps (float locals) against one RK4 call per step
on complex scalars, a Measurement built through its slots against its constructor.

(tools/same_signals.py compares whole runs against the code before the fast paths.)
"""

from __future__ import annotations

import cmath
import math
import random
from dataclasses import fields
from types import SimpleNamespace

import pytest

from dbc.modes import SetpointFrame
from dbc.motor import MotorParams
from dbc.timing import Sampling
from gateway.control import sampled
from gateway.control.controller import ControllerConfig, Sample, wrap_angle
from gateway.control.interface import Command, make_command
from gateway.control.refwindow import ReferenceWindow
from gateway.control.sampled import (
    FullOrderSampledController,
    Interval,
    SampledController,
    make_controller,
)
from gateway.reference import load_profile, paper_profile
from gateway.reference.signals import _make_references
from plant.drive import (
    Drive,
    Measurement,
    MotorState,
    Setpoints,
    _mean_turning,
    _measurement,
)
from plant.motor import rk4_step_current_fed, rk4_step_full
from plant.params import DriveParams

MOTOR = MotorParams.paper()


def same(a: object, b: object) -> bool:
    """Equal to the last bit, the sign of a zero and NaN included."""
    return repr(a) == repr(b)


def _controller(**kw) -> SampledController:
    cfg = ControllerConfig(discretisation="exact", **kw)
    ctl = make_controller(MOTOR, cfg, paper_profile().at)
    assert isinstance(ctl, SampledController)
    return ctl


def _values(rnd: random.Random) -> float:
    return rnd.choice([rnd.uniform(-300.0, 300.0), rnd.uniform(-1e-3, 1e-3), 0.0, -0.0])


def test_the_dq_interval_model_is_the_general_one():
    ctl = _controller()
    rnd = random.Random(1)
    for _ in range(3000):
        i_dq = complex(_values(rnd), _values(rnd))
        c = Interval(i_dq, 0j, rnd.uniform(-math.pi, math.pi), _values(rnd))
        psi0 = complex(_values(rnd), _values(rnd))
        w_m = _values(rnd)
        fast = ctl._interval_dq(c.i_dq, c.w_0, psi0, w_m)
        plain = ctl._interval(c, psi0, w_m, [(c.i_dq, 0j)])
        assert same(fast, plain), (c, psi0, w_m)
        assert same(ctl._current_dq(c), ctl._current(c, [(c.i_dq, 0j)])), c


def test_the_frame_rotation_is_the_conjugate_of_the_last_steps():
    """The full-order step takes e^{jε} of the last step's ε_k (not a zero) as the conjugate
    of that step's e^{−jε_k}."""
    rnd = random.Random(2)
    angles = [rnd.uniform(-math.pi, math.pi) for _ in range(100000)]
    angles += [rnd.uniform(-1e-6, 1e-6) for _ in range(10000)]
    angles += [math.pi, -math.pi, math.nextafter(-math.pi, 0.0), 5e-324, -5e-324, 1e-300]
    angles += [wrap_angle(rnd.uniform(-1e3, 1e3)) for _ in range(10000)]
    for eps in angles:
        assert same(cmath.exp(-1j * eps).conjugate(), cmath.exp(1j * eps)), eps
    # the zeros are left out: -0.0's would not be
    assert not same(cmath.exp(-1j * -0.0).conjugate(), cmath.exp(1j * -0.0))


def _samples(n: int = 700) -> list[Sample]:
    """Currents and voltages of a plausible run (a turning field, its flux, noise-free)."""
    out = []
    for k in range(1, n + 1):
        t = k * 1e-3
        w = 100.0 * min(1.0, t / 0.3)
        ang = 0.5 * w * t
        i = (3.0 + 2.0 * min(1.0, t / 0.2)) * cmath.exp(1j * (ang + 0.3))
        u = 150.0 * min(1.0, t / 0.3) * cmath.exp(1j * (ang + 0.9))
        out.append(Sample(i, u, min(1.16, 4.0 * t) * cmath.exp(1j * ang)))
    return out


@pytest.mark.parametrize("kw", [
    {}, {"flux": "true"}, {"estimator": "drift-free"}, {"estimator": "rs-adaptive"},
    {"identify": True},
    {"sampling": Sampling(1e-3, 1, "ab")}, {"sampling": Sampling(1e-3, 0, "dq")},
    {"current_lag": 1 / 2000}, {"law": "full-order"},
    {"law": "full-order", "sampling": Sampling(1e-3, 0, "dq")},
], ids=lambda kw: ",".join(f"{k}={v}" for k, v in kw.items()) or "default")
def test_the_kept_prediction_is_the_model_computed_again(kw, monkeypatch):
    """Every step with the kept model equals the same step with the model computed again,
    through coasts and withheld commands; the frame angle the command carried is the one
    the frame turned to."""
    prof = paper_profile()
    fast, plain = _controller(**kw), _controller(**kw)
    T = fast._T
    models = {"fast": 0, "plain": 0}
    for who, ctl in (("fast", fast), ("plain", plain)):
        for name in ("_interval", "_interval_dq"):
            real = getattr(ctl, name)
            setattr(ctl, name, lambda *a, _r=real, _w=who: (models.__setitem__(
                _w, models[_w] + 1), _r(*a))[1])
    turn = {"who": "fast"}

    def sqrt(z):  # the full-order law's matrix exponentials (expm2, inline or not)
        models[turn["who"]] += 1
        return cmath.sqrt(z)

    monkeypatch.setattr(sampled, "cmath", SimpleNamespace(exp=cmath.exp, sqrt=sqrt,
                                                          phase=cmath.phase))
    coasted = -100
    for k, s in enumerate(_samples(), start=1):
        refs = prof.at(k * T)
        if k % 37 == 0:
            coasted = k
            turn["who"] = "fast"
            fast.coast()
            turn["who"] = "plain"
            plain._kept = None
            plain.coast()
        else:
            turn["who"] = "fast"
            got = fast.step(refs, s)
            turn["who"] = "plain"
            plain._kept = None  # nothing kept: the model is computed again
            assert same(got, plain.step(refs, s)), k
            if k % 53 == 0:
                fast.withhold()
                plain.withhold()
        assert same((fast.w_hat, fast.eps_0), (plain.w_hat, plain.eps_0)), k
        hist = fast._hist
        for a, b in zip(list(hist)[:-1], list(hist)[1:], strict=True):
            # continuous, but for the command after a coast: its frame is set on the flux
            if k > fast._d and k - coasted > fast._d + 1:
                assert same(b.eps, wrap_angle(a.eps + T * a.w_0)), k
    assert isinstance(fast, FullOrderSampledController) == (kw.get("law") == "full-order")
    if fast._d:  # one model per step instead of two
        assert models["fast"] < 0.7 * models["plain"], models


@pytest.mark.parametrize("name", ["paper", "quick", "zero-speed", "slow-reversal"])
def test_constant_stretches_are_the_signals_values(name):
    prof = paper_profile() if name == "paper" else load_profile(f"profiles/{name}.toml")
    ts = [k * 2.5e-4 for k in range(-40, int(prof.duration / 2.5e-4) + 40)]
    for sig in (prof.speed, prof.flux, prof.load):
        for st in sig.steps:
            ts += [st.t, st.end, math.nextafter(st.t, -math.inf), math.nextafter(st.end, math.inf),
                   math.nextafter(st.end, -math.inf)]
    ts += [-math.inf, math.inf, 1e300]
    for t in ts:
        w, p, tl = prof.speed.at(t), prof.flux.at(t), prof.load.at(t)
        assert same(prof.at(t), _make_references(*w, *p, tl[0], tl[1])), t
    assert all(math.isnan(x) for x in (prof.at(math.nan).w_ref, prof.at(math.nan).T_L))


def test_the_reference_window_is_the_profile():
    prof = paper_profile()
    calls = []

    def at(t: float):
        calls.append(t)
        return prof.at(t)

    T = 1e-3
    win = ReferenceWindow(at, T, 6)
    for n0 in (0, 2, 4, 5, 7, 9, 11, 30, 32, 3):
        got = win.starting(n0)
        assert len(got) == 6
        for i, r in enumerate(got):
            assert same(r, prof.at(0.5 * (n0 + i) * T)), (n0, i)
    # sliding by one step evaluates two new instants only
    calls.clear()
    win.starting(5)
    assert calls == [0.5 * 9 * T, 0.5 * 10 * T]


def test_a_command_built_through_its_slots_is_the_constructors():
    args = (1 + 2j, -3j, -0.5, 123.0, 0.25 - 1j, 7 + 0j, True, (1.0, 2.0, -0.0, 4.0))
    fast, plain = make_command(*args), Command(*args)
    assert fast == plain
    assert [getattr(fast, f.name) for f in fields(Command)] == [
        getattr(plain, f.name) for f in fields(Command)]


# ---- the drive model's fused internal steps ---------------------------------------------------
class _ReferenceDrive(Drive):
    """The drive with its internal steps written plainly, on complex scalars, one call of
    :func:`plant.motor.rk4_step_full` / :func:`rk4_step_current_fed` per step (the code
    before the steps were fused onto float locals)."""

    def _turning(self, n: int) -> tuple[complex, complex, complex]:
        rot, (sa, sb, ha, hb) = self._frame(n)
        return rot, complex(sa, sb), complex(ha, hb)

    def _advance_ideal(self, n: int, T_L: float) -> complex:
        c, h, sp = self._c, self._h, self._sp
        psi_s_start = c.sigma * self._i + c.M_over_L_r * self._psi
        if self._enabled and abs(sp.i_s_ref) > self.params.i_trip:
            self._trip()
        if self._enabled:
            rot, step, half = self._turning(n)
            turning = _mean_turning(sp.w_0 * n * h) if sp.frame is SetpointFrame.DQ else 1.0
            mean_i = sp.i_s_ref * rot * turning
            w, psi = self._w, self._psi
            i0 = sp.i_s_ref * rot
            if self._exact_sensors and self.load is None:
                for _ in range(n):
                    i1 = i0 * step
                    w, psi = rk4_step_current_fed(c, w, psi, i0, i0 * half, i1, T_L, h)
                    i0 = i1
                self._w, self._psi, self._i = w, psi, i0
            else:
                un = self._unsense
                mean_i = un(mean_i)
                for k in range(n):
                    i1 = i0 * step
                    w, psi = rk4_step_current_fed(c, w, psi, un(i0), un(i0 * half), un(i1),
                                                  self._torque(k, T_L), h)
                    i0 = i1
                self._w, self._psi, self._i = w, psi, un(i0)
        else:
            mean_i = 0j
            self._i = 0j
            self._open_circuit(n * h, self._torque(0.5 * n - 0.5, T_L))
        psi_s_end = c.sigma * self._i + c.M_over_L_r * self._psi
        return (psi_s_end - psi_s_start) / (n * h) + c.R_s * mean_i

    def _run_inverter(self, n: int, T_L: float) -> tuple[int, complex, bool]:
        if self._loop:
            return self._run_current_loop(n, T_L)
        return self._run_voltage(n, T_L)

    def _run_current_loop(self, n: int, T_L: float) -> tuple[int, complex, bool]:
        c, h = self._c, self._h
        rot, step, half = self._turning(n)
        i_ref, u_ff = self._sp.i_s_ref, self._sp.u_s_ref
        K_p, K_i_h = self._K_p, self._K_i * h
        h_over_T_i = K_i_h / K_p
        u_lim = self.params.u_lim
        w, psi, i = self._w, self._psi, self._i
        x = self._x_ab * rot.conjugate()
        u_sum, limited, done = 0j, False, n
        plain = self._exact_sensors and not self._u_errors and self.load is None
        t0 = self._n * h
        for k in range(n):
            e = i_ref - (i if plain else self._sense(i)) * rot.conjugate()
            u = u_ff + K_p * e + x
            m2 = u.real * u.real + u.imag * u.imag
            if m2 > u_lim * u_lim:
                limited = True
                u *= u_lim / math.sqrt(m2)
                x += h_over_T_i * (u - u_ff - x)
            else:
                x += K_i_h * e
            u_ab = u * (rot * half)
            u_sum += u_ab
            if plain:
                w, psi, i = rk4_step_full(c, w, psi, i, u_ab, T_L, h)
            else:
                u_app = self._u_error(u_ab, i, t0 + (k + 0.5) * h) if self._u_errors else u_ab
                w, psi, i = rk4_step_full(c, w, psi, i, u_app, self._torque(k, T_L), h)
            rot *= step
            if i.real * i.real + i.imag * i.imag > self.params.i_trip**2:
                done = k + 1
                break
        self._w, self._psi, self._i = w, psi, i
        self._x_ab = x * rot
        if done < n:
            self._trip()
        return done, u_sum, limited

    def _run_voltage(self, n: int, T_L: float) -> tuple[int, complex, bool]:
        c, h = self._c, self._h
        rot, step, half = self._turning(n)
        u = self._sp.u_s_ref
        u_lim = self.params.u_lim
        limited = abs(u) > u_lim
        if limited:
            u *= u_lim / abs(u)
        w, psi, i = self._w, self._psi, self._i
        u_rot = u * rot * half
        u_sum, done = 0j, n
        plain = not self._u_errors and self.load is None
        t0 = self._n * h
        for k in range(n):
            u_sum += u_rot
            if plain:
                w, psi, i = rk4_step_full(c, w, psi, i, u_rot, T_L, h)
            else:
                u_app = self._u_error(u_rot, i, t0 + (k + 0.5) * h) if self._u_errors else u_rot
                w, psi, i = rk4_step_full(c, w, psi, i, u_app, self._torque(k, T_L), h)
            u_rot *= step
            if i.real * i.real + i.imag * i.imag > self.params.i_trip**2:
                done = k + 1
                break
        self._w, self._psi, self._i = w, psi, i
        if done < n:
            self._trip()
        return done, u_sum, limited


def _drive_run(cls: type[Drive], seed: int, mode: str) -> list[str]:
    """A random drive's life (sensor and inverter errors, a varying load, drift, trips,
    the limit, (d, q) and (a, b) setpoints, signed zeros): every sample, as repr."""
    rnd = random.Random(seed)
    kw: dict = {}
    if rnd.random() < 0.3:
        kw.update(i_noise_rms=0.01, i_gain_error=0.02, i_offset_ab=0.01 - 0.02j)
    if rnd.random() < 0.2:
        kw.update(i_gain_phase=(0.01, -0.02))
    if rnd.random() < 0.2:
        kw.update(dead_time=1e-6)
    if rnd.random() < 0.2:
        kw.update(u_dc_ripple=0.05)
    if rnd.random() < 0.2:
        kw.update(f_pwm=rnd.choice([8e3, 16e3]))
    if rnd.random() < 0.3:
        kw.update(i_trip=rnd.choice([5.0, 10.0]))
    params = DriveParams(mode=mode, **kw)
    load = (lambda t, T_L: T_L * (1.0 + 0.1 * math.sin(100.0 * t))) if rnd.random() < 0.2 else None
    drift = {"R_s": 0.1} if rnd.random() < 0.1 else None
    state = (MotorState() if rnd.random() < 0.3 else
             MotorState(0.5 * _values(rnd), complex(_values(rnd), _values(rnd)) * 0.005,
                        complex(_values(rnd), _values(rnd)) * 0.02))
    d = cls(MOTOR, params, state, load=load, motor_drift=drift)
    d.enable(rnd.random() < 0.9)
    out = []
    for _ in range(30):
        x = rnd.random()
        if x < 0.3:
            d.set_setpoints(Setpoints(
                rnd.choice(["dq", "ab"]), complex(_values(rnd), _values(rnd)) * 0.03,
                complex(_values(rnd), _values(rnd)) * 1.5, rnd.uniform(-4.0, 4.0),
                _values(rnd) if rnd.random() < 0.7 else 0.0))
        elif x < 0.35:
            d.set_references(Setpoints("dq", complex(_values(rnd), _values(rnd)) * 0.03,
                                       complex(_values(rnd), _values(rnd)) * 1.5))
        elif x < 0.38:
            d.enable(not d.enabled)
        m = d.advance(params.h * rnd.choice([1, 4, 10, 10, 25]), 0.01 * _values(rnd))
        out.append(repr((m, d.state, d.t, d.enabled, d.tripped, d._x_ab)))
    return out


@pytest.mark.parametrize("mode", ["ideal", "current-loop", "voltage"])
def test_the_drives_fused_steps_are_the_plain_rk4_steps(mode):
    """Drive's internal steps run fused on float locals: the same numbers as one
    rk4_step_* call per step on complex scalars, bit for bit."""
    for seed in range(60):
        assert _drive_run(Drive, seed, mode) == _drive_run(_ReferenceDrive, seed, mode), seed


def test_a_measurement_built_through_its_slots_is_the_constructors():
    args = (1 + 2j, -0.0 - 3j, 560.0, -0.0, 0.25 - 1j, 7.5, True)
    fast, plain = _measurement(*args), Measurement(*args)
    assert fast == plain and repr(fast) == repr(plain)


def test_setpoints_are_checked_as_before():
    sp = Setpoints("ab", 1, 2.5, 0, 3)  # numbers of any kind, the frame by its value
    assert sp.frame is SetpointFrame.AB and sp.i_s_ref == 1
    assert Setpoints(SetpointFrame.DQ).frame is SetpointFrame.DQ
    assert Setpoints("dq", "1+2j").i_s_ref == "1+2j"  # complex() reads it, as before
    for bad in ({"frame": "DQ"}, {"frame": ["dq"]}, {"i_s_ref": complex(math.inf, 0.0)},
                {"u_s_ref": math.nan}, {"eps_0": -math.inf}, {"w_0": complex(0.0, math.nan)}):
        with pytest.raises(ValueError):
            Setpoints(**bad)
