"""The units of a drive's standard CiA 402 objects, in SI (pure).

A standard object carries an integer in the drive's units: the emulated drive's are fixed
(:data:`EMULATOR`: position 1/65536 revolution, velocity 0.001 rev/min, acceleration
0.001 rev/min per second, torque 1/1000 of the rated 10 N·m, current 1/1000 of the rated
10 A). A twin of another drive takes them from its EDS/DCF (:func:`units_from`) by the rule
of :mod:`dbc.units402`, the one the gateway's generated profiles use too, with the
emulator's rated torque and current where the file states none.
"""

from __future__ import annotations

from dbc import units402
from dbc.cia402 import (
    POSITION_UNIT,
    TARGET_POSITION,
    TARGET_TORQUE,
    TARGET_VELOCITY,
    VELOCITY_UNIT,
    OperationMode,
)
from dbc.units402 import ENCODER_INCREMENTS, DriveUnits, Lookup, Quantity
from plant.servo import I_RATED, T_RATED, TORQUE_UNIT

__all__ = ["EMULATOR", "ENCODER_INCREMENTS", "TARGETS", "DriveUnits", "Quantity",
           "units_from"]

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


def units_from(value: Lookup) -> tuple[DriveUnits, list[str]]:
    """A drive's units from its objects (:func:`dbc.units402.units_from`, the emulator's
    rated torque and current where the file has none) and one line per unit saying where
    it came from."""
    units, notes, _ = units402.units_from(value, rated_torque=T_RATED, rated_current=I_RATED)
    return units, [f"{q.value}: {text}" for q, text in notes.items()]
