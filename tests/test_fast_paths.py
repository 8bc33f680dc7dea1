"""The controller's and the references' fast paths give the plain expressions' numbers, bit
for bit (signed zeros included: compared by repr): the (d, q) interval model against the
general one, the model kept from a step's prediction against the one computed again, the
references' constant stretches against the signals' own evaluation, the reference window
against the profile, a Command built through its slots against its constructor.

(tools/same_signals.py compares whole runs against the code before the fast paths.)
"""

from __future__ import annotations

import cmath
import math
import random
from dataclasses import fields
from types import SimpleNamespace

import pytest

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

    monkeypatch.setattr(sampled, "cmath", SimpleNamespace(exp=cmath.exp, sqrt=sqrt))
    for k, s in enumerate(_samples(), start=1):
        refs = prof.at(k * T)
        if k % 37 == 0:
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
            if k > fast._d:
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
