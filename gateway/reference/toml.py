"""The reference profile file format: TOML, parsed and validated into a
:class:`gateway.reference.signals.Profile`.

Reference profiles are TOML files (Python's :mod:`tomllib`)::

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

Limits (:func:`reference_limits`): a value that cannot run is refused the same way. ω*
must fit the speed signals of the bus (``w_0`` in RPDO1, ``w_m`` in TPDO3 of ``drive.dbc``)
and stay within the emulated drive's over-speed limit ``w_max`` (0x2201:9 of ``drive.eds``,
beyond which it faults); ψ* must fit the rotor-flux signals (``psi_ra``, ``psi_rb``) and
T_L the load-torque signal (``T_L``). A transition stays between its end values, so checking
the initial value and every set point suffices. The numbers come from the DBC's scalings
and the EDS's default, not from this file. Demands that are merely high (current, voltage)
are not refused here: ``hil-gateway reference check`` warns about them.

The bundled reference profiles are package data in ``gateway/profiles/``
(:func:`paper_profile` reads ``paper.toml``). Values are converted to SI units.
"""

from __future__ import annotations

import configparser
import functools
import math
import tomllib
from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from importlib import resources
from pathlib import Path
from types import MappingProxyType
from typing import Any

from dbc.filecache import FileMemo, resolved
from gateway.reference.signals import Profile, ProfileError, Signal, Step

__all__ = ["ReferenceLimit", "load_profile", "paper_profile", "parse_profile",
           "reference_limits"]


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


_SYMBOL = MappingProxyType({"speed": "ω*", "flux": "ψ*", "load": "T_L"})
_LABEL = MappingProxyType({"speed": "speed reference", "flux": "flux reference",
                           "load": "load torque"})
#: The PDO signals (roles of ``drive.dbc``) that carry each reference or its consequence:
#: the frame speed and the measured speed, the rotor-flux components, the load torque.
_CARRIERS = MappingProxyType({"speed": ("w_0", "w_m"), "flux": ("psi_ra", "psi_rb"),
                              "load": ("T_L",)})


# ---------------------------------------------------------------------------------- limits


@dataclass(frozen=True, slots=True)
class ReferenceLimit:
    """A range a reference's values must stay within to run, SI units, and why.

    lo, hi: the range (SI: rad/s, Wb, N·m); what: the limit, for messages ("the range the
    bus carries it in (...)").
    """

    lo: float
    hi: float
    what: str

    def holds(self, x: float) -> bool:
        """Whether ``x`` (SI) is within the range."""
        return self.lo <= x <= self.hi


def _bus_limit(name: str) -> ReferenceLimit:
    """The range the PDO signals carrying reference ``name`` can represent (``drive.dbc``)."""
    from dbc.codec import DBC_PATH, parse_dbc

    messages, specs = parse_dbc(DBC_PATH)
    by_message: dict[str, list[str]] = {}
    lo, hi = -math.inf, math.inf
    for sig in _CARRIERS[name]:
        spec = specs[sig]
        lo, hi = max(lo, spec.lo * spec.factor), min(hi, spec.hi * spec.factor)
        for m in messages.values():
            if any(s.name == sig for s in m.signals):
                by_message.setdefault(m.name, []).append(sig)
    if name == "flux":  # a modulus: its components swing through ±ψ*
        hi = min(hi, -lo)
        lo = -hi
    carried = " and ".join(f"{' and '.join(sigs)} in {msg}" for msg, sigs in by_message.items())
    spec = specs[_CARRIERS[name][0]]
    unit = _SI_NAME[name]
    span = f"up to {hi:g} {unit}" if name == "flux" else f"{lo:g} to {hi:g} {unit}"
    return ReferenceLimit(lo, hi, (
        f"the range the bus carries it in ({carried} of {DBC_PATH.name}: "
        f"{'' if spec.signed else 'U'}INT{spec.bits} at {spec.factor:g} {unit} per bit, "
        f"{span})"))


def _eds_default(eds: Path, parameter: str) -> tuple[str, float] | None:
    """(object as "0xIIII:S", DefaultValue) of the EDS entry named ``parameter``; None if the
    EDS has none or cannot be read."""
    cp = configparser.ConfigParser(interpolation=None, strict=False)
    try:
        cp.read(eds, encoding="utf-8")
    except (OSError, configparser.Error, UnicodeDecodeError):
        return None
    for section in cp.sections():
        if cp[section].get("ParameterName", "").strip() != parameter:
            continue
        index, _, sub = section.lower().partition("sub")
        try:
            value = float(cp[section].get("DefaultValue", ""))
            where = f"0x{int(index, 16):04X}" + (f":{int(sub, 16)}" if sub else "")
        except ValueError:
            return None
        return where, value
    return None


def _overspeed_limit() -> ReferenceLimit | None:
    """The emulated drive's over-speed limit w_max (its EDS default), or None without one."""
    from dbc.cia301 import Emcy
    from dbc.codec import EDS_PATH

    found = _eds_default(EDS_PATH, "w_max")
    if found is None or not found[1] > 0.0:
        return None
    where, w_max = found
    return ReferenceLimit(-w_max, w_max, (
        f"the emulated drive's over-speed limit (w_max = {w_max:g} rad/s, {where} in "
        f"{EDS_PATH.name}: beyond it the drive faults with EMCY 0x{int(Emcy.OVERSPEED):04X})"))


@functools.cache
def reference_limits() -> Mapping[str, tuple[ReferenceLimit, ...]]:
    """What each reference ("speed", "flux", "load") must stay within to run on the
    emulated drive: the range of its PDO signals in ``drive.dbc`` and, for ω*, the drive's
    over-speed limit ``w_max`` from ``drive.eds``. Read once per process."""
    out: dict[str, tuple[ReferenceLimit, ...]] = {}
    for name in _CARRIERS:
        limits = [_bus_limit(name)]
        if name == "speed" and (overspeed := _overspeed_limit()) is not None:
            limits.append(overspeed)
        out[name] = tuple(limits)
    return MappingProxyType(out)


# ---------------------------------------------------------------------------------- parsing


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


def _beyond(src: str, w: str, raw: Any, name: str, x: float, vunit_name: str, vscale: float,
            limits: Sequence[ReferenceLimit]) -> ProfileError | None:
    """The refusal of value ``x`` (SI) of reference ``name`` at ``w`` if it breaks one of
    ``limits``, else None."""
    broken = [lim for lim in limits if not lim.holds(x)]
    if not broken:
        return None
    si = _SI_NAME[name]

    def show(v: float) -> str:
        return f"{v:g} {si}" if vscale == 1.0 else f"{v / vscale:g} {vunit_name} ({v:g} {si})"

    lo, hi = max(lim.lo for lim in limits), min(lim.hi for lim in limits)
    sym = _SYMBOL[name]
    keep = (f"|{sym}| ≤ {show(hi)}" if lo == -hi and name != "flux"
            else f"{sym} ≤ {show(hi)}" if name == "flux"
            else f"{sym} within {lo / vscale:g} to {show(hi)}")
    return _fail(
        src, f"{w} = {raw!r}",
        f"the {_LABEL[name]} {sym} = {show(x)} cannot run: it is beyond "
        f"{' and beyond '.join(lim.what for lim in broken)}; every value of [{name}] "
        f"must have {keep}: change this one",
    )


@dataclass(frozen=True)
class _Reading:
    """How the values of reference ``name`` ([speed], [flux], [load]) of profile ``src``
    read: value unit ``vunit_name`` (``vscale`` SI units per unit), time unit ``tunit_name``
    (``tscale`` s per unit), > 0 required (``positive``: the flux) and its ``limits``."""

    src: str
    name: str
    vunit_name: str
    vscale: float
    tunit_name: str
    tscale: float
    positive: bool
    limits: Sequence[ReferenceLimit]

    def value(self, w: str, raw: Any) -> float:
        """The value ``raw`` at ``w`` in SI: refused when not > 0 (``positive``) or beyond
        the ``limits``."""
        x = _number(self.src, w, raw, self.vunit_name) * self.vscale
        if self.positive and not x > 0.0:
            raise _fail(
                self.src, f"{w} = {raw!r}",
                f"the flux reference must stay > 0 (ψ* > 0 is required by (15)); "
                f"use a positive value in {self.vunit_name}",
            )
        refusal = _beyond(self.src, w, raw, self.name, x, self.vunit_name, self.vscale,
                          self.limits)
        if refusal is not None:
            raise refusal
        return x

    def time(self, w: str, raw: Any) -> float:
        """The time ``raw`` at ``w`` (a step's ``t`` or ``ramp``) in s."""
        return _number(self.src, w, raw, self.tunit_name) * self.tscale


def _signal(src: str, name: str, tab: Mapping[str, Any], units: Mapping[str, Any],
            raw_units: Mapping[str, Any], duration: float, positive: bool,
            limits: Sequence[ReferenceLimit] = ()) -> Signal:
    """Reference [``name``] (keys ``initial``, ``steps``) in SI: its values in the
    profile's ``units`` (SI per unit; ``raw_units``: their names), the steps one after
    the other, each ended by ``duration`` (s)."""
    where = f"[{name}]"
    _keys(src, where, tab, ("initial", "steps"))
    rd = _Reading(src, name, vunit_name=str(raw_units.get(_SIGNAL_UNIT[name], _SI_NAME[name])),
                  vscale=units.get(_SIGNAL_UNIT[name], 1.0),
                  tunit_name=str(raw_units["time"]), tscale=units["time"],
                  positive=positive, limits=limits)
    if "initial" in tab:
        initial = rd.value(f"{where}.initial", tab["initial"])
    elif name == "load":
        initial = 0.0
    else:
        raise _fail(src, f"{where}.initial", f"missing; add initial = <value in {rd.vunit_name}>")
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
        step = _step(rd, w, raw, prev_end, prev_where, duration)
        steps.append(step)
        prev_end, prev_where = step.end, w
    return Signal(initial, tuple(steps))


def _step_fields(rd: _Reading, w: str, raw: Any) -> tuple[float, float, float]:
    """Step ``w`` (a table with keys ``t``, ``value``, ``ramp``) as t (s, ≥ 0), value (SI)
    and ramp (s, > 0)."""
    src = rd.src
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
    t = rd.time(f"{w}.t", t_raw)
    v = rd.value(f"{w}.value", raw["value"])
    ramp = rd.time(f"{w}.ramp", ramp_raw)
    if t < 0.0:
        raise _fail(src, f"{w}.t = {t_raw!r}", "must be ≥ 0; transitions start at or after 0")
    if not ramp > 0.0:
        raise _fail(
            src, f"{w}.ramp = {ramp_raw!r}",
            f"must be > 0: a jump has no derivative and the laws need C² references "
            f"(docs/paper.md §E7); use a short ramp, e.g. ramp = {0.01 / rd.tscale:g} "
            f"({rd.tunit_name})",
        )
    return t, v, ramp


def _step(rd: _Reading, w: str, raw: Any, prev_end: float, prev_where: str,
          duration: float) -> Step:
    """Step ``w`` (see :func:`_step_fields`), starting when the previous transition
    (``prev_where``) has ended at ``prev_end`` (s) and ending by ``duration`` (s)."""
    t, v, ramp = _step_fields(rd, w, raw)
    tscale, tunit_name = rd.tscale, rd.tunit_name
    if t < prev_end * (1.0 - 1e-12):
        raise _fail(
            rd.src, f"{w}.t = {raw['t']!r}",
            f"starts before the previous transition ({prev_where}) ends at "
            f"{prev_end / tscale:g} {tunit_name}; step times must increase and a "
            f"transition may start only when the previous ramp has ended — move t to "
            f"≥ {prev_end / tscale:g} or shorten the previous ramp",
        )
    t = max(t, prev_end)
    if t + ramp > duration * (1.0 + 1e-12):
        raise _fail(
            rd.src, f"{w}",
            f"the transition ends at {(t + ramp) / tscale:g} {tunit_name}, after the "
            f"profile's end ([profile].duration = {duration / tscale:g} {tunit_name}); "
            f"raise the duration or move/shorten the step",
        )
    return Step(t, v, ramp)


def parse_profile(text: str, source: str = "<string>",
                  limits: Mapping[str, Sequence[ReferenceLimit]] | None = None) -> Profile:
    """A reference :class:`Profile` from TOML text (see the module docstring for the format).

    ``source`` names the text in error messages and becomes :attr:`Profile.source`.
    ``limits``: what each reference ("speed", "flux", "load") must stay within; None gives
    :func:`reference_limits` (the emulated drive on the built-in ``drive.dbc``).
    """
    src = source
    if limits is None:
        limits = reference_limits()
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
        signals[sig] = _signal(src, sig, tab, units, raw_units, duration,
                               positive=sig == "flux", limits=tuple(limits.get(sig, ())))
    return Profile(name, duration, signals["speed"], signals["flux"], signals["load"],
                   source=source, description=description)


#: Profiles read, kept while their file is unchanged (a campaign's points read the same
#: one again and again); a :class:`Profile` is frozen: shared, read-only.
_READ: FileMemo[Profile] = FileMemo()


def load_profile(path: str | Path,
                 limits: Mapping[str, Sequence[ReferenceLimit]] | None = None) -> Profile:
    """Read a reference profile TOML file; :class:`ProfileError` (naming the file) on any
    problem, a value beyond ``limits`` included (see :func:`parse_profile`). Read again
    only when the file changed (:mod:`dbc.filecache`)."""
    checks = None if limits is None else tuple(sorted((k, tuple(v))
                                                      for k, v in limits.items()))
    return _READ.get((str(path), resolved(path), checks),
                     lambda: (_load_profile(path, limits), (path,)))


def _load_profile(path: str | Path,
                  limits: Mapping[str, Sequence[ReferenceLimit]] | None) -> Profile:
    """:func:`load_profile` from the file."""
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
    return parse_profile(text, src, limits)


def shipped_profiles() -> list[str]:
    """The names of the reference profiles shipped in ``gateway/profiles/`` (paper, quick,
    …)."""
    folder = resources.files("gateway").joinpath("profiles")
    return sorted(p.name[:-5] for p in folder.iterdir() if p.name.endswith(".toml"))


def resolve_profile(arg: str | Path,
                    limits: Mapping[str, Sequence[ReferenceLimit]] | None = None) -> Profile:
    """A reference profile file, or the name of a shipped one ("quick": its
    :attr:`Profile.source` is then ``profiles/quick.toml``); :class:`ProfileError` naming
    the file, or the shipped names when ``arg`` is neither."""
    path = Path(arg)
    if not path.exists() and path.suffix != ".toml" and str(arg) in shipped_profiles():
        text = resources.files("gateway").joinpath("profiles", f"{arg}.toml").read_text("utf-8")
        return parse_profile(text, f"profiles/{arg}.toml", limits)
    if not path.exists() and path.suffix != ".toml":
        raise ProfileError(f"{arg}: no such profile file, and no shipped profile of that name "
                           f"(shipped: {', '.join(shipped_profiles())})")
    return load_profile(path, limits)


def paper_profile() -> Profile:
    """The paper's section-6 reference profile (package data ``gateway/profiles/paper.toml``).

    Its :attr:`Profile.source` is "<embedded>"; it equals ``load_profile("profiles/paper.toml")``.
    """
    text = resources.files("gateway").joinpath("profiles", "paper.toml").read_text("utf-8")
    return parse_profile(text, "<embedded>")
