"""gateway.control.recursion: the first-order recursion the identification's rotor model
uses, against SciPy's lfilter (which it replaces: importing scipy.signal cost every run
0.5–1 s)."""

from __future__ import annotations

import math

import numpy as np
import pytest
from import_support import loaded_after
from scipy.signal import lfilter

from gateway.control.recursion import first_order


def test_first_order_is_lfilter_to_the_last_places():
    rng = np.random.default_rng(7)
    for trial in range(200):
        n = int(rng.integers(1, 4000))
        q = math.exp(-rng.uniform(1e-6, 4.0))  # from a slow rotor at 1 µs to 4 per sample
        g = float(rng.uniform(0.05, 3.0))
        x = rng.normal(size=(2, n)) + 1j * rng.normal(size=(2, n)) + (3.0 if trial % 2 else 0)
        ref = lfilter([g], [1.0, -q], x, axis=1)
        got = first_order(x, q, g)
        assert got.shape == ref.shape
        np.testing.assert_allclose(got, ref, rtol=0, atol=1e-13 * np.max(np.abs(ref)))
    # one axis, real input, and the trivial decay
    x = rng.normal(size=50)
    np.testing.assert_allclose(first_order(x, 0.9), lfilter([1.0], [1.0, -0.9], x),
                               rtol=1e-13, atol=1e-15)
    np.testing.assert_array_equal(first_order(x, 0.0, 2.0), 2.0 * x)
    assert first_order(np.zeros((2, 0)), 0.5).shape == (2, 0)
    with pytest.raises(ValueError, match="decays"):
        first_order(x, 1.0)


def test_building_the_controllers_imports_no_scipy_signal():
    code = "import gateway.control.sampled, gateway.control.commissioning, gateway.control.identify"
    assert loaded_after(code, ("scipy.signal",)) == []
