"""Tolerance files: how far each metric of a run may move from a baseline run's.

A TOML file of limits by the dotted key of ``summary.json`` (:mod:`gateway.dotted`)::

    "speed_error.rms" = { rel = 0.2, abs = 1e-4 }     # may grow by 1e-4 + 20 % of the baseline
    "peak_current" = { rel = 0.05, direction = "both" }
    [speed_error.windows.1]                             # the same, nested
    max = { rel = 0.5 }

A run fails a metric when its change from the baseline, in the limit's direction, is more
than ``abs + rel·|baseline|`` (:meth:`Limit.exceeded`): by default only growth counts
(``direction = "up"``: the metrics are errors, peaks and counts, where more is worse);
``"down"`` fails a decrease, ``"both"`` either.
"""

from __future__ import annotations

import math
import tomllib
from collections.abc import Mapping
from dataclasses import dataclass
from enum import StrEnum
from pathlib import Path
from typing import Any

from gateway.errors import UserError


class Direction(StrEnum):
    """Which change of a metric counts against its limit."""

    UP = "up"  #: growth (the default: errors, peaks, missed cycles)
    DOWN = "down"  #: a decrease (a metric where more is better)
    BOTH = "both"  #: either

    def excess(self, change: float) -> float:
        """The part of ``change`` (value − baseline) that counts in this direction."""
        return {Direction.UP: change, Direction.DOWN: -change,
                Direction.BOTH: abs(change)}[self]


#: The fields of one limit.
FIELDS = ("rel", "abs", "direction")


@dataclass(frozen=True)
class Limit:
    """The limit of one metric (``key``: dotted, into summary.json): ``abs`` in the
    metric's unit plus ``rel`` times the baseline's magnitude, in ``direction``."""

    key: str
    rel: float = 0.0
    abs: float = 0.0
    direction: Direction = Direction.UP

    def allowed(self, baseline: float) -> float:
        """How far the metric may move from ``baseline`` (≥ 0)."""
        return self.abs + self.rel * abs(baseline)

    def exceeded(self, baseline: float, value: float) -> bool:
        """Whether ``value`` moved from ``baseline`` by more than :meth:`allowed` in the
        limit's direction (a change equal to the limit passes)."""
        return self.direction.excess(value - baseline) > self.allowed(baseline)

    def describe(self) -> str:
        """The limit in words: ``abs 0.0001 + rel 0.2 × |baseline|, growth``."""
        what = {Direction.UP: "growth", Direction.DOWN: "decrease",
                Direction.BOTH: "either way"}[self.direction]
        return f"abs {self.abs:g} + rel {self.rel:g} × |baseline|, {what}"


def load_tolerances(path: Path) -> list[Limit]:
    """The limits of a tolerance file, in its order; :class:`UserError` naming the file,
    the key and the fix for anything wrong."""
    try:
        doc = tomllib.loads(path.read_text(encoding="utf-8"))
    except OSError as exc:
        raise UserError(f"--tolerance {path}: cannot read it ({exc.strerror or exc})") from exc
    except (tomllib.TOMLDecodeError, UnicodeDecodeError) as exc:
        raise UserError(f"--tolerance {path}: not valid TOML: {exc}") from exc
    limits: list[Limit] = []
    _collect(path, doc, "", limits)
    if not limits:
        raise UserError(f"--tolerance {path}: names no metric; give limits by the dotted key "
                        "of summary.json, e.g. \"speed_error.rms\" = { rel = 0.2, abs = 1e-4 } "
                        "(examples/tolerance.toml)")
    return limits


def _collect(path: Path, table: Mapping[str, Any], prefix: str, out: list[Limit]) -> None:
    """Walk the file's tables: a table of limit fields only is a limit at its dotted key."""
    for name, value in table.items():
        key = f"{prefix}{name}"
        if not isinstance(value, Mapping):
            raise UserError(f"--tolerance {path}: {key} = {value!r}: a limit is a table such "
                            f"as \"{key}\" = {{ rel = 0.2, abs = 1e-4 }} (fields "
                            f"{', '.join(FIELDS)})")
        fields = [k for k in value if k in FIELDS]
        if not fields:
            _collect(path, value, f"{key}.", out)
            continue
        other = [k for k in value if k not in FIELDS]
        if other:
            raise UserError(f"--tolerance {path}: {key} has {', '.join(other)}, which a "
                            f"limit does not know: its fields are {', '.join(FIELDS)}")
        out.append(_limit(path, key, value))


def _limit(path: Path, key: str, fields: Mapping[str, Any]) -> Limit:
    values: dict[str, float] = {}
    for name, unit in (("rel", "a fraction of the baseline"), ("abs", "in the metric's unit")):
        x = fields.get(name, 0.0)
        number = isinstance(x, int | float) and not isinstance(x, bool)
        if not number or not math.isfinite(x) or x < 0:
            raise UserError(f"--tolerance {path}: {key}.{name} = {x!r}: give a number ≥ 0 "
                            f"({unit})")
        values[name] = float(x)
    raw = fields.get("direction", Direction.UP.value)
    try:
        direction = Direction(raw)
    except ValueError:
        raise UserError(f"--tolerance {path}: {key}.direction = {raw!r}: give "
                        f"{', '.join(repr(d.value) for d in Direction)} (up: only growth "
                        "fails, the default)") from None
    return Limit(key, values["rel"], values["abs"], direction)
