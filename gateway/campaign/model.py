"""A campaign file (TOML): the base run, its axes and the pass criteria.

::

    [campaign]
    name = "rs-sweep"              # names the campaign (and its default DIR)
    command = "simulate"           # or "sim": over CANopen against the emulator
    description = "..."            # optional

    [base]                         # the command's options, as on its command line
    profile = "profiles/paper.toml"
    period = "1ms"

    [grid]                         # every combination (several [[grid]] tables: their union)
    "plant.motor.Rs" = [0.9, 1.0, 1.1]
    delay = [0, 1]
    variant = [{label = "drift-free", estimator = "drift-free"},   # a table of settings
               {label = "true flux", flux = "true"}]               # per value

    [random]                       # n draws with a seed, crossed with every grid point
    n = 1000
    seed = 1
    "plant.motor.J" = {dist = "uniform", low = 0.8, high = 1.2}

    [pass]                         # criteria on the table's metrics
    speed_rms = "< 0.05"

An axis is a command option (``period``, ``delay``, ``profile``, ``motor``, ``controller``,
``k-w``, ...), a plant scenario key ``plant.<table>.<key>`` (plant/scenario.py: motor
factors, sensors, inverter, load; merged into the ``plant`` option's scenario, or the
nominal one), a controller parameter ``controller.<name>`` (merged into
``controller-params``), a bus fault key ``bus.<key>`` (set in every ``[[bus.fault]]`` of
the point's plant scenario, dbc/busfaults.py: ``bus.probability``, ``bus.start``; the
scenario names the faults, e.g. ``plant = ["bus-drop", "bus-delay"]``; `sim`, or a sampled
`simulate`), or a
table of such settings per value (its ``label`` names it in the table). An axis overrides
[base]. Distributions: ``uniform`` and ``loguniform`` (low, high), ``normal`` (mean,
std), ``integers`` (low, high, both included), ``choice`` (values).
"""

from __future__ import annotations

import itertools
import math
import re
import tomllib
from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field
from enum import Enum, StrEnum
from pathlib import Path
from typing import Any

import numpy as np

from gateway.campaign.options import Command, Option, check_value, option
from gateway.errors import UserError

TABLES = ("campaign", "base", "grid", "random", "pass")
#: The tables of a plant scenario an axis may reach (plant/scenario.py).
PLANT_TABLES = ("motor", "sensors", "inverter", "load")


class AxisKind(Enum):
    """What an axis (or a [base] key) sets."""

    OPTION = "option"  #: a command-line option
    PLANT = "plant"  #: a plant scenario key, plant.<table>.<key>
    CONTROLLER = "controller"  #: a controller parameter, controller.<name>
    SETTINGS = "settings"  #: a table of the above per value, named by its label
    BUS_FAULT = "bus"  #: a key of every [[bus.fault]] of the plant scenario, bus.<key>


class Dist(StrEnum):
    """A random axis's distribution."""

    UNIFORM = "uniform"
    LOGUNIFORM = "loguniform"
    NORMAL = "normal"
    INTEGERS = "integers"
    CHOICE = "choice"


@dataclass(frozen=True)
class Distribution:
    """How a random axis draws: ``low``/``high`` (uniform, loguniform, integers),
    ``mean``/``std`` (normal), ``values`` (choice)."""

    dist: Dist
    low: float = math.nan
    high: float = math.nan
    mean: float = math.nan
    std: float = math.nan
    values: tuple[Any, ...] = ()

    def draw(self, rng: np.random.Generator) -> Any:
        if self.dist is Dist.UNIFORM:
            return float(rng.uniform(self.low, self.high))
        if self.dist is Dist.LOGUNIFORM:
            return float(math.exp(rng.uniform(math.log(self.low), math.log(self.high))))
        if self.dist is Dist.NORMAL:
            return float(rng.normal(self.mean, self.std))
        if self.dist is Dist.INTEGERS:
            return int(rng.integers(int(self.low), int(self.high), endpoint=True))
        return self.values[int(rng.integers(len(self.values)))]

    def describe(self) -> str:
        if self.dist is Dist.NORMAL:
            return f"normal(mean {self.mean:g}, std {self.std:g})"
        if self.dist is Dist.CHOICE:
            return f"choice of {len(self.values)}"
        return f"{self.dist}({self.low:g} … {self.high:g})"


@dataclass(frozen=True)
class Settings:
    """One value of a settings axis: its ``label`` and what it sets (key → value)."""

    label: str
    values: Mapping[str, Any]

    def __str__(self) -> str:
        return self.label


@dataclass(frozen=True)
class Axis:
    """One axis: ``key`` (as written), ``kind``, and either grid ``values`` or a random
    ``dist``; ``target``: what it sets (the option's name for an option)."""

    key: str
    kind: AxisKind
    target: str
    values: tuple[Any, ...] = ()
    dist: Distribution | None = None

    def describe(self) -> str:
        if self.dist is not None:
            return f"{self.key}: {self.dist.describe()}"
        return f"{self.key}: {', '.join(str(v) for v in self.values)}"


class Op(StrEnum):
    """A criterion's comparison."""

    LT = "<"
    LE = "<="
    GT = ">"
    GE = ">="
    EQ = "=="
    NE = "!="

    def holds(self, a: float, b: float) -> bool:
        return {Op.LT: a < b, Op.LE: a <= b, Op.GT: a > b, Op.GE: a >= b, Op.EQ: a == b,
                Op.NE: a != b}[self]


_CRITERION = re.compile(r"^\s*(<=|>=|==|!=|<|>)\s*([-+]?(?:\d+\.?\d*|\.\d+)(?:[eE][-+]?\d+)?)\s*$")


@dataclass(frozen=True)
class Criterion:
    """``metric op threshold`` (``speed_rms < 0.05``): a point passes when its metric has a
    finite value that satisfies it."""

    metric: str
    op: Op
    threshold: float

    def passes(self, value: Any) -> bool:
        try:
            x = float(value)
        except (TypeError, ValueError):
            return False
        return math.isfinite(x) and self.op.holds(x, self.threshold)

    def __str__(self) -> str:
        return f"{self.metric} {self.op} {self.threshold:g}"


def parse_criterion(metric: str, spec: Any, where: str) -> Criterion:
    m = _CRITERION.match(spec) if isinstance(spec, str) else None
    if m is None:
        raise UserError(f"{where}: {metric} = {spec!r}: write a comparison and a number as a "
                        "string, e.g. \"< 0.05\" (<, <=, >, >=, ==, !=)")
    return Criterion(metric, Op(m.group(1)), float(m.group(2)))


@dataclass(frozen=True)
class Campaign:
    """A campaign file, checked: ``grids`` (one tuple of axes per grid table), the
    ``random`` axes drawn ``n`` times from ``seed``, the ``criteria`` of [pass]."""

    name: str
    command: Command
    base: Mapping[str, Any]
    grids: tuple[tuple[Axis, ...], ...] = ((),)
    random: tuple[Axis, ...] = ()
    n: int = 1
    seed: int = 0
    criteria: tuple[Criterion, ...] = ()
    description: str = ""
    source: str = "<campaign>"
    text: str = ""
    options: Mapping[str, Option] = field(default_factory=dict, repr=False, compare=False)

    @property
    def axes(self) -> tuple[Axis, ...]:
        """Every axis once, in the file's order (grid axes first)."""
        seen: dict[str, Axis] = {}
        for ax in (*itertools.chain.from_iterable(self.grids), *self.random):
            seen.setdefault(ax.key, ax)
        return tuple(seen.values())

    @property
    def size(self) -> int:
        """The number of points (before identical configurations are merged)."""
        return sum(math.prod(len(a.values) for a in g) for g in self.grids) * self.n


def classify(key: str, value: Any, options: Mapping[str, Option], where: str
             ) -> tuple[AxisKind, str]:
    """What ``key`` sets and its canonical target (an option's name, the plant key
    ``table.key``, the controller parameter's name)."""
    head, _, rest = key.partition(".")
    if head == "plant" and rest:
        table, _, name = rest.partition(".")
        if table not in PLANT_TABLES or not name or "." in name:
            raise UserError(f"{where}: {key!r}: a plant scenario key is plant.<table>.<key> "
                            f"with a table of {', '.join(PLANT_TABLES)} (plant/scenario.py), "
                            "e.g. plant.motor.Rs")
        return AxisKind.PLANT, rest
    if head == "controller" and rest:
        return AxisKind.CONTROLLER, rest
    if head == "bus" and rest:
        if "." in rest:
            raise UserError(f"{where}: {key!r}: a bus fault key is bus.<key>, set in every "
                            "[[bus.fault]] of the point's plant scenario (dbc/busfaults.py), "
                            "e.g. bus.probability")
        return AxisKind.BUS_FAULT, rest
    if isinstance(value, dict) and key not in options:
        return AxisKind.SETTINGS, key
    return AxisKind.OPTION, option(options, key, where).name


def _scalar(key: str, value: Any, where: str) -> Any:
    if isinstance(value, bool | int | float | str):
        return value
    raise UserError(f"{where}: {key} = {value!r}: give a string, a number or a boolean")


def _setting(key: str, value: Any, options: Mapping[str, Option], where: str
             ) -> tuple[str, Any]:
    """One setting (of [base] or a settings table), checked: its canonical key (the option's
    name, or ``plant.<table>.<key>`` / ``controller.<name>``) and value."""
    kind, target = classify(key, value, options, where)
    if kind is AxisKind.SETTINGS:
        raise UserError(f"{where}: {key} = {value!r}: a table of settings belongs in [grid] "
                        "as one value of an axis")
    if kind is AxisKind.OPTION:
        return target, check_value(options[key], key, value, where)
    return key, _scalar(key, value, where)


def _settings_value(key: str, value: Any, options: Mapping[str, Option], where: str
                    ) -> Settings:
    if not isinstance(value, dict):
        raise UserError(f"{where}: {key}: every value of a settings axis is a table "
                        "({label = \"...\", option = value, ...})")
    label = value.get("label")
    body = {k: v for k, v in value.items() if k != "label"}
    if not body:
        raise UserError(f"{where}: {key}: a table sets nothing: give options, plant.* or "
                        "controller.* keys besides its label")
    settings = dict(_setting(k, v, options, f"{where} {key}") for k, v in body.items())
    if label is None:
        label = ", ".join(f"{k}={v}" for k, v in body.items())
    if not isinstance(label, str):
        raise UserError(f"{where}: {key}: label = {label!r} must be a string")
    return Settings(label, settings)


def _grid_axis(key: str, values: Any, options: Mapping[str, Option], where: str) -> Axis:
    if not isinstance(values, list) or not values:
        raise UserError(f"{where}: {key} = {values!r}: a grid axis is a non-empty list of "
                        f"values, e.g. {key} = [0.9, 1.0, 1.1]")
    kind, target = classify(key, values[0], options, where)
    if kind is AxisKind.SETTINGS:
        vals = tuple(_settings_value(key, v, options, where) for v in values)
        labels = [v.label for v in vals]
        if len(set(labels)) != len(labels):
            raise UserError(f"{where}: {key}: two tables have the same label; give each its "
                            "own label")
    elif kind is AxisKind.OPTION:
        vals = tuple(check_value(options[key], key, v, where) for v in values)
    else:
        vals = tuple(_scalar(key, v, where) for v in values)
    return Axis(key, kind, target, vals)


def _number(where: str, name: str, spec: Mapping[str, Any]) -> float:
    v = spec.get(name)
    if isinstance(v, bool) or not isinstance(v, int | float) or not math.isfinite(v):
        raise UserError(f"{where}: give {name} as a finite number")
    return float(v)


def _distribution(key: str, spec: Any, where: str) -> Distribution:
    w = f"{where} {key}"
    if not isinstance(spec, dict) or "dist" not in spec:
        raise UserError(f"{w}: a random axis is a table with its distribution, e.g. {{dist = "
                        "\"uniform\", low = 0.8, high = 1.2}")
    try:
        dist = Dist(spec["dist"])
    except ValueError:
        raise UserError(f"{w}: dist = {spec['dist']!r}: use one of "
                        f"{', '.join(d.value for d in Dist)}") from None
    keys = {Dist.UNIFORM: ("low", "high"), Dist.LOGUNIFORM: ("low", "high"),
            Dist.INTEGERS: ("low", "high"), Dist.NORMAL: ("mean", "std"),
            Dist.CHOICE: ("values",)}[dist]
    extra = set(spec) - {"dist", *keys}
    if extra:
        raise UserError(f"{w}: {', '.join(sorted(extra))}: not a parameter of {dist}; it "
                        f"takes {', '.join(keys)}")
    if dist is Dist.CHOICE:
        values = spec.get("values")
        if not isinstance(values, list) or not values:
            raise UserError(f"{w}: give values = [...], a non-empty list")
        return Distribution(dist, values=tuple(_scalar(key, v, w) for v in values))
    if dist is Dist.NORMAL:
        mean, std = _number(w, "mean", spec), _number(w, "std", spec)
        if std <= 0:
            raise UserError(f"{w}: std = {std:g} must be > 0")
        return Distribution(dist, mean=mean, std=std)
    low, high = _number(w, "low", spec), _number(w, "high", spec)
    if not low < high and not (dist is Dist.INTEGERS and low == high):
        raise UserError(f"{w}: low = {low:g} must be below high = {high:g}")
    if dist is Dist.LOGUNIFORM and low <= 0:
        raise UserError(f"{w}: a log-uniform distribution needs low > 0")
    if dist is Dist.INTEGERS and (low != int(low) or high != int(high)):
        raise UserError(f"{w}: integers take whole numbers for low and high")
    return Distribution(dist, low=low, high=high)


def _random(data: Mapping[str, Any], options: Mapping[str, Option], src: str
            ) -> tuple[tuple[Axis, ...], int, int]:
    where = f"{src}: [random]"
    n, seed = data.get("n", 1), data.get("seed", 0)
    for name, v, lo in (("n", n, 1), ("seed", seed, 0)):
        if isinstance(v, bool) or not isinstance(v, int) or v < lo:
            raise UserError(f"{where}: {name} = {v!r}: give a whole number ≥ {lo}")
    axes = []
    for key, spec in data.items():
        if key in ("n", "seed"):
            continue
        dist = _distribution(key, spec, where)
        kind, target = classify(key, dist.values[0] if dist.values else dist.low, options,
                                where)
        if kind is AxisKind.OPTION and options[key].flag:
            raise UserError(f"{where}: {key}: --{target} is a flag: put it in [grid] as "
                            "[true, false]")
        axes.append(Axis(key, kind, target, dist=dist))
    return tuple(axes), n, seed


def _grids(data: Any, options: Mapping[str, Option], src: str) -> tuple[tuple[Axis, ...], ...]:
    tables = data if isinstance(data, list) else [data]
    grids = []
    for i, table in enumerate(tables):
        where = f"{src}: [grid]" if not isinstance(data, list) else f"{src}: [[grid]] #{i + 1}"
        if not isinstance(table, dict):
            raise UserError(f"{where}: must be a table of axes")
        grids.append(tuple(_grid_axis(k, v, options, where) for k, v in table.items()))
    return tuple(grids) or ((),)


def _check_unique(grids: Sequence[Sequence[Axis]], random: Sequence[Axis], src: str) -> None:
    """An axis's target set twice in one point (two spellings, or in [grid] and [random])
    is refused."""
    for grid in grids:
        seen: dict[tuple[AxisKind, str], str] = {}
        for ax in (*grid, *random):
            k = (ax.kind, ax.target)
            if k in seen and ax.kind is not AxisKind.SETTINGS:
                raise UserError(f"{src}: {ax.key!r} and {seen[k]!r} set the same thing; keep "
                                "one")
            seen[k] = ax.key


def parse_campaign(text: str, source: str, options_of: Any) -> Campaign:
    """A :class:`Campaign` from the TOML ``text`` of ``source``; ``options_of(command)``
    gives the command's options (:func:`gateway.campaign.options.command_options`)."""
    try:
        data = tomllib.loads(text)
    except tomllib.TOMLDecodeError as exc:
        raise UserError(f"{source}: not valid TOML ({exc}); fix the syntax") from None
    for key in data:
        if key not in TABLES:
            raise UserError(f"{source}: [{key}]: unknown table; a campaign has "
                            f"{', '.join(TABLES)}")
    head = data.get("campaign", {})
    name, cmd = head.get("name"), head.get("command", "simulate")
    if not isinstance(name, str) or not re.fullmatch(r"[A-Za-z0-9][A-Za-z0-9._+-]*", name):
        raise UserError(f"{source}: [campaign] name = {name!r}: give a name of letters, digits "
                        "and . _ + - (it names the campaign's directory)")
    try:
        command = Command(cmd)
    except ValueError:
        raise UserError(f"{source}: [campaign] command = {cmd!r}: use \"simulate\" (the loop "
                        "without CAN) or \"sim\" (over CANopen against the emulator)") from None
    extra = set(head) - {"name", "command", "description"}
    if extra:
        raise UserError(f"{source}: [campaign] {', '.join(sorted(extra))}: unknown key; "
                        "[campaign] has name, command, description")
    options = options_of(command)
    base_where = f"{source}: [base]"
    base = dict(_setting(k, v, options, base_where) for k, v in data.get("base", {}).items())
    grids = _grids(data.get("grid", {}), options, source)
    random, n, seed = _random(data.get("random", {}), options, source)
    _check_unique(grids, random, source)
    criteria = tuple(parse_criterion(k, v, f"{source}: [pass]")
                     for k, v in data.get("pass", {}).items())
    from gateway.campaign.metrics import check_metric

    for c in criteria:
        check_metric(c.metric, f"{source}: [pass]")
    return Campaign(name=name, command=command, base=base, grids=grids, random=random, n=n,
                    seed=seed, criteria=criteria, description=str(head.get("description", "")),
                    source=source, text=text, options=options)


def load_campaign(path: str | Path) -> Campaign:
    """Read and check a campaign file."""
    from gateway.campaign.options import command_options

    p = Path(path)
    try:
        text = p.read_text(encoding="utf-8")
    except FileNotFoundError:
        raise UserError(f"{p}: no such campaign file; give the path of a campaign TOML file "
                        "(campaigns/*.toml are the shipped ones)") from None
    except (OSError, UnicodeDecodeError) as exc:
        raise UserError(f"{p}: cannot read it ({getattr(exc, 'strerror', None) or exc})"
                        ) from None
    return parse_campaign(text, str(p), command_options)
