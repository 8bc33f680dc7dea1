"""Reference profiles ω*(t), ψ*(t) > 0 and T_L(t) with analytic first and second derivatives.

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

Profiles are TOML files (Python's :mod:`tomllib`)::

    [units]                    # required; values below are converted to SI
    time = "s"                 # "s" | "ms"
    speed = "rad/s"            # "rad/s" | "rpm"
    flux = "Wb"                # "Wb" | "mWb"
    torque = "N*m"             # "N*m" | "N·m" | "Nm"

    [profile]
    name = "paper"
    description = "..."        # optional
    duration = 2.5             # in the time unit, > 0

    [speed]                    # ω*, required
    initial = 0.0
    steps = [{ t = 0.32, value = 100.0, ramp = 0.18 }]

    [flux]                     # ψ* > 0, required
    initial = 0.001
    steps = [{ t = 0.0, value = 1.16, ramp = 0.3 }]

    [load]                     # T_L, optional (zero when omitted); initial defaults to 0
    steps = [{ t = 0.5, value = 5.8, ramp = 0.01 }]

Rules: ``ramp`` > 0; step ``t`` ≥ 0 and not before the previous ramp has ended (t_i ≥
t_{i−1} + ramp_{i−1}, so start times are strictly increasing); every ramp ends by
``duration``. Before t = 0 a signal holds its initial value, after ``duration`` its last one.
Any mistake raises :class:`ProfileError` (a :class:`ValueError`) naming the file, the key
path, what is wrong and how to fix it.

:func:`demand` estimates the peak stator current and voltage a profile asks of a motor
under perfect tracking (open-loop references (9)–(11)).

Units: SI (s, rad/s, Wb, N·m, A, V). Pure module: no clock, no global mutable state.
"""

from __future__ import annotations

import math
import tomllib
from bisect import bisect_right
from collections.abc import Mapping
from dataclasses import dataclass, field
from importlib import resources
from pathlib import Path
from types import MappingProxyType
from typing import Any, Protocol

import numpy as np

__all__ = [
    "Demand",
    "Profile",
    "ProfileError",
    "References",
    "SetPoint",
    "Signal",
    "Step",
    "demand",
    "demand_trace",
    "load_profile",
    "paper_profile",
    "parse_profile",
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
        t0, inv, v0, dv, k1, k2, v1, t1 = self._segs[bisect_right(self._starts, t) - 1]
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
    """The three references of a run: speed ω*, rotor-flux modulus ψ* > 0, load torque T_L.

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

    def __post_init__(self) -> None:
        if not (self.duration > 0.0 and math.isfinite(self.duration)):
            raise ProfileError(f"{self.source}: duration = {self.duration!r} must be > 0 s")
        bad = [v for v in self.flux.values() if not v > 0.0]
        if bad:
            raise ProfileError(
                f"{self.source}: flux value {bad[0]!r} Wb: the flux reference must stay > 0 "
                f"(ψ* > 0 is required by (15)); use positive values"
            )

    def at(self, t: float) -> References:
        """All references at time t (s). Pure Python, about 1–2 µs per call."""
        w, dw, ddw = self.speed.at(t)
        p, dp, ddp = self.flux.at(t)
        tl, dtl, _ = self.load.at(t)
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


# ------------------------------------------------------------------------------ TOML input

_TIME_UNITS = MappingProxyType({"s": 1.0, "ms": 1e-3})
_SPEED_UNITS = MappingProxyType({"rad/s": 1.0, "rpm": 2.0 * math.pi / 60.0})
_FLUX_UNITS = MappingProxyType({"Wb": 1.0, "mWb": 1e-3})
_TORQUE_UNITS = MappingProxyType({"N*m": 1.0, "N·m": 1.0, "Nm": 1.0})
_UNIT_TABLES = MappingProxyType({
    "time": _TIME_UNITS, "speed": _SPEED_UNITS, "flux": _FLUX_UNITS, "torque": _TORQUE_UNITS,
})
_TABLES = ("units", "profile", "speed", "flux", "load")
_SIGNAL_UNIT = MappingProxyType({"speed": "speed", "flux": "flux", "load": "torque"})
_SI_NAME = MappingProxyType({"speed": "rad/s", "flux": "Wb", "load": "N·m"})


def _fail(src: str, where: str, msg: str) -> ProfileError:
    return ProfileError(f"{src}: {where}{': ' if where else ''}{msg}")


def _keys(src: str, where: str, data: Mapping[str, Any], valid: tuple[str, ...]) -> None:
    for key in data:
        if key not in valid:
            raise _fail(
                src, f"{where}.{key}" if where else f"[{key}]",
                f"unknown {'key' if where else 'table'}; valid "
                f"{'keys' if where else 'tables'} here are {', '.join(valid)} "
                f"(fix the spelling or remove it)",
            )


def _table(src: str, data: Mapping[str, Any], name: str, required: bool) -> dict | None:
    value = data.get(name)
    if value is None:
        if required:
            raise _fail(src, f"[{name}]", f"missing section; add a [{name}] table")
        return None
    if not isinstance(value, dict):
        raise _fail(src, f"{name} = {value!r}", f"must be a table: write it as a [{name}] section")
    return value


def _number(src: str, where: str, value: Any, unit: str) -> float:
    if isinstance(value, bool) or not isinstance(value, int | float):
        raise _fail(src, f"{where} = {value!r}",
                    f"must be a number (in {unit}), e.g. {where.split('.')[-1]} = 1.0")
    x = float(value)
    if not math.isfinite(x):
        raise _fail(src, f"{where} = {value!r}", f"must be a finite number (in {unit})")
    return x


def _units(src: str, data: Mapping[str, Any], need_torque: bool) -> dict[str, float]:
    units = _table(src, data, "units", required=True)
    assert units is not None
    _keys(src, "[units]", units, tuple(_UNIT_TABLES))
    out: dict[str, float] = {}
    for key, table in _UNIT_TABLES.items():
        if key not in units:
            if key == "torque" and not need_torque:
                continue
            raise _fail(
                src, f"[units].{key}",
                f"missing; add {key} = {next(iter(table))!r} (one of {', '.join(table)})",
            )
        name = units[key]
        if not isinstance(name, str) or name not in table:
            raise _fail(
                src, f"[units].{key} = {name!r}",
                f"unknown unit; use one of {', '.join(repr(u) for u in table)}",
            )
        out[key] = table[name]
    return out


def _signal(src: str, name: str, tab: Mapping[str, Any], units: Mapping[str, Any],
            raw_units: Mapping[str, Any], duration: float, positive: bool) -> Signal:
    where = f"[{name}]"
    _keys(src, where, tab, ("initial", "steps"))
    vunit_name = str(raw_units.get(_SIGNAL_UNIT[name], _SI_NAME[name]))
    tunit_name = str(raw_units["time"])
    vscale = units.get(_SIGNAL_UNIT[name], 1.0)
    tscale = units["time"]

    def value(w: str, raw: Any) -> float:
        x = _number(src, w, raw, vunit_name) * vscale
        if positive and not x > 0.0:
            raise _fail(
                src, f"{w} = {raw!r}",
                f"the flux reference must stay > 0 (ψ* > 0 is required by (15)); "
                f"use a positive value in {vunit_name}",
            )
        return x

    if "initial" in tab:
        initial = value(f"{where}.initial", tab["initial"])
    elif name == "load":
        initial = 0.0
    else:
        raise _fail(src, f"{where}.initial", f"missing; add initial = <value in {vunit_name}>")
    raw_steps = tab.get("steps", [])
    if not isinstance(raw_steps, list):
        raise _fail(
            src, f"{where}.steps = {raw_steps!r}",
            "must be an array of tables, e.g. steps = [{ t = 0.5, value = 1.0, ramp = 0.1 }]",
        )
    steps: list[Step] = []
    prev_end = 0.0
    prev_where = ""
    for i, raw in enumerate(raw_steps):
        w = f"{where}.steps[{i}]"
        if not isinstance(raw, dict):
            raise _fail(
                src, f"{w} = {raw!r}",
                "must be a table { t = ..., value = ..., ramp = ... }",
            )
        _keys(src, w, raw, ("t", "value", "ramp"))
        for key in ("t", "value", "ramp"):
            if key not in raw:
                raise _fail(src, f"{w}.{key}", "missing; every step needs t, value and ramp")
        t_raw, ramp_raw = raw["t"], raw["ramp"]
        t = _number(src, f"{w}.t", t_raw, tunit_name) * tscale
        v = value(f"{w}.value", raw["value"])
        ramp = _number(src, f"{w}.ramp", ramp_raw, tunit_name) * tscale
        if t < 0.0:
            raise _fail(src, f"{w}.t = {t_raw!r}", "must be ≥ 0; transitions start at or after 0")
        if not ramp > 0.0:
            raise _fail(
                src, f"{w}.ramp = {ramp_raw!r}",
                f"must be > 0: a jump has no derivative and the laws need C² references "
                f"(docs/paper.md §E7); use a short ramp, e.g. ramp = {0.01 / tscale:g} "
                f"({tunit_name})",
            )
        if t < prev_end * (1.0 - 1e-12):
            raise _fail(
                src, f"{w}.t = {t_raw!r}",
                f"starts before the previous transition ({prev_where}) ends at "
                f"{prev_end / tscale:g} {tunit_name}; step times must increase and a "
                f"transition may start only when the previous ramp has ended — move t to "
                f"≥ {prev_end / tscale:g} or shorten the previous ramp",
            )
        t = max(t, prev_end)
        if t + ramp > duration * (1.0 + 1e-12):
            raise _fail(
                src, f"{w}",
                f"the transition ends at {(t + ramp) / tscale:g} {tunit_name}, after the "
                f"profile's end ([profile].duration = {duration / tscale:g} {tunit_name}); "
                f"raise the duration or move/shorten the step",
            )
        steps.append(Step(t, v, ramp))
        prev_end, prev_where = t + ramp, w
    return Signal(initial, tuple(steps))


def parse_profile(text: str, source: str = "<string>") -> Profile:
    """A :class:`Profile` from TOML text (see the module docstring for the format).

    ``source`` names the text in error messages and becomes :attr:`Profile.source`.
    """
    src = source
    try:
        data = tomllib.loads(text)
    except tomllib.TOMLDecodeError as exc:
        raise ProfileError(f"{src}: not valid TOML: {exc}; fix the syntax") from None
    _keys(src, "", data, _TABLES)
    load_tab = _table(src, data, "load", required=False)
    units = _units(src, data, need_torque=load_tab is not None)
    raw_units = data["units"]
    prof = _table(src, data, "profile", required=True)
    assert prof is not None
    _keys(src, "[profile]", prof, ("name", "description", "duration"))
    name = prof.get("name", Path(source).stem if source[:1] != "<" else "profile")
    if not isinstance(name, str) or not name:
        raise _fail(src, f"[profile].name = {name!r}",
                    'must be a non-empty string, e.g. name = "paper"')
    description = prof.get("description", "")
    if not isinstance(description, str):
        raise _fail(src, f"[profile].description = {description!r}", "must be a string")
    tunit = str(raw_units["time"])
    if "duration" not in prof:
        raise _fail(src, "[profile].duration",
                    f"missing; add duration = <length of the run in {tunit}>")
    duration_raw = prof["duration"]
    duration = _number(src, "[profile].duration", duration_raw, tunit) * units["time"]
    if not duration > 0.0:
        raise _fail(src, f"[profile].duration = {duration_raw!r}",
                    f"must be > 0; give the length of the run in {tunit}")
    signals: dict[str, Signal] = {}
    for sig in ("speed", "flux", "load"):
        tab = load_tab if sig == "load" else _table(src, data, sig, required=True)
        if tab is None:
            signals[sig] = Signal(0.0)
            continue
        signals[sig] = _signal(src, sig, tab, units, raw_units, duration, positive=sig == "flux")
    return Profile(name, duration, signals["speed"], signals["flux"], signals["load"],
                   source=source, description=description)


def load_profile(path: str | Path) -> Profile:
    """Read a profile TOML file; :class:`ProfileError` (naming the file) on any problem."""
    src = str(path)
    try:
        text = Path(path).read_bytes().decode("utf-8")
    except FileNotFoundError:
        raise ProfileError(
            f"{src}: no such file; give the path of a profile TOML file "
            f"(shipped ones are in profiles/, e.g. profiles/paper.toml)"
        ) from None
    except OSError as exc:
        raise ProfileError(f"{src}: cannot read the file ({exc.strerror})") from None
    except UnicodeDecodeError as exc:
        raise ProfileError(f"{src}: not UTF-8 text ({exc.reason}); save it as UTF-8") from None
    return parse_profile(text, src)


def paper_profile() -> Profile:
    """The paper's section-6 scenario (package data ``gateway/profiles/paper.toml``).

    Its :attr:`Profile.source` is "<embedded>"; it equals ``load_profile("profiles/paper.toml")``.
    """
    text = resources.files("gateway").joinpath("profiles", "paper.toml").read_text("utf-8")
    return parse_profile(text, "<embedded>")


# ---------------------------------------------------------------------------------- demand


class MotorLike(Protocol):
    """What :func:`demand` needs of a motor (``plant.params.MotorParams``), SI units."""

    J: float
    R_s: float
    R_r: float
    L_s: float
    L_r: float
    M: float

    @property
    def alpha(self) -> float: ...
    @property
    def mu(self) -> float: ...
    @property
    def sigma(self) -> float: ...


@dataclass(frozen=True, slots=True)
class Demand:
    """Peaks a profile demands of a motor under perfect tracking (SI units).

    i_s_peak (A) at t_i_s_peak (s): max |i_s| = |(i_sd*, i_sq*)| of (9), (10).
    u_s_peak (V) at t_u_s_peak (s): max |u_s| from the stator flux in the rotating frame.
    w_peak (rad/s): max |ω*|; w_0_peak (rad/s): max |ω0| of (11) (electrical frequency).
    T_e_peak (N·m) at t_T_e_peak (s): max |T_e| = |J·ω̇* + T_L|.
    i_sd_peak, i_sq_peak (A): max |i_sd*|, max |i_sq*|.
    """

    i_s_peak: float
    t_i_s_peak: float
    u_s_peak: float
    t_u_s_peak: float
    w_peak: float
    w_0_peak: float
    T_e_peak: float
    t_T_e_peak: float
    i_sd_peak: float
    i_sq_peak: float


def sample_times(profile: Profile, dt: float | None = None, max_points: int = 200_000
                 ) -> np.ndarray:
    """Times to sample ``profile`` at, s: a uniform grid of step ``dt`` (default 1e-4 s or
    1/200 of the shortest ramp if smaller) when that takes at most ``max_points``;
    otherwise every transition at step ``dt`` (at most 2000 points each) and the constant
    stretches between them coarsely, so a long profile (``duration = 1e7``) costs megabytes,
    not gigabytes, and no transition is skipped."""
    steps = [s for sig in (profile.speed, profile.flux, profile.load) for s in sig.steps]
    if dt is None:
        dt = min([1e-4, *(s.ramp / 200.0 for s in steps)])
    duration = profile.duration
    n = max(2, math.ceil(duration / dt) + 1)
    if n <= max_points:
        return np.linspace(0.0, duration, n)
    parts = [np.linspace(0.0, duration, max(2, max_points // 4))]
    for s in steps:
        if s.t < duration:
            end = min(s.end, duration)
            parts.append(np.linspace(s.t, end, min(2000, max(3, math.ceil((end - s.t) / dt)))))
    return np.unique(np.concatenate(parts))


def demand_trace(profile: Profile, motor: MotorLike, dt: float | None = None
                 ) -> dict[str, np.ndarray]:
    """Open-loop currents, frame speed and voltages along ``profile`` on a fine grid.

    Grid (:func:`sample_times`) of step ``dt`` (s): by default 1e-4 s or 1/200 of the
    shortest ramp if smaller; long profiles get a dense grid only on their transitions.
    Perfect tracking (ω = ω*, ψ_rd = ψ*, ψ_rq = 0):
      i_sd* = ψ*/M + ψ̇*/(αM)                  (9)
      i_sq* = (T_L/J + ω̇*)/(μψ*)              (10)
      ω0 = ω* + αM·i_sq*/ψ*                     (11)
      ψ_sd = σ·i_sd* + (M/L_r)·ψ*,  ψ_sq = σ·i_sq*   (stator flux, §E1)
      u_sd = dψ_sd/dt + R_s·i_sd* − ω0·ψ_sq,  u_sq = dψ_sq/dt + R_s·i_sq* + ω0·ψ_sd
    with dψ_s/dt by central finite differences (numpy.gradient) on the grid.
    Keys: t, w_ref, psi_ref, T_L, i_sd, i_sq, w_0, u_sd, u_sq, T_e (N·m).
    """
    t = sample_times(profile, dt)
    r = profile.sample(t)
    m = motor
    alpha, mu, sigma, M = m.alpha, m.mu, m.sigma, m.M
    psi = r["psi_ref"]
    i_sd = psi / M + r["dpsi_ref"] / (alpha * M)
    i_sq = (r["T_L"] / m.J + r["dw_ref"]) / (mu * psi)
    w_0 = r["w_ref"] + alpha * M * i_sq / psi
    psi_sd = sigma * i_sd + (M / m.L_r) * psi
    psi_sq = sigma * i_sq
    u_sd = np.gradient(psi_sd, t) + m.R_s * i_sd - w_0 * psi_sq
    u_sq = np.gradient(psi_sq, t) + m.R_s * i_sq + w_0 * psi_sd
    T_e = m.J * r["dw_ref"] + r["T_L"]
    return {"t": t, "w_ref": r["w_ref"], "psi_ref": psi, "T_L": r["T_L"], "i_sd": i_sd,
            "i_sq": i_sq, "w_0": w_0, "u_sd": u_sd, "u_sq": u_sq, "T_e": T_e}


def demand(profile: Profile, motor: MotorLike, dt: float | None = None) -> Demand:
    """Peak current, voltage, speed and torque ``profile`` asks of ``motor`` (see
    :func:`demand_trace`). Compare i_s_peak with the drive's trip level and u_s_peak with
    its voltage limit u_dc/√3 before running a profile."""
    d = demand_trace(profile, motor, dt)
    t = d["t"]
    i_s = np.hypot(d["i_sd"], d["i_sq"])
    u_s = np.hypot(d["u_sd"], d["u_sq"])
    T_e = np.abs(d["T_e"])
    ki, ku, kt = int(np.argmax(i_s)), int(np.argmax(u_s)), int(np.argmax(T_e))
    return Demand(
        i_s_peak=float(i_s[ki]), t_i_s_peak=float(t[ki]),
        u_s_peak=float(u_s[ku]), t_u_s_peak=float(t[ku]),
        w_peak=float(np.max(np.abs(d["w_ref"]))), w_0_peak=float(np.max(np.abs(d["w_0"]))),
        T_e_peak=float(T_e[kt]), t_T_e_peak=float(t[kt]),
        i_sd_peak=float(np.max(np.abs(d["i_sd"]))), i_sq_peak=float(np.max(np.abs(d["i_sq"]))),
    )
