"""Reference signals ω*(t), ψ*(t) > 0 and T_L(t) with analytic first and second derivatives.

The laws of Marino, Tomei & Verrelli (IFAC 2002) need smooth references: (15) uses ψ̇* and
ω̇* (through (9), (10)), the full-order law (25)–(32) also ψ̈*, ω̈* and dT_L/dt in φ_d0, φ_q0
(§E7: references must be at least C²; §E6: T_L is treated as known). Every signal
here is a constant ``initial`` value followed by transitions to new set points. Each
transition starts at ``t`` and lasts ``ramp`` > 0 and follows the **quintic smoothstep**

    p(s) = 6s⁵ − 15s⁴ + 10s³,  s = (t − t_start)/ramp ∈ [0, 1],

whose first and second derivatives vanish at both ends (p′ = 30s²(1−s)², p″ = 60s(1−s)(1−2s)),
so the signal is C² everywhere (its third derivative jumps at the ramp ends). A transition
between two values stays between them (p is monotone), so ψ* > 0 as soon as the initial
value and every set point are > 0.

A reference profile (:class:`Profile`) is the three signals of a run and its duration;
its file format is in :mod:`gateway.reference.toml`. Before t = 0 a signal holds its
initial value, after its last transition its final one.

Units: SI (s, rad/s, Wb, N·m). Pure module: no I/O, no clock, no global mutable state.
"""

from __future__ import annotations

import math
from bisect import bisect_right
from dataclasses import dataclass, field
from typing import Any

import numpy as np

__all__ = [
    "REFERENCE_KEYS",
    "Profile",
    "ProfileError",
    "References",
    "SetPoint",
    "Signal",
    "Step",
]


class ProfileError(ValueError):
    """An invalid profile: the message names the file, the key path, the problem and the fix."""


# ---------------------------------------------------------------------------------- values


@dataclass(frozen=True, slots=True)
class References:
    """The references of one instant, SI units.

    w_ref, dw_ref, ddw_ref: ω* (rad/s), dω*/dt (rad/s²), d²ω*/dt² (rad/s³).
    psi_ref, dpsi_ref, ddpsi_ref: ψ* > 0 (Wb), ψ̇* (Wb/s), ψ̈* (Wb/s²).
    T_L, dT_L: load torque (N·m) and its derivative (N·m/s), known to the laws (§E6).
    """

    w_ref: float
    dw_ref: float
    ddw_ref: float
    psi_ref: float
    dpsi_ref: float
    ddpsi_ref: float
    T_L: float
    dT_L: float


REFERENCE_KEYS: tuple[str, ...] = (
    "w_ref", "dw_ref", "ddw_ref", "psi_ref", "dpsi_ref", "ddpsi_ref", "T_L", "dT_L",
)

# Fast construction of References for Profile.at: the generated __init__ of a frozen dataclass
# calls object.__setattr__ per field (≈1.3 µs for 8 fields); writing the slots through their
# member descriptors on a bare instance is about twice as fast and gives an equal object.
_SET_REFS = tuple(References.__dict__[k].__set__ for k in REFERENCE_KEYS)


def _make_references(
    w: float, dw: float, ddw: float, p: float, dp: float, ddp: float, tl: float, dtl: float,
    _new: Any = object.__new__, _cls: type = References, _s: tuple = _SET_REFS,
) -> References:
    r = _new(_cls)
    _s[0](r, w); _s[1](r, dw); _s[2](r, ddw); _s[3](r, p)  # noqa: E702
    _s[4](r, dp); _s[5](r, ddp); _s[6](r, tl); _s[7](r, dtl)  # noqa: E702
    return r


def with_flux(r: References, psi: float, dpsi: float, ddpsi: float) -> References:
    """``r`` with its flux references ψ*, ψ̇*, ψ̈* replaced (as ``dataclasses.replace``,
    about ten times faster: a controller whose flux references are shifted calls it at
    every reference it takes)."""
    return _make_references(r.w_ref, r.dw_ref, r.ddw_ref, psi, dpsi, ddpsi, r.T_L, r.dT_L)


@dataclass(frozen=True, slots=True)
class Step:
    """One transition of a :class:`Signal`, SI units: from the previous value to ``value``,
    starting at ``t`` (s) and lasting ``ramp`` > 0 (s), quintic smoothstep."""

    t: float
    value: float
    ramp: float

    @property
    def end(self) -> float:
        """t + ramp, s: when the transition is complete."""
        return self.t + self.ramp


@dataclass(frozen=True, slots=True)
class SetPoint:
    """One line of :meth:`Profile.set_points`: a signal's initial value or one transition.

    signal: "speed", "flux" or "load"; unit: the SI unit of the values.
    t_start, t_end: when the transition starts and ends, s (both 0 for the initial value).
    start, end: the values before and after, SI.
    """

    signal: str
    t_start: float
    t_end: float
    start: float
    end: float
    unit: str
    initial: bool = False

    def __str__(self) -> str:
        if self.initial:
            return f"{self.signal:<5}  initial            {self.end:g} {self.unit}"
        span = f"{self.t_start:.4g}–{self.t_end:.4g} s"
        return f"{self.signal:<5}  {span:<17}  {self.start:g} → {self.end:g} {self.unit}"


# ---------------------------------------------------------------------------------- signal


def _on(seg: tuple[float, float, float, float, float, float, float, float], t: float
        ) -> tuple[float, float, float]:
    """(x, ẋ, ẍ) at t (s) on one segment of :attr:`Signal._segs` (the one t falls in)."""
    t0, inv, v0, dv, k1, k2, v1, t1 = seg
    if t >= t1:
        return v1, 0.0, 0.0
    s = (t - t0) * inv
    s2 = s * s
    u = 1.0 - s
    return (
        v0 + dv * s2 * s * (10.0 + s * (6.0 * s - 15.0)),
        k1 * 30.0 * s2 * u * u,
        k2 * 60.0 * s * u * (1.0 - 2.0 * s),
    )


@dataclass(frozen=True, slots=True, eq=False)
class Signal:
    """A piecewise-C² signal: ``initial`` then quintic-smoothstep transitions (``steps``).

    Evaluation: :meth:`at` (scalar, pure Python: bisect + a few multiplications) and
    :meth:`sample` (NumPy arrays). Both return (value, first derivative, second derivative).
    Two signals are equal when their initial values and steps are.
    """

    initial: float
    steps: tuple[Step, ...] = ()
    # Segment table for evaluation: segment 0 is a dummy "transition" at −∞ holding the
    # initial value, so that bisect always finds a segment for finite t.
    _starts: list[float] = field(init=False, repr=False)
    _segs: list[tuple[float, float, float, float, float, float, float, float]] = field(
        init=False, repr=False
    )

    def __post_init__(self) -> None:
        initial = float(self.initial)
        steps = tuple(self.steps)
        prev_end = -math.inf
        for i, s in enumerate(steps):
            if not (s.ramp > 0.0 and math.isfinite(s.ramp)):
                raise ProfileError(f"Signal: steps[{i}].ramp = {s.ramp!r} must be > 0 s")
            if not s.t >= prev_end:
                raise ProfileError(
                    f"Signal: steps[{i}].t = {s.t!r} starts before the previous transition "
                    f"ends at {prev_end!r} s"
                )
            if not (math.isfinite(s.t) and math.isfinite(s.value)):
                raise ProfileError(f"Signal: steps[{i}] = {s!r} must be finite")
            prev_end = s.t + s.ramp
        object.__setattr__(self, "initial", initial)
        object.__setattr__(self, "steps", steps)
        starts = [-math.inf]
        # (t0, 1/ramp, v0, dv, dv/ramp, dv/ramp², end value, end time)
        segs = [(-math.inf, 1.0, initial, 0.0, 0.0, 0.0, initial, -math.inf)]
        v = initial
        for s in steps:
            dv = s.value - v
            inv = 1.0 / s.ramp
            starts.append(s.t)
            segs.append((s.t, inv, v, dv, dv * inv, dv * inv * inv, float(s.value), s.end))
            v = float(s.value)
        object.__setattr__(self, "_starts", starts)
        object.__setattr__(self, "_segs", segs)

    def __eq__(self, other: object) -> bool:
        if not isinstance(other, Signal):
            return NotImplemented
        return self.initial == other.initial and self.steps == other.steps

    def __hash__(self) -> int:
        return hash((self.initial, self.steps))

    @property
    def final(self) -> float:
        """The value after the last transition."""
        return self._segs[-1][6]

    def values(self) -> tuple[float, ...]:
        """The initial value and every set point."""
        return (self.initial, *(s.value for s in self.steps))

    def at(self, t: float) -> tuple[float, float, float]:
        """(x, ẋ, ẍ) at time t (s): exact values of the quintic smoothstep."""
        return _on(self._segs[bisect_right(self._starts, t) - 1], t)

    def sample(self, t: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Vectorised :meth:`at`: (x, ẋ, ẍ) as float arrays of the shape of ``t``."""
        t = np.asarray(t, dtype=float)
        seg = np.array(self._segs, dtype=float)  # columns t0, inv, v0, dv, k1, k2, v1
        idx = np.searchsorted(np.asarray(self._starts), t, side="right") - 1
        idx = np.clip(idx, 0, None)
        t0, inv, v0, dv, k1, k2 = (seg[idx, j] for j in range(6))
        with np.errstate(invalid="ignore"):
            s = np.where(idx == 0, 1.0, np.clip((t - np.where(idx == 0, 0.0, t0)) * inv, 0, 1))
        u = 1.0 - s
        x = v0 + dv * s**3 * (10.0 + s * (6.0 * s - 15.0))
        dx = k1 * 30.0 * s * s * u * u
        ddx = k2 * 60.0 * s * u * (1.0 - 2.0 * s)
        return x, dx, ddx


# --------------------------------------------------------------------------------- profile


@dataclass(frozen=True, slots=True)
class Profile:
    """A reference profile: the three references of a run, speed ω*, rotor-flux modulus
    ψ* > 0 and load torque T_L.

    name: a short name; duration: length of the run, s; source: the file it came from, or
    "<embedded>" for :func:`paper_profile` (not part of equality); description: free text.
    """

    name: str
    duration: float
    speed: Signal
    flux: Signal
    load: Signal = field(default_factory=lambda: Signal(0.0))
    source: str = field(default="<embedded>", compare=False)
    description: str = field(default="", compare=False)

    # The stretches between the transitions' starts and ends: their boundaries and, per
    # stretch, its References when all three signals are constant there (built once), or
    # None and the segment of each signal (Signal._segs) that holds there.
    _bounds: list[float] = field(init=False, repr=False, compare=False)
    _still: list[References | None] = field(init=False, repr=False, compare=False)
    _moving: list[tuple] = field(init=False, repr=False, compare=False)

    def __post_init__(self) -> None:
        if not (self.duration > 0.0 and math.isfinite(self.duration)):
            raise ProfileError(f"{self.source}: duration = {self.duration!r} must be > 0 s")
        bad = [v for v in self.flux.values() if not v > 0.0]
        if bad:
            raise ProfileError(
                f"{self.source}: flux value {bad[0]!r} Wb: the flux reference must stay > 0 "
                f"(ψ* > 0 is required by (15)); use positive values"
            )
        signals = (self.speed, self.flux, self.load)
        bounds = sorted({-math.inf, *(x for sig in signals for seg in sig._segs[1:]
                                      for x in (seg[0], seg[7]))})
        still: list[References | None] = []
        moving: list[tuple] = []
        for lo in bounds:
            # no transition starts inside [lo, next bound): each signal's segment there is
            # the one at lo, and the signal is constant there iff that segment has ended by
            # lo (then _on gives (v1, 0.0, 0.0), the numbers built here)
            segs = tuple(sig._segs[bisect_right(sig._starts, lo) - 1] for sig in signals)
            moving.append(segs)
            still.append(_make_references(segs[0][6], 0.0, 0.0, segs[1][6], 0.0, 0.0,
                                          segs[2][6], 0.0)
                         if all(lo >= seg[7] for seg in segs) else None)
        # t beyond the last bound, +inf or NaN: each Signal.at decides
        object.__setattr__(self, "_bounds", [*bounds, math.inf])
        object.__setattr__(self, "_still", [*still, None])
        object.__setattr__(self, "_moving", [*moving, None])

    def at(self, t: float) -> References:
        """All references at time t (s). Pure Python, about 1–2 µs per call during a
        transition; between transitions (every signal constant) one bisection."""
        n = bisect_right(self._bounds, t) - 1
        r = self._still[n]
        if r is not None:
            return r
        segs = self._moving[n]
        if segs is None:
            w, dw, ddw = self.speed.at(t)
            p, dp, ddp = self.flux.at(t)
            tl, dtl, _ = self.load.at(t)
        else:
            w, dw, ddw = _on(segs[0], t)
            p, dp, ddp = _on(segs[1], t)
            tl, dtl, _ = _on(segs[2], t)
        return _make_references(w, dw, ddw, p, dp, ddp, tl, dtl)

    def sample(self, t: np.ndarray) -> dict[str, np.ndarray]:
        """Vectorised :meth:`at`: arrays keyed like the fields of :class:`References`."""
        w, dw, ddw = self.speed.sample(t)
        p, dp, ddp = self.flux.sample(t)
        tl, dtl, _ = self.load.sample(t)
        return dict(zip(REFERENCE_KEYS, (w, dw, ddw, p, dp, ddp, tl, dtl), strict=True))

    def set_points(self) -> list[SetPoint]:
        """The initial values and every transition, in time order (for ``profile check``)."""
        out: list[SetPoint] = []
        for name, sig, unit in (("speed", self.speed, "rad/s"), ("flux", self.flux, "Wb"),
                                ("load", self.load, "N·m")):
            out.append(SetPoint(name, 0.0, 0.0, sig.initial, sig.initial, unit, initial=True))
            v = sig.initial
            for s in sig.steps:
                out.append(SetPoint(name, s.t, s.end, v, s.value, unit))
                v = s.value
        order = {"speed": 0, "flux": 1, "load": 2}
        out.sort(key=lambda sp: (not sp.initial, sp.t_start, order[sp.signal]))
        return out
