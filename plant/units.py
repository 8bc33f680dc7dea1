"""The units of a drive's standard CiA 402 objects, in SI (pure).

A standard object carries an integer in the drive's units: the emulated drive's are fixed
(:data:`EMULATOR`: position 1/65536 revolution, velocity 0.001 rev/min, acceleration
0.001 rev/min per second, torque 1/1000 of the rated 10 N·m, current 1/1000 of the rated
10 A). A twin of another drive takes them from its EDS/DCF where the file states them
(:func:`units_from`), else from CiA 402's defaults:

* position: 0x60A8 (SI unit position) when it names revolutions or radians; else the
  factor group: one unit is 1/feed of a shaft revolution, feed = 0x6092 (feed constant,
  sub 1 / sub 2), the shaft turning once per 0x6091 (gear ratio, sub 1 / sub 2) motor
  revolutions; without a feed constant one unit is one increment of the position encoder,
  0x608F (sub 1 increments per sub 2 motor revolutions), assumed 65536 per revolution when
  the file has none;
* velocity: 0x60A9 (SI unit velocity) when it names revolutions or radians per minute or
  second; else one position unit per second (CiA 402's default velocity unit);
* acceleration: one velocity unit per second (0x6097, the acceleration factor, is not
  applied);
* torque: 1/1000 of the motor rated torque 0x6076 (mN·m), the emulator's 10 N·m without
  it; current: 1/1000 of the motor rated current 0x6075 (mA), 10 A without it.

All rotation is the motor shaft's: the model has one pole pair and no gearbox of its own.
"""

from __future__ import annotations

import math
from collections.abc import Callable
from dataclasses import dataclass
from enum import Enum

from dbc.cia402 import (
    FEED_CONSTANT,
    GEAR_RATIO,
    MOTOR_RATED_CURRENT,
    MOTOR_RATED_TORQUE,
    POSITION_ENCODER_RESOLUTION,
    POSITION_UNIT,
    SI_UNIT_POSITION,
    SI_UNIT_VELOCITY,
    TARGET_POSITION,
    TARGET_TORQUE,
    TARGET_VELOCITY,
    VELOCITY_UNIT,
    OperationMode,
)
from plant.servo import I_RATED, T_RATED, TORQUE_UNIT

#: Increments per motor revolution assumed for a position encoder the file does not state.
ENCODER_INCREMENTS = 65536
#: CiA 303-2 unit codes: revolution, radian (numerators), second, minute (denominators).
_REVOLUTION, _RADIAN, _SECOND, _MINUTE = 0xB4, 0x10, 0x03, 0x47
_ANGLE = {_REVOLUTION: 2.0 * math.pi, _RADIAN: 1.0}
_TIME = {_SECOND: 1.0, _MINUTE: 60.0}


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


#: The emulated drive's own units (those ``dbc/drive.eds`` states).
EMULATOR = DriveUnits(position=POSITION_UNIT, velocity=VELOCITY_UNIT,
                      acceleration=VELOCITY_UNIT, torque=TORQUE_UNIT, current=I_RATED / 1000)

#: Each standard mode's target object and the quantity it carries.
TARGETS: dict[OperationMode, tuple[int, Quantity]] = {
    OperationMode.PROFILE_VELOCITY: (TARGET_VELOCITY, Quantity.VELOCITY),
    OperationMode.PROFILE_TORQUE: (TARGET_TORQUE, Quantity.TORQUE),
    OperationMode.CYCLIC_SYNC_POSITION: (TARGET_POSITION, Quantity.POSITION),
    OperationMode.CYCLIC_SYNC_VELOCITY: (TARGET_VELOCITY, Quantity.VELOCITY),
    OperationMode.CYCLIC_SYNC_TORQUE: (TARGET_TORQUE, Quantity.TORQUE),
}

#: ``value(index, subindex)``: an object's present value, None where the file has none.
Lookup = Callable[[int, int], int | None]


def _ratio(value: Lookup, index: int) -> float | None:
    """sub 1 / sub 2 of a factor-group record (sub 2 absent: 1); None unless both are > 0."""
    num, den = value(index, 1), value(index, 2)
    if num is None:
        return None
    den = 1 if den is None else den
    return num / den if num > 0 and den > 0 else None


def _si_unit(code: int | None, per_time: bool) -> tuple[float, str] | None:
    """A CiA 402 SI unit code of an angle (``per_time``: an angle per second or minute) →
    (its size in rad or rad/s, a description); None when it names anything else."""
    if code is None:
        return None
    exponent = (code >> 24) & 0xFF
    exponent -= 256 if exponent > 127 else 0
    num, den = (code >> 16) & 0xFF, (code >> 8) & 0xFF
    if num not in _ANGLE or (den not in _TIME if per_time else den != 0):
        return None
    size = 10.0 ** exponent * _ANGLE[num] / (_TIME[den] if per_time else 1.0)
    name = ("rev" if num == _REVOLUTION else "rad") + (
        ("/s" if den == _SECOND else "/min") if per_time else "")
    return size, (f"1e{exponent} " if exponent else "") + name


def units_from(value: Lookup) -> tuple[DriveUnits, list[str]]:
    """A drive's units from its objects (see the module docstring) and one line for each
    unit saying where it came from."""
    notes: list[str] = []
    stated = _si_unit(value(SI_UNIT_POSITION, 0), per_time=False)
    increments = _ratio(value, POSITION_ENCODER_RESOLUTION)
    feed, gear = _ratio(value, FEED_CONSTANT), _ratio(value, GEAR_RATIO) or 1.0
    if stated is not None:
        position = stated[0]
        notes.append(f"position: {stated[1]} (0x60A8)")
    elif feed is not None:
        position = 2.0 * math.pi * gear / feed
        notes.append(f"position: 1/{feed:g} of a shaft revolution (0x6092), "
                     f"{gear:g} motor revolution(s) per shaft revolution"
                     + (" (0x6091)" if value(GEAR_RATIO, 1) is not None else " (assumed)"))
    else:
        counts = increments or ENCODER_INCREMENTS
        position = 2.0 * math.pi / counts
        notes.append(f"position: 1 increment, {counts:g} per revolution "
                     + ("(0x608F)" if increments else "(assumed: the file has no 0x608F)"))
    stated_v = _si_unit(value(SI_UNIT_VELOCITY, 0), per_time=True)
    if stated_v is not None:
        velocity = stated_v[0]
        notes.append(f"velocity: {stated_v[1]} (0x60A9)")
    else:
        velocity = position
        notes.append("velocity: 1 position unit per second (CiA 402 default)")
    notes.append("acceleration: 1 velocity unit per second (CiA 402 default)")
    rated_torque, rated_current = value(MOTOR_RATED_TORQUE, 0), value(MOTOR_RATED_CURRENT, 0)
    if rated_torque:
        torque = rated_torque * 1e-6
        notes.append(f"torque: 1/1000 of the rated {rated_torque * 1e-3:g} N·m (0x6076)")
    else:
        torque = TORQUE_UNIT
        notes.append(f"torque: 1/1000 of {T_RATED:g} N·m (assumed: no 0x6076)")
    if rated_current:
        current = rated_current * 1e-6
        notes.append(f"current: 1/1000 of the rated {rated_current * 1e-3:g} A (0x6075)")
    else:
        current = I_RATED / 1000
        notes.append(f"current: 1/1000 of {I_RATED:g} A (assumed: no 0x6075)")
    return DriveUnits(position, velocity, velocity, torque, current), notes
