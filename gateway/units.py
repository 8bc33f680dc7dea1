"""Parsing of quantities given on the command line."""

from __future__ import annotations

import math
import re

from gateway.errors import UserError

_DURATION = re.compile(r"^\s*([0-9]*\.?[0-9]+(?:[eE][-+]?[0-9]+)?)\s*(s|ms|us|µs|ns)?\s*$")
_SCALE = {None: 1.0, "s": 1.0, "ms": 1e-3, "us": 1e-6, "µs": 1e-6, "ns": 1e-9}


def parse_duration(text: str, what: str = "duration") -> float:
    """'1ms', '250us', '250µs', '0.5 s', '1e-3' → seconds (float > 0).

    Raises :class:`UserError` naming ``what`` for anything else.
    """
    m = _DURATION.match(text)
    if not m and text.strip().startswith("-") and _DURATION.match(text.strip()[1:]):
        raise UserError(f"{what} {text!r} must be greater than zero")
    if not m:
        raise UserError(
            f"{what} {text!r} is not a duration: write a number with a unit, "
            "e.g. 1ms, 250us or 0.5s (a bare number is seconds)"
        )
    value = float(m.group(1)) * _SCALE[m.group(2)]
    if not math.isfinite(value):
        raise UserError(f"{what} {text!r} is too large to be a duration: write a finite "
                        "number with a unit, e.g. 10s")
    if not value > 0.0:
        raise UserError(f"{what} {text!r} must be greater than zero")
    return value


def parse_period(text: str, what: str = "--period", f_pwm: float | None = None) -> float:
    """A cycle period with its unit ('1ms', '250us') → seconds, checked by
    :func:`dbc.timing.check_period` (the same answer in `simulate`, `sim` and `run`).

    A bare number is refused: '1' would be one second, 1000 times the usual period, and
    '0.001' reads badly; the message asks for the unit. ``f_pwm``: the emulated drive's
    internal rate, Hz, when the period is for the emulator (None for a real drive).
    """
    from dbc.timing import check_period

    m = _DURATION.match(text)
    if m and m.group(2) is None:
        value = float(m.group(1))
        hint = (f"{format_duration(value)} if you meant {value:g} seconds" if value < 1.0
                else f"{value:g}ms or {value:g}us")
        raise UserError(f"{what} {text!r} has no unit: write it with one, e.g. {hint}")
    period = parse_duration(text, what)
    check_period(period, what, f_pwm)
    return period


def format_duration(seconds: float) -> str:
    """0.001 → '1ms', 0.00025 → '250us', 2.5 → '2.5s'."""
    for unit, scale in (("s", 1.0), ("ms", 1e-3), ("us", 1e-6)):
        if seconds >= scale:
            return f"{seconds / scale:g}{unit}"
    return f"{seconds / 1e-9:g}ns"
