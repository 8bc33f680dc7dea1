"""The units of a CiA 402 drive's standard process data, from what its EDS or DCF states.

CiA 402 leaves the units of velocity and position to the drive; an EDS states them, where it
does, in these objects (read here in this order):

* velocity (0x606C, 0x60FF): 0x60A9 *SI unit velocity* — byte 3 the power of ten (signed),
  byte 2 the position unit, byte 1 the time unit (CiA 402 / CiA 303-2 unit codes: 0xB4
  revolution, 0x10 radian, 0x41 degree; 0x03 second, 0x47 minute, 0x48 hour): 0x00B44700 is
  rev/min, 0xFDB44700 0.001 rev/min. Else, with a position encoder resolution, position
  units per second (CiA 402's velocity without a velocity factor).
* position (0x6064, 0x607A): 0x60A8 *SI unit position* (as above, no time unit); else the
  position encoder resolution 0x608F (sub 1 increments per sub 2 motor revolutions).
* torque (0x6071, 0x6077): per mille of the motor rated torque 0x6076 (mN·m).

Where the file states nothing, :func:`standard_units` assumes (1 rev/min; 1/65536 rev;
a rated torque of 1 N·m) and says so in :attr:`StandardUnits.assumed`, for the profile's
TODO marks. Pure: ``get(index, sub)`` returns the file's value (a DCF's ParameterValue
first) or None.
"""

from __future__ import annotations

import math
from collections.abc import Callable
from dataclasses import dataclass, field

__all__ = ["StandardUnits", "decode_si_unit", "standard_units"]

#: CiA 303-2 unit codes of 0x60A8/0x60A9, byte 2: position unit → rad.
_POSITION_UNITS: dict[int, tuple[float, str]] = {
    0xB4: (2.0 * math.pi, "rev"), 0x10: (1.0, "rad"), 0x41: (math.pi / 180.0, "°"),
}
#: byte 1: time unit → s.
_TIME_UNITS: dict[int, tuple[float, str]] = {0x03: (1.0, "s"), 0x47: (60.0, "min"),
                                             0x48: (3600.0, "h")}
#: What is assumed where the file states nothing.
ASSUMED_VELOCITY = 2.0 * math.pi / 60.0  #: 1 rev/min, rad/s
ASSUMED_POSITION = 2.0 * math.pi / 65536.0  #: 1/65536 rev, rad
ASSUMED_RATED_TORQUE_MNM = 1000  #: 1 N·m


def decode_si_unit(value: int, with_time: bool) -> tuple[float, str] | None:
    """An SI-unit object's value (0x60A9 with ``with_time``, 0x60A8 without) as (SI value
    of one unit: rad/s or rad, text); None if it uses a unit code not known here."""
    exp = (value >> 24) & 0xFF
    exp = exp - 256 if exp >= 128 else exp
    pos = _POSITION_UNITS.get((value >> 16) & 0xFF)
    time = _TIME_UNITS.get((value >> 8) & 0xFF) if with_time else (1.0, "")
    if pos is None or time is None or (not with_time and (value >> 8) & 0xFF):
        return None
    scale = 10.0 ** exp
    prefix = "" if exp == 0 else f"{scale:g} "
    text = f"{prefix}{pos[1]}" + (f"/{time[1]}" if with_time else "")
    return scale * pos[0] / time[0], text


@dataclass(frozen=True)
class StandardUnits:
    """SI value of one unit of the standard objects, and where each came from.

    velocity: rad/s per unit of 0x606C/0x60FF; position: rad per unit of 0x6064/0x607A;
    torque: N·m per unit of 0x6071/0x6077; sources: quantity → how it was found;
    assumed: the quantities the file does not state.
    """

    velocity: float
    position: float
    torque: float
    sources: dict[str, str] = field(default_factory=dict)
    assumed: frozenset[str] = frozenset()


def standard_units(get: Callable[[int, int], int | None]) -> StandardUnits:
    """The units of a drive's standard objects from its file (module docstring)."""
    sources: dict[str, str] = {}
    assumed: set[str] = set()

    position = None
    si = get(0x60A8, 0)
    if isinstance(si, int) and (d := decode_si_unit(si, with_time=False)) is not None:
        position = d[0]
        sources["position"] = f"0x60A8 = 0x{si:08X}: {d[1]}"
    inc, revs = get(0x608F, 1), get(0x608F, 2)
    encoder = (2.0 * math.pi * revs / inc if isinstance(inc, int) and isinstance(revs, int)
               and inc > 0 and revs > 0 else None)
    if position is None and encoder is not None:
        position = encoder
        sources["position"] = f"0x608F = {inc} increments per {revs} rev"
    if position is None:
        position = ASSUMED_POSITION
        sources["position"] = "assumed 1/65536 rev (no 0x60A8 or 0x608F in the file)"
        assumed.add("position")

    velocity = None
    si = get(0x60A9, 0)
    if isinstance(si, int) and (d := decode_si_unit(si, with_time=True)) is not None:
        velocity = d[0]
        sources["velocity"] = f"0x60A9 = 0x{si:08X}: {d[1]}"
    elif encoder is not None:
        velocity = encoder
        sources["velocity"] = "position units per second (0x608F; no 0x60A9 in the file)"
    if velocity is None:
        velocity = ASSUMED_VELOCITY
        sources["velocity"] = "assumed 1 rev/min (no 0x60A9 or 0x608F in the file)"
        assumed.add("velocity")

    rated = get(0x6076, 0)
    if isinstance(rated, int) and rated > 0:
        torque = rated * 1e-6
        sources["torque"] = f"per mille of 0x6076 = {rated} mN.m"
    else:
        torque = ASSUMED_RATED_TORQUE_MNM * 1e-6
        sources["torque"] = "assumed per mille of 1 N·m (no 0x6076 rated torque in the file)"
        assumed.add("torque")
    return StandardUnits(velocity, position, torque, sources, frozenset(assumed))
