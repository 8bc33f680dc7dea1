"""Plant scenarios: how the emulated motor and drive differ from what the controller believes.

A scenario is one TOML file (``--plant FILE`` of ``hil-gateway simulate``, ``hil-gateway
sim`` and ``hil-plant run``). Everything is relative to the controller's model: the
controller keeps the motor parameters it was given (``--motor`` or the paper's motor), the
plant gets them multiplied by the scenario's factors, with sensor and inverter errors and a
load the controller may or may not be told::

    [scenario]                 # optional
    name = "rs+10-offset"
    description = "stator resistance 10 % high (hot motor), 10 mA offset on phase a"

    [motor]                    # plant value = controller's value × factor (default 1)
    Rs = 1.10                  # also Rr, Ls, Lr, M, J (or R_s, R_r, L_s, L_r)
    Rs_drift = 0.0             # linear drift of the factor, per second: Rs·(1 + Rs_drift·t)

    [sensors]                  # the drive's current sensors (three-phase: phases a and b)
    offset_a = 0.010           # A, added to the phase-a reading
    offset_b = 0.0             # A, phase b
    gain_a = 1.0               # reading = gain × true current
    gain_b = 1.02
    noise = 0.005              # A rms, white, on each axis of the (a, b) frame
    seed = 0                   # of the noise generator

    [inverter]
    dead_time = 2e-6           # s; phase-voltage error −dead_time·f_pwm·u_dc·sign(i_phase)
    dc_ripple = 0.05           # relative amplitude of the DC-link ripple
    dc_ripple_hz = 300.0       # its frequency, Hz

    [load]
    known = false              # is the controller told T_L? (default: the command's default)
    torque = "profile"         # what the dynamometer applies, see below
    initial = 0.0              # plus an extra torque T_x(t), N·m, s (quintic steps, like
    steps = [{ t = 1.2, value = 1.0, ramp = 0.01 }]  # a profile's [load]), unknown to the
                                                      # controller

    [[bus.fault]]              # faults on the bus between gateway and drive (dbc/busfaults.py;
    kind = "drop"              # sim, bridge, and a sampled simulate's PDO link)
    message = "TPDO1"
    start = 0.5                # s (or cycle = N)
    duration = 0.1             # s; omitted: to the end
    probability = 0.2          # per frame; omitted: every one
    seed = 3

Load (the dynamometer of the emulator):

* ``torque = "rpdo"`` (default): the T_L the gateway sends in
  RPDO3 each cycle — the profile's T_L at the start of the interval — held over the period;
* ``torque = "profile"``: the run's reference profile T_L(t) evaluated *within* the period at
  the emulator's internal rate (10 kHz), RPDO3 ignored: the load a real dynamometer applies
  continuously. Needs the profile on the plant side: ``simulate`` and ``sim`` only;
* ``torque = "none"``: no load from the profile (RPDO3 ignored), only the extra torque.

The extra torque T_x(t) is always added, evaluated within the period. Whether the controller
is *told* the load is ``known``: when true the law gets the profile's T_L and dT_L/dt (the
paper's case, docs/paper.md §E6; the extra torque is never told); when false it uses the load-torque
observer of :mod:`gateway.control.load_observer`. Default (``--load`` overrides): told where
the drive applies the profile's load (the emulator; ``hil-gateway run`` with a drive profile
that maps a T_L signal), not told (``--load untold``: the laws assume no load) where it cannot.
"Not told" does not mean observed: the observer runs away with realistic sensor and
resistance errors even without a load (docs/robustness.md §2), and the orientation guard of
:mod:`gateway.guard` stops a motor lost to a load the laws are not told.

Sensors: phases a and b are measured, i_c = −i_a − i_b, and mapped to the (a, b) frame of (1)
by the amplitude-invariant Clarke transform; a phase-a offset o_a therefore appears as
(o_a, o_a/√3) in (a, b) and a phase-b offset o_b as (0, 2·o_b/√3) (see
:class:`plant.params.DriveParams` and :mod:`plant.drive`). The drive's current control
regulates the measured currents.

Motor drift: p(t) = p_controller·factor·(1 + drift·t), t from the start of the run, updated
once per period (a thermal drift is far slower). A drift that makes a parameter ≤ 0 or
M² ≥ L_s·L_r stops the run with a message.

Pure module: no clock, no global state; :func:`load_scenario` reads one file.
"""

from __future__ import annotations

import math
import tomllib
from collections.abc import Callable, Mapping
from dataclasses import dataclass, field, replace
from importlib import resources
from pathlib import Path
from types import MappingProxyType
from typing import Any

from dbc.busfaults import BusFault, BusFaultError, parse_bus_faults
from dbc.motor import MotorParams, ParamsError
from plant.params import DriveParams

SQRT3 = math.sqrt(3.0)
#: [motor] keys: the file's spelling → MotorParams field
MOTOR_KEYS = MappingProxyType({
    "Rs": "R_s", "Rr": "R_r", "Ls": "L_s", "Lr": "L_r", "M": "M", "J": "J",
    "R_s": "R_s", "R_r": "R_r", "L_s": "L_s", "L_r": "L_r",
})
MOTOR_FIELDS = ("J", "R_s", "R_r", "L_s", "L_r", "M")
SENSOR_KEYS = ("offset_a", "offset_b", "gain_a", "gain_b", "noise", "seed")
INVERTER_KEYS = ("dead_time", "dc_ripple", "dc_ripple_hz")
LOAD_KEYS = ("known", "torque", "initial", "steps")
LOAD_SOURCES = ("rpdo", "profile", "none")
TABLES = ("scenario", "motor", "sensors", "inverter", "load", "bus")

LoadFunction = Callable[[float, float], float]


class ScenarioError(ValueError):
    """An invalid scenario: the message names the file, the key, the problem and the fix."""


@dataclass(frozen=True, slots=True)
class TorqueStep:
    """A transition of the extra load torque: to ``value`` (N·m) from ``t`` over ``ramp`` (s),
    quintic smoothstep 6s⁵ − 15s⁴ + 10s³ (as in reference profiles)."""

    t: float
    value: float
    ramp: float


@dataclass(frozen=True)
class PlantScenario:
    """How the plant differs from the controller's model (see the module docstring).

    The defaults are the nominal plant: no difference, load from RPDO3, ``known`` left to
    the command (None).
    """

    name: str = "nominal"
    description: str = ""
    source: str = "<nominal>"
    motor_factors: Mapping[str, float] = field(default_factory=dict)
    motor_drift: Mapping[str, float] = field(default_factory=dict)
    offset_a: float = 0.0
    offset_b: float = 0.0
    gain_a: float = 1.0
    gain_b: float = 1.0
    noise: float = 0.0
    seed: int = 0
    dead_time: float = 0.0
    dc_ripple: float = 0.0
    dc_ripple_hz: float = 300.0
    load_known: bool | None = None
    load_torque: str = "rpdo"
    load_initial: float = 0.0
    load_steps: tuple[TorqueStep, ...] = ()
    #: faults injected on the bus between gateway and drive ([[bus.fault]];
    #: :mod:`dbc.busfaults`); on a bus (sim, bridge) or a sampled simulation's PDO link
    bus_faults: tuple[BusFault, ...] = ()

    # ---- what the plant is --------------------------------------------------------------
    def factor(self, name: str) -> float:
        """The plant/controller factor of MotorParams field ``name`` at t = 0."""
        return float(self.motor_factors.get(name, 1.0))

    def plant_motor(self, motor: MotorParams) -> MotorParams:
        """The plant's motor at t = 0: the controller's ``motor`` × the factors."""
        if not any(self.factor(k) != 1.0 for k in MOTOR_FIELDS):
            return motor
        values = {k: getattr(motor, k) * self.factor(k) for k in MOTOR_FIELDS}
        try:
            return MotorParams.from_mapping(values, f"{self.source} [motor] × controller motor")
        except ParamsError as exc:
            raise ScenarioError(f"{exc} (check the factors of [motor])") from None

    def drive_params(self, base: DriveParams) -> DriveParams:
        """``base`` (mode, rate, DC link of the command) with the scenario's sensor and
        inverter errors: offsets add to base's, the other errors replace base's values where
        the scenario sets them (a nominal scenario returns ``base`` unchanged)."""
        changes: dict[str, Any] = {}
        if self.offset_a or self.offset_b:
            changes["i_offset_ab"] = base.i_offset_ab + complex(
                self.offset_a, (self.offset_a + 2.0 * self.offset_b) / SQRT3)
        if (self.gain_a, self.gain_b) != (1.0, 1.0):
            changes["i_gain_phase"] = (self.gain_a - 1.0, self.gain_b - 1.0)
        if self.noise:
            changes["i_noise_rms"] = self.noise
            changes["seed"] = self.seed
        if self.dead_time:
            changes["dead_time"] = self.dead_time
        if self.dc_ripple:
            changes["u_dc_ripple"] = self.dc_ripple
            changes["u_dc_ripple_hz"] = self.dc_ripple_hz
        if not changes:
            return base
        try:
            return replace(base, **changes)
        except ParamsError as exc:
            raise ScenarioError(f"{self.source}: {exc}") from None

    def extra_torque(self, t: float) -> float:
        """T_x(t), N·m: the scenario's own load steps (never told to the controller)."""
        v = self.load_initial
        for s in self.load_steps:
            if t <= s.t:
                break
            x = min((t - s.t) / s.ramp, 1.0)
            v += (s.value - v) * x * x * x * (10.0 + x * (6.0 * x - 15.0))
        return v

    @property
    def has_extra_torque(self) -> bool:
        return self.load_initial != 0.0 or bool(self.load_steps)

    def load_function(self, profile_load: Callable[[float], float] | None = None
                      ) -> LoadFunction | None:
        """The dynamometer for :class:`plant.drive.Drive`: f(t, T_L of RPDO3) → torque at t.

        ``profile_load(t)``: the run profile's T_L(t), needed for ``torque = "profile"``.
        None when the dynamometer simply holds RPDO3's value (the drive's plain path).
        """
        extra = self.extra_torque if self.has_extra_torque else None
        if self.load_torque == "rpdo":
            if extra is None:
                return None
            return lambda t, T_L: T_L + extra(t)
        if self.load_torque == "profile":
            if profile_load is None:
                raise ScenarioError(
                    f"{self.source}: [load].torque = \"profile\" needs the run's reference "
                    f"profile on the plant side, which only `hil-gateway simulate` and "
                    f"`hil-gateway sim` have; use torque = \"rpdo\" (or \"none\" with steps) "
                    f"for `hil-plant run`")
            if extra is None:
                return lambda t, T_L: profile_load(t)
            return lambda t, T_L: profile_load(t) + extra(t)
        if extra is None:
            return lambda t, T_L: 0.0
        return lambda t, T_L: extra(t)

    def drive_options(self, profile_load: Callable[[float], float] | None = None
                      ) -> dict[str, Any]:
        """Keyword arguments of :class:`plant.drive.Drive` (``load``, ``motor_drift``)."""
        return {"load": self.load_function(profile_load), "motor_drift": dict(self.motor_drift)}

    def known(self, default: bool) -> bool:
        """Whether the controller is told T_L: the scenario's ``known``, else ``default``."""
        return default if self.load_known is None else self.load_known

    @property
    def nominal(self) -> bool:
        """No difference at all between plant and controller model (the default)."""
        return self == replace(PlantScenario(), name=self.name, description=self.description,
                               source=self.source, load_known=self.load_known)

    @property
    def continuous_time_ok(self) -> bool:
        """What the continuous-time loop can model: motor factors and the load only."""
        return (not self.motor_drift and self.offset_a == self.offset_b == 0.0
                and self.gain_a == self.gain_b == 1.0 and self.noise == 0.0
                and self.dead_time == 0.0 and self.dc_ripple == 0.0)

    def describe(self) -> dict[str, Any]:
        """The resolved scenario, JSON-able (``configuration.plant_scenario`` of summaries)."""
        return {
            "file": None if self.source.startswith("<") else self.source,
            "name": self.name,
            "description": self.description,
            "motor_factors": {k: self.factor(k) for k in MOTOR_FIELDS},
            "motor_drift_per_s": {k: self.motor_drift.get(k, 0.0) for k in MOTOR_FIELDS},
            "sensors": {"offset_a": self.offset_a, "offset_b": self.offset_b,
                        "gain_a": self.gain_a, "gain_b": self.gain_b, "noise": self.noise,
                        "seed": self.seed},
            "inverter": {"dead_time": self.dead_time, "dc_ripple": self.dc_ripple,
                         "dc_ripple_hz": self.dc_ripple_hz},
            "load": {"known": self.load_known, "torque": self.load_torque,
                     "extra_initial": self.load_initial,
                     "extra_steps": [[s.t, s.value, s.ramp] for s in self.load_steps]},
        }


# ------------------------------------------------------------------------------ TOML input


def _fail(src: str, where: str, msg: str) -> ScenarioError:
    return ScenarioError(f"{src}: {where}: {msg}")


def _keys(src: str, table: str, data: Mapping[str, Any], valid: tuple[str, ...]) -> None:
    for key in data:
        if key not in valid:
            raise _fail(src, f"[{table}].{key}",
                        f"unknown key; valid keys of [{table}] are {', '.join(valid)} "
                        f"(fix the spelling or remove it)")


def _num(src: str, where: str, value: Any, unit: str, lo: float = -math.inf,
         hi: float = math.inf, lo_open: bool = False) -> float:
    if isinstance(value, bool) or not isinstance(value, int | float):
        raise _fail(src, f"{where} = {value!r}", f"must be a number ({unit})")
    x = float(value)
    if not math.isfinite(x) or x < lo or (lo_open and x == lo) or x >= hi:
        rng = (f"{'>' if lo_open else '≥'} {lo:g}" if lo > -math.inf else "") + (
            f"{' and ' if lo > -math.inf else ''}< {hi:g}" if hi < math.inf else "")
        raise _fail(src, f"{where} = {value!r}", f"must be a finite number {rng} ({unit})")
    return x


def _table(src: str, data: Mapping[str, Any], name: str) -> dict[str, Any]:
    value = data.get(name, {})
    if not isinstance(value, dict):
        raise _fail(src, f"{name} = {value!r}", f"must be a table: write it as a [{name}] section")
    return value


def parse_scenario(text: str, source: str = "<string>") -> PlantScenario:
    """A :class:`PlantScenario` from TOML text; ``source`` names it in error messages."""
    data = _parse_toml(text, source)
    _check_tables(source, data)
    kw: dict[str, Any] = {"source": source}
    kw |= _scenario_part(source, data)
    kw |= _motor_part(source, data)
    kw |= _sensors_part(source, data)
    kw |= _inverter_part(source, data)
    kw |= _load_part(source, data)
    kw |= _bus_part(source, data)
    return PlantScenario(**kw)


def _bus_part(src: str, data: Mapping[str, Any]) -> dict[str, Any]:
    """``bus_faults`` from [[bus.fault]] (:func:`dbc.busfaults.parse_bus_faults`)."""
    bus = _table(src, data, "bus")
    _keys(src, "bus", bus, ("fault",))
    if "fault" not in bus:
        return {}
    try:
        return {"bus_faults": parse_bus_faults(bus["fault"], src)}
    except BusFaultError as exc:
        raise ScenarioError(str(exc)) from None


def _parse_toml(text: str, src: str) -> dict[str, Any]:
    """The TOML document; ScenarioError when it is not valid TOML."""
    try:
        return tomllib.loads(text)
    except tomllib.TOMLDecodeError as exc:
        raise ScenarioError(f"{src}: not valid TOML ({exc}); fix the syntax") from None


def _check_tables(src: str, data: Mapping[str, Any]) -> None:
    """ScenarioError unless every top-level key is one of :data:`TABLES`."""
    for key in data:
        if key not in TABLES:
            raise _fail(src, f"[{key}]", f"unknown table; valid tables are "
                        f"{', '.join(TABLES)} (fix the spelling or remove it)")


def _scenario_part(src: str, data: Mapping[str, Any]) -> dict[str, Any]:
    """``name`` and ``description`` from [scenario] (strings); the name defaults to the file's
    stem ("scenario" for a text without a file)."""
    sc = _table(src, data, "scenario")
    _keys(src, "scenario", sc, ("name", "description"))
    kw = {"name": sc.get("name", Path(src).stem if not src.startswith("<") else "scenario"),
          "description": sc.get("description", "")}
    for key in ("name", "description"):
        if not isinstance(kw[key], str):
            raise _fail(src, f"[scenario].{key} = {kw[key]!r}", "must be a string")
    return kw


def _motor_part(src: str, data: Mapping[str, Any]) -> dict[str, Any]:
    """``motor_factors`` and ``motor_drift`` (MotorParams field → value) from [motor]: a factor
    (> 0, plant value = controller's value × factor) per key of :data:`MOTOR_KEYS`, a drift
    (relative change per second) per ``<key>_drift``; zero drifts are left out."""
    mo = _table(src, data, "motor")
    valid = (*MOTOR_KEYS, *(f"{k}_drift" for k in MOTOR_KEYS))
    _keys(src, "motor", mo, valid)
    factors: dict[str, float] = {}
    drift: dict[str, float] = {}
    for key, value in mo.items():
        is_drift = key.endswith("_drift")
        name = MOTOR_KEYS[key[: -len("_drift")] if is_drift else key]
        target = drift if is_drift else factors
        if name in target:
            raise _fail(src, f"[motor].{key}", f"{name} is given twice (as {key} and another "
                        f"spelling); keep one")
        if is_drift:
            target[name] = _num(src, f"[motor].{key}", value, "relative change per second")
        else:
            target[name] = _num(src, f"[motor].{key}", value,
                                "factor: plant value = controller's value × factor", 0.0,
                                lo_open=True)
    return {"motor_factors": factors, "motor_drift": {k: v for k, v in drift.items() if v}}


def _sensors_part(src: str, data: Mapping[str, Any]) -> dict[str, Any]:
    """The keys of [sensors] it sets: ``offset_a``, ``offset_b`` (A), ``gain_a``, ``gain_b``
    (reading / true current, in (0, 2)), ``noise`` (A rms, ≥ 0), ``seed`` (an integer)."""
    se = _table(src, data, "sensors")
    _keys(src, "sensors", se, SENSOR_KEYS)
    kw: dict[str, Any] = {}
    for key in ("offset_a", "offset_b"):
        if key in se:
            kw[key] = _num(src, f"[sensors].{key}", se[key], "A")
    for key in ("gain_a", "gain_b"):
        if key in se:
            kw[key] = _num(src, f"[sensors].{key}", se[key], "reading / true current, e.g. "
                           "1.02 for 2 % high", 0.0, 2.0, lo_open=True)
    if "noise" in se:
        kw["noise"] = _num(src, "[sensors].noise", se["noise"], "A rms", 0.0)
    if "seed" in se:
        if isinstance(se["seed"], bool) or not isinstance(se["seed"], int):
            raise _fail(src, f"[sensors].seed = {se['seed']!r}", "must be an integer")
        kw["seed"] = se["seed"]
    return kw


def _inverter_part(src: str, data: Mapping[str, Any]) -> dict[str, Any]:
    """The keys of [inverter] it sets: ``dead_time`` (s, in [0, 50 µs)), ``dc_ripple``
    (relative amplitude, in [0, 1)), ``dc_ripple_hz`` (Hz, > 0)."""
    inv = _table(src, data, "inverter")
    _keys(src, "inverter", inv, INVERTER_KEYS)
    kw: dict[str, Any] = {}
    if "dead_time" in inv:
        kw["dead_time"] = _num(src, "[inverter].dead_time", inv["dead_time"],
                               "s, e.g. 2e-6", 0.0, 5e-5)
    if "dc_ripple" in inv:
        kw["dc_ripple"] = _num(src, "[inverter].dc_ripple", inv["dc_ripple"],
                               "relative amplitude, e.g. 0.05", 0.0, 1.0)
    if "dc_ripple_hz" in inv:
        kw["dc_ripple_hz"] = _num(src, "[inverter].dc_ripple_hz", inv["dc_ripple_hz"], "Hz",
                                  0.0, lo_open=True)
    return kw


def _load_part(src: str, data: Mapping[str, Any]) -> dict[str, Any]:
    """From [load]: ``load_known`` (``known``, a boolean), ``load_torque`` (``torque``, one of
    :data:`LOAD_SOURCES`), ``load_initial`` (``initial``, N·m) where given, and
    ``load_steps`` (``steps``, see :func:`_load_steps`)."""
    lo = _table(src, data, "load")
    _keys(src, "load", lo, LOAD_KEYS)
    kw: dict[str, Any] = {}
    if "known" in lo:
        if not isinstance(lo["known"], bool):
            raise _fail(src, f"[load].known = {lo['known']!r}",
                        "must be true (the controller is told T_L) or false (it estimates it)")
        kw["load_known"] = lo["known"]
    if "torque" in lo:
        if lo["torque"] not in LOAD_SOURCES:
            raise _fail(src, f"[load].torque = {lo['torque']!r}",
                        f"use one of {', '.join(repr(x) for x in LOAD_SOURCES)}: RPDO3's "
                        f"value held per period, the profile's T_L(t) within the period, or "
                        f"no profile load")
        kw["load_torque"] = lo["torque"]
    if "initial" in lo:
        kw["load_initial"] = _num(src, "[load].initial", lo["initial"], "N·m")
    kw["load_steps"] = _load_steps(src, lo.get("steps", []))
    return kw


def _load_steps(src: str, steps: Any) -> tuple[TorqueStep, ...]:
    """[load].steps: an array of tables { t (s, ≥ 0), value (N·m), ramp (s, > 0) }, each
    starting at or after the end (t + ramp) of the one before."""
    if not isinstance(steps, list):
        raise _fail(src, f"[load].steps = {steps!r}",
                    "must be an array of tables, e.g. steps = [{ t = 1.2, value = 1.0, "
                    "ramp = 0.01 }]")
    out: list[TorqueStep] = []
    prev_end = 0.0
    for i, st in enumerate(steps):
        w = f"[load].steps[{i}]"
        if not isinstance(st, dict):
            raise _fail(src, f"{w} = {st!r}",
                        "must be a table { t = ..., value = ..., ramp = ... }")
        for key in st:
            if key not in ("t", "value", "ramp"):
                raise _fail(src, f"{w}.{key}", "unknown key; a step has t, value and ramp")
        for key in ("t", "value", "ramp"):
            if key not in st:
                raise _fail(src, f"{w}.{key}", "missing; every step needs t (s), value (N·m) "
                            "and ramp (s)")
        t = _num(src, f"{w}.t", st["t"], "s", 0.0)
        ramp = _num(src, f"{w}.ramp", st["ramp"], "s, > 0 (a C² transition)", 0.0, lo_open=True)
        if t < prev_end:
            raise _fail(src, f"{w}.t = {st['t']!r}", f"starts before the previous step ends at "
                        f"{prev_end:g} s; move t to ≥ {prev_end:g} or shorten the previous ramp")
        out.append(TorqueStep(t, _num(src, f"{w}.value", st["value"], "N·m"), ramp))
        prev_end = t + ramp
    return tuple(out)


def load_scenario(path: str | Path) -> PlantScenario:
    """Read a scenario TOML file; :class:`ScenarioError` (naming the file) on any problem."""
    src = str(path)
    try:
        text = Path(path).read_bytes().decode("utf-8")
    except FileNotFoundError:
        names = ", ".join(shipped_names())
        raise ScenarioError(
            f"{src}: no such file; give the path of a plant scenario TOML file or the name "
            f"of a shipped one ({names})") from None
    except OSError as exc:
        raise ScenarioError(f"{src}: cannot read the file ({exc.strerror})") from None
    except UnicodeDecodeError as exc:
        raise ScenarioError(f"{src}: not UTF-8 text ({exc.reason}); save it as UTF-8") from None
    return parse_scenario(text, src)


def shipped_names() -> list[str]:
    """Names of the scenarios shipped in ``plant/scenarios/`` (package data)."""
    d = resources.files("plant").joinpath("scenarios")
    return sorted(p.name[:-5] for p in d.iterdir() if p.name.endswith(".toml"))


def resolve_scenario(arg: str) -> PlantScenario:
    """``--plant ARG``: a file path, or the name of a shipped scenario (e.g. ``rs+10``)."""
    shipped = _shipped_source(arg)
    return load_scenario(arg) if shipped is None else parse_scenario(*shipped)


def scenario_source(arg: str) -> tuple[str, str]:
    """The TOML text of ``--plant ARG`` (a file path, or a shipped scenario's name) and
    the name it goes by in messages, as :func:`resolve_scenario` reads it; ScenarioError
    when there is no such file."""
    shipped = _shipped_source(arg)
    if shipped is not None:
        return shipped
    try:
        return Path(arg).read_bytes().decode("utf-8"), arg
    except (OSError, UnicodeDecodeError):
        load_scenario(arg)  # raises the one message for a file that cannot be read
        raise


def _shipped_source(arg: str) -> tuple[str, str] | None:
    """A shipped scenario's text and source name, when ``arg`` names one and no file."""
    p = Path(arg)
    if not p.exists() and p.suffix != ".toml" and arg in shipped_names():
        res = resources.files("plant").joinpath("scenarios", f"{arg}.toml")
        return res.read_text("utf-8"), f"scenarios/{arg}.toml"
    return None
