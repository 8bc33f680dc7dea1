"""The units of a CiA 402 drive's standard objects in SI, from what its EDS or DCF states:
the one rule for the emulator's twin of a drive (``hil-plant run --eds``) and for the
profile ``hil-gateway profile new-drive`` writes (pure).

A standard object carries an integer in the drive's units. Where the file states them:

* position (0x6064, 0x607A): 0x60A8 (SI unit position) when it names revolutions, radians
  or degrees; else the factor group: one unit is 1/feed of a shaft revolution, feed = 0x6092
  (feed constant, sub 1 / sub 2), the shaft turning once per 0x6091 (gear ratio, sub 1 /
  sub 2) motor revolutions; without a feed constant one unit is one increment of the
  position encoder, 0x608F (sub 1 increments per sub 2 motor revolutions), assumed 65536
  per revolution when the file has none;
* velocity (0x606C, 0x60FF): 0x60A9 (SI unit velocity) when it names revolutions, radians
  or degrees per second, minute or hour (0x00B44700 is rev/min, 0xFDB44700 0.001 rev/min);
  else one position unit per second (CiA 402's default velocity unit);
* acceleration: one velocity unit per second (0x6097, the acceleration factor, is not
  applied);
* torque (0x6071, 0x6077): 1/1000 of the motor rated torque 0x6076 (mN·m); current: 1/1000
  of the motor rated current 0x6075 (mA); each assumed (the caller's rated values) when the
  file has none.

The SI unit codes (byte 3: the power of ten, signed; byte 2: the angle unit; byte 1: the time
unit) are CiA 303-2's. All rotation is the motor shaft's. What is assumed rather than read
is in the result's ``assumed``, for the TODO marks of a generated profile.
"""

from __future__ import annotations

import math
from collections.abc import Callable
from dataclasses import dataclass, field
from enum import Enum

__all__ = ["ENCODER_INCREMENTS", "DriveUnits", "Quantity", "StandardUnits", "decode_si_unit",
           "standard_units", "units_from"]

#: Increments per motor revolution assumed for a position encoder the file does not state.
ENCODER_INCREMENTS = 65536
#: CiA 303-2 unit codes: angle (numerator) → rad, time (denominator) → s.
_ANGLE = {0xB4: (2.0 * math.pi, "rev"), 0x10: (1.0, "rad"), 0x41: (math.pi / 180.0, "°")}
_TIME = {0x03: (1.0, "s"), 0x47: (60.0, "min"), 0x48: (3600.0, "h")}
_SI_POSITION, _SI_VELOCITY = 0x60A8, 0x60A9
_ENCODER, _GEAR, _FEED = 0x608F, 0x6091, 0x6092
_RATED_TORQUE, _RATED_CURRENT = 0x6076, 0x6075

#: ``value(index, subindex)``: an object's value as the file configures it, None if none.
Lookup = Callable[[int, int], int | None]


class Quantity(Enum):
    """What a standard object's integer measures."""

    POSITION = "position"
    VELOCITY = "velocity"
    ACCELERATION = "acceleration"
    TORQUE = "torque"
    CURRENT = "current"


@dataclass(frozen=True)
class DriveUnits:
    """One unit of each quantity in SI: rad, rad/s, rad/s², N·m, A."""

    position: float
    velocity: float
    acceleration: float
    torque: float
    current: float

    def of(self, quantity: Quantity) -> float:
        """One unit of ``quantity`` in SI."""
        return float(getattr(self, quantity.value))


def decode_si_unit(code: int | None, with_time: bool) -> tuple[float, str] | None:
    """A CiA 402 SI unit code of an angle (``with_time``: an angle per time, 0x60A9; else
    0x60A8) → (one unit in rad or rad/s, a description); None when it names anything
    else (a length, an unknown code)."""
    if code is None:
        return None
    exponent = (code >> 24) & 0xFF
    exponent -= 256 if exponent > 127 else 0
    num, den = (code >> 16) & 0xFF, (code >> 8) & 0xFF
    angle = _ANGLE.get(num)
    time = _TIME.get(den) if with_time else ((1.0, "") if den == 0 else None)
    if angle is None or time is None:
        return None
    scale = 10.0 ** exponent
    prefix = "" if exponent == 0 else f"{scale:g} "
    return scale * angle[0] / time[0], prefix + angle[1] + (f"/{time[1]}" if with_time else "")


def _ratio(value: Lookup, index: int) -> float | None:
    """sub 1 / sub 2 of a factor-group record (sub 2 absent: 1); None unless both are > 0."""
    num, den = value(index, 1), value(index, 2)
    if num is None:
        return None
    den = 1 if den is None else den
    return num / den if num > 0 and den > 0 else None


def units_from(value: Lookup, rated_torque: float = 10.0, rated_current: float = 10.0
               ) -> tuple[DriveUnits, dict[Quantity, str], frozenset[Quantity]]:
    """A drive's units from its objects (see the module docstring): the units, a line per
    quantity saying where it came from, and the quantities assumed (``rated_torque`` N·m
    and ``rated_current`` A where the file has no 0x6076, 0x6075)."""
    notes: dict[Quantity, str] = {}
    assumed: set[Quantity] = set()
    stated = decode_si_unit(value(_SI_POSITION, 0), with_time=False)
    increments = _ratio(value, _ENCODER)
    feed, gear = _ratio(value, _FEED), _ratio(value, _GEAR) or 1.0
    if stated is not None:
        position = stated[0]
        notes[Quantity.POSITION] = f"{stated[1]} (0x60A8)"
    elif feed is not None:
        position = 2.0 * math.pi * gear / feed
        notes[Quantity.POSITION] = (
            f"1/{feed:g} of a shaft revolution (0x6092), {gear:g} motor revolution(s) per "
            "shaft revolution" + (" (0x6091)" if value(_GEAR, 1) is not None else " (assumed)"))
    else:
        counts = increments or ENCODER_INCREMENTS
        position = 2.0 * math.pi / counts
        notes[Quantity.POSITION] = f"1 increment, {counts:g} per revolution " + (
            "(0x608F)" if increments else "(assumed: the file has no 0x60A8, 0x6092, 0x608F)")
        if not increments:
            assumed.add(Quantity.POSITION)
    stated_v = decode_si_unit(value(_SI_VELOCITY, 0), with_time=True)
    if stated_v is not None:
        velocity = stated_v[0]
        notes[Quantity.VELOCITY] = f"{stated_v[1]} (0x60A9)"
    else:
        velocity = position
        notes[Quantity.VELOCITY] = "1 position unit per second (CiA 402 default)"
        if Quantity.POSITION in assumed:
            assumed.add(Quantity.VELOCITY)
    notes[Quantity.ACCELERATION] = "1 velocity unit per second (CiA 402 default)"
    torque_mnm, current_ma = value(_RATED_TORQUE, 0), value(_RATED_CURRENT, 0)
    if torque_mnm:
        torque = torque_mnm * 1e-6
        notes[Quantity.TORQUE] = f"1/1000 of the rated {torque_mnm * 1e-3:g} N·m (0x6076)"
    else:
        torque = rated_torque / 1000.0
        notes[Quantity.TORQUE] = f"1/1000 of {rated_torque:g} N·m (assumed: no 0x6076)"
        assumed.add(Quantity.TORQUE)
    if current_ma:
        current = current_ma * 1e-6
        notes[Quantity.CURRENT] = f"1/1000 of the rated {current_ma * 1e-3:g} A (0x6075)"
    else:
        current = rated_current / 1000.0
        notes[Quantity.CURRENT] = f"1/1000 of {rated_current:g} A (assumed: no 0x6075)"
        assumed.add(Quantity.CURRENT)
    return (DriveUnits(position, velocity, velocity, torque, current), notes,
            frozenset(assumed))


@dataclass(frozen=True)
class StandardUnits:
    """The units a generated profile's DBC uses: velocity (rad/s), position (rad) and
    torque (N·m) per unit; sources: quantity name → where it came from; assumed: the
    quantity names the file does not state."""

    velocity: float
    position: float
    torque: float
    sources: dict[str, str] = field(default_factory=dict)
    assumed: frozenset[str] = frozenset()


def standard_units(get: Lookup) -> StandardUnits:
    """:func:`units_from` as a generated profile needs it (the twin's assumed rated torque,
    10 N·m, where the file has none)."""
    units, notes, assumed = units_from(get)
    return StandardUnits(units.velocity, units.position, units.torque,
                         {q.value: text for q, text in notes.items()},
                         frozenset(q.value for q in assumed))
