"""The first-order linear recursion y_k = q·y_{k−1} + g·x_k (y_{−1} = 0) along an array's
last axis, in numpy: the rotor model of the standstill identification (its (I1)) and its
derivative in α are such filters.

SciPy's ``lfilter`` computes the same, but importing ``scipy.signal`` takes 0.5–1 s, which
every run that builds a controller with the identification paid, in real time too. Here the
recursion is solved in closed form block by block, y_{s+j} = q^j·(g·Σ_{i≤j} q^{−i}·x_{s+i})
+ q^{j+1}·y_{s−1}, the blocks short enough that q^{−i} stays below e³ (the rounding of the
sum then stays within a few units of the last place of the result).

Pure module: no I/O, no global state.
"""

from __future__ import annotations

import math

import numpy as np

#: the largest q^{−i} within a block (its length: ln(SPAN)/(−ln q) samples)
SPAN = math.exp(3.0)


def first_order(x: np.ndarray, q: float, g: float = 1.0) -> np.ndarray:
    """y with y_k = q·y_{k−1} + g·x_k along the last axis of ``x``, from y_{−1} = 0, for
    0 ≤ q < 1 (a decay per sample, e^{−α·T})."""
    x = np.asarray(x)
    if not 0.0 <= q < 1.0:
        raise ValueError(f"q = {q!r}: the recursion decays, 0 ≤ q < 1")
    if q == 0.0:
        return g * x
    n = x.shape[-1]
    block = max(1, int(math.log(SPAN) / -math.log(q)))
    out = np.empty(np.broadcast(x, 1.0 * g).shape, dtype=np.result_type(x, 1.0))
    k = np.arange(min(block, n), dtype=float)
    ln_q = math.log(q)
    down = np.exp(k * ln_q)  # q^j
    up = np.exp(-k * ln_q)  # q^{−j}
    carry = None
    for s in range(0, n, block):
        m = min(block, n - s)
        y = down[:m] * np.cumsum(x[..., s:s + m] * up[:m], axis=-1)
        if g != 1.0:
            y = g * y
        if carry is not None:
            y = y + (q * down[:m]) * carry[..., None]
        out[..., s:s + m] = y
        carry = y[..., -1]
    return out
