"""How the drive runs: modes and frames as enums (the values are the command-line words).

:class:`DriveMode` is what the drive does with the setpoints, :class:`SetpointFrame` the
frame they are sent in, :class:`RpdoApply` when the drive makes received data active.
"""

from __future__ import annotations

from enum import IntEnum, StrEnum


class DriveMode(StrEnum):
    """What the drive does with the setpoints.

    IDEAL: the stator currents equal the setpoints (current-fed model; emulator only).
    CURRENT_LOOP: a PI current loop at the drive's internal rate (CiA 402 current vector
    mode on a real drive). VOLTAGE: the voltage setpoints are applied (voltage vector mode).
    TORQUE, VELOCITY, POSITION: a standard CiA 402 drive, which takes a target torque, speed
    or position every SYNC and runs its own field orientation (and speed and position loops):
    cyclic synchronous torque (CST), velocity (CSV) and position (CSP) modes, or the profile
    torque and velocity modes where the drive profile's [modes] says so.
    """

    IDEAL = "ideal"
    CURRENT_LOOP = "current-loop"
    VOLTAGE = "voltage"
    TORQUE = "torque"
    VELOCITY = "velocity"
    POSITION = "position"

    @property
    def mode_of_operation(self) -> int:
        """The emulator's 0x6060 value: −2 voltage vector mode, −1 current vector mode,
        10 CST, 9 CSV, 8 CSP."""
        return {DriveMode.VOLTAGE: -2, DriveMode.TORQUE: 10, DriveMode.VELOCITY: 9,
                DriveMode.POSITION: 8}.get(self, -1)

    @property
    def standard(self) -> bool:
        """A CiA 402 standard cyclic mode (the drive's own control), not a vector mode."""
        return self in (DriveMode.TORQUE, DriveMode.VELOCITY, DriveMode.POSITION)

    @property
    def target(self) -> str | None:
        """The role of a standard drive's target in this mode (N·m, rad/s, rad); None for
        the vector modes."""
        return {DriveMode.TORQUE: "target_torque", DriveMode.VELOCITY: "target_velocity",
                DriveMode.POSITION: "target_position"}.get(self)

    @property
    def emulator_model(self) -> int:
        """The emulator's 0x2202 value: 0 ideal current source, 1 PI current loop."""
        return 0 if self is DriveMode.IDEAL else 1


class SetpointFrame(StrEnum):
    """DQ: (d, q) setpoints that the drive turns from ε0 at ω0; AB: fixed-frame setpoints,
    held over the period."""

    DQ = "dq"
    AB = "ab"


class RpdoApply(IntEnum):
    """When the drive makes RPDO data active (the emulator's 0x2203).

    AT_NEXT_SYNC: CiA 301 synchronous RPDO, after the cycle that received them (one period
    of delay). ON_RECEIPT: before the next cycle's advance (no delay; emulator only).
    """

    AT_NEXT_SYNC = 0
    ON_RECEIPT = 1

    @classmethod
    def for_delay(cls, delay: int) -> RpdoApply:
        """Delay 1 → AT_NEXT_SYNC, delay 0 → ON_RECEIPT."""
        return cls.AT_NEXT_SYNC if delay == 1 else cls.ON_RECEIPT

    @property
    def delay(self) -> int:
        """Periods between a sample and the interval its setpoints act on."""
        return 1 if self is RpdoApply.AT_NEXT_SYNC else 0
