"""CiA 402 vocabulary both sides use: power states, statusword, controlword.

States and statusword patterns (0x6041; CiA 402-2, "state coding"):

=========================  ============  =====  ======================
state                      pattern       mask   emulator's statusword
=========================  ============  =====  ======================
Not ready to switch on     x0xx 0000     0x4F   0x0200
Switch on disabled         x1xx 0000     0x4F   0x0240
Ready to switch on         x01x 0001     0x6F   0x0231
Switched on                x01x 0011     0x6F   0x0233
Operation enabled          x01x 0111     0x6F   0x0237
Quick stop active          x00x 0111     0x6F   0x0217
Fault reaction active      x0xx 1111     0x4F   0x020F
Fault                      x0xx 1000     0x4F   0x0208
=========================  ============  =====  ======================

(bit 9 "remote" is always set by the emulator, bit 4 "voltage enabled" in the energised
states, bit 11 "internal limit active" while the voltage limit clips.)

Controlword (0x6040) commands, bits 7, 3..0 (transition numbers of CiA 402-2):
shutdown 0xxx x110 (2, 6, 8), switch on 0xxx 0111 (3, 5), switch on + enable operation
0xxx 1111 (3 + 4, 4, 16), disable voltage 0xxx xx0x (7, 9, 10, 12), quick stop 0xxx x01x
(7, 10, 11), fault reset: rising edge of bit 7 (15).
"""

from __future__ import annotations

from enum import Enum, IntEnum


class State(IntEnum):
    """CiA 402 states; the value is the emulator's statusword without bits 9 and 11."""

    NOT_READY_TO_SWITCH_ON = 0x0000
    SWITCH_ON_DISABLED = 0x0040
    READY_TO_SWITCH_ON = 0x0031
    SWITCHED_ON = 0x0033
    OPERATION_ENABLED = 0x0037
    QUICK_STOP_ACTIVE = 0x0017
    FAULT_REACTION_ACTIVE = 0x000F
    FAULT = 0x0008

    @classmethod
    def from_statusword(cls, sw: int) -> State | None:
        """The state a statusword reports (the standard's masks); None if no pattern."""
        s = _BY_4F.get(sw & 0x4F)
        return s if s is not None else _BY_6F.get(sw & 0x6F)


_BY_4F = {0x00: State.NOT_READY_TO_SWITCH_ON, 0x40: State.SWITCH_ON_DISABLED,
          0x0F: State.FAULT_REACTION_ACTIVE, 0x08: State.FAULT}
_BY_6F = {0x21: State.READY_TO_SWITCH_ON, 0x23: State.SWITCHED_ON,
          0x27: State.OPERATION_ENABLED, 0x07: State.QUICK_STOP_ACTIVE}

SW_FAULT = 0x0008  #: statusword bit 3: fault
SW_REMOTE = 0x0200  #: statusword bit 9
SW_INTERNAL_LIMIT = 0x0800  #: statusword bit 11


class Controlword(IntEnum):
    """The controlword values the gateway writes (CiA 402-2, device control)."""

    DISABLE_VOLTAGE = 0x0000  #: → Switch on disabled (power stage off)
    QUICK_STOP = 0x0002  #: → Quick stop active / Switch on disabled
    SHUTDOWN = 0x0006  #: → Ready to switch on
    SWITCH_ON = 0x0007  #: → Switched on
    ENABLE_OPERATION = 0x000F  #: → Operation enabled
    FAULT_RESET = 0x0080  #: rising edge of bit 7: Fault → Switch on disabled


CW_FAULT_RESET_BIT = 0x0080  #: controlword bit 7


class Command(Enum):
    """The command a controlword encodes (bits 7, 3..0), as a device decodes it."""

    DISABLE_VOLTAGE = "disable voltage"
    QUICK_STOP = "quick stop"
    SHUTDOWN = "shutdown"
    SWITCH_ON = "switch on"
    ENABLE_OPERATION = "enable operation"

    @classmethod
    def decode(cls, cw: int) -> Command | None:
        """The command of controlword ``cw`` (bit 7 not considered); None if no pattern."""
        if cw & 0x0002 == 0:
            return cls.DISABLE_VOLTAGE
        if cw & 0x0006 == 0x0002:
            return cls.QUICK_STOP
        if cw & 0x0007 == 0x0006:
            return cls.SHUTDOWN
        if cw & 0x000F == 0x0007:
            return cls.SWITCH_ON
        if cw & 0x000F == 0x000F:
            return cls.ENABLE_OPERATION
        return None


#: The enable sequence: (controlword, the state it must reach).
ENABLE_SEQUENCE: tuple[tuple[Controlword, State], ...] = (
    (Controlword.SHUTDOWN, State.READY_TO_SWITCH_ON),
    (Controlword.SWITCH_ON, State.SWITCHED_ON),
    (Controlword.ENABLE_OPERATION, State.OPERATION_ENABLED),
)

#: Object indices of the CiA 402 objects both sides use.
CONTROLWORD = 0x6040
STATUSWORD = 0x6041
MODES_OF_OPERATION = 0x6060
MODES_OF_OPERATION_DISPLAY = 0x6061
ERROR_CODE = 0x603F


class OperationMode(IntEnum):
    """Modes of operation (0x6060) the emulated drive offers. The negative ones are the
    emulator's manufacturer-specific vector modes (what the paper's laws need); the others
    are CiA 402's standard modes, in which the drive runs its own field orientation (and
    speed loop): the profile modes take a target whenever the master sends one and ramp to
    it, the cyclic synchronous modes take one every SYNC."""

    VOLTAGE_VECTOR = -2
    CURRENT_VECTOR = -1
    PROFILE_VELOCITY = 3  #: PV: target velocity 0x60FF, ramped by 0x6083/0x6084
    PROFILE_TORQUE = 4  #: PT: target torque 0x6071, ramped by 0x6087
    CYCLIC_SYNC_POSITION = 8  #: CSP: target position 0x607A every SYNC
    CYCLIC_SYNC_VELOCITY = 9  #: CSV: target velocity 0x60FF every SYNC
    CYCLIC_SYNC_TORQUE = 10  #: CST: target torque 0x6071 every SYNC

    @property
    def supported_bit(self) -> int:
        """Its bit in 0x6502 (CiA 402: bit 2 PV, bit 3 PT, bit 7 CSP, bit 8 CSV, bit 9 CST;
        bits 16.. manufacturer)."""
        return {OperationMode.VOLTAGE_VECTOR: 1 << 17, OperationMode.CURRENT_VECTOR: 1 << 16,
                OperationMode.PROFILE_VELOCITY: 1 << 2, OperationMode.PROFILE_TORQUE: 1 << 3,
                OperationMode.CYCLIC_SYNC_POSITION: 1 << 7,
                OperationMode.CYCLIC_SYNC_VELOCITY: 1 << 8,
                OperationMode.CYCLIC_SYNC_TORQUE: 1 << 9}[self]

    @property
    def standard(self) -> bool:
        """A CiA 402 standard mode (the drive's own control), not a vector mode."""
        return self > 0

    @property
    def profiled(self) -> bool:
        """A profile mode (PV, PT): the drive ramps to the target itself."""
        return self in (OperationMode.PROFILE_VELOCITY, OperationMode.PROFILE_TORQUE)

    @property
    def torque(self) -> bool:
        """Its target is a torque (PT, CST)."""
        return self in (OperationMode.PROFILE_TORQUE, OperationMode.CYCLIC_SYNC_TORQUE)

    @classmethod
    def offered(cls, supported: int) -> frozenset[OperationMode]:
        """The modes whose bit a 0x6502 value ``supported`` sets."""
        return frozenset(m for m in cls if supported & m.supported_bit)


#: 0x6502 of the emulated drive: every :class:`OperationMode`.
SUPPORTED_DRIVE_MODES = sum(m.supported_bit for m in OperationMode)

#: Standard objects of the cyclic modes (CiA 402).
TARGET_TORQUE = 0x6071  #: INTEGER16, per mille of the rated torque 0x6076
MAX_TORQUE = 0x6072  #: UNSIGNED16, per mille of the rated torque
MOTOR_RATED_TORQUE = 0x6076  #: UNSIGNED32, mN·m
TORQUE_ACTUAL = 0x6077  #: INTEGER16, per mille of the rated torque
VELOCITY_ACTUAL = 0x606C  #: INTEGER32, velocity units
POSITION_ACTUAL = 0x6064  #: INTEGER32, position units
TARGET_POSITION = 0x607A  #: INTEGER32, position units
TARGET_VELOCITY = 0x60FF  #: INTEGER32, velocity units
VELOCITY_DEMAND = 0x606B  #: INTEGER32, velocity units (PV: the ramp's output)
VELOCITY_WINDOW = 0x606D  #: UNSIGNED16, velocity units (PV: target reached, bit 10)
VELOCITY_WINDOW_TIME = 0x606E  #: UNSIGNED16, ms
VELOCITY_THRESHOLD = 0x606F  #: UNSIGNED16, velocity units (PV: speed = 0, bit 12)
VELOCITY_THRESHOLD_TIME = 0x6070  #: UNSIGNED16, ms
TORQUE_DEMAND = 0x6074  #: INTEGER16, per mille of the rated torque (PT: the ramp's output)
MOTOR_RATED_CURRENT = 0x6075  #: UNSIGNED32, mA
CURRENT_ACTUAL = 0x6078  #: INTEGER16, per mille of the rated current
DC_LINK_VOLTAGE = 0x6079  #: UNSIGNED32, mV
PROFILE_ACCELERATION = 0x6083  #: UNSIGNED32, acceleration units
PROFILE_DECELERATION = 0x6084  #: UNSIGNED32, acceleration units
TORQUE_SLOPE = 0x6087  #: UNSIGNED32, per mille of the rated torque per second
TORQUE_PROFILE_TYPE = 0x6088  #: INTEGER16, 0 linear ramp
#: The factor group (CiA 402): encoder increments per motor revolutions (sub 1, sub 2),
#: motor revolutions per shaft revolutions, feed per shaft revolutions.
POSITION_ENCODER_RESOLUTION = 0x608F
GEAR_RATIO = 0x6091
FEED_CONSTANT = 0x6092
#: SI unit of position and velocity (CiA 402 / CiA 303-2 coding): bits 31..24 the power of
#: ten (signed), 23..16 the numerator's unit, 15..8 the denominator's.
SI_UNIT_POSITION = 0x60A8
SI_UNIT_VELOCITY = 0x60A9
SUPPORTED_MODES = 0x6502  #: UNSIGNED32, bits of :attr:`OperationMode.supported_bit`
#: Statusword bits of the profile modes (CiA 402): 10 target reached, 12 speed = 0 (PV).
SW_TARGET_REACHED = 0x0400
SW_SPEED_ZERO = 0x1000
#: Controlword bit 8: halt.
CW_HALT_BIT = 0x0100
#: The emulated drive's velocity unit (0x606C, 0x60FF): 0.001 rev/min, in rad/s.
VELOCITY_UNIT = 2.0 * 3.141592653589793 / 60000.0
#: The emulated drive's position unit (0x6064, 0x607A): 1/65536 of a revolution, in rad.
POSITION_UNIT = 2.0 * 3.141592653589793 / 65536.0
#: DBC signal names of the standard process data, by object (a drive profile's DBC may name
#: them so; the master maps them by index, whatever the EDS calls the object).
STANDARD_SIGNALS: dict[str, int] = {
    "target_torque": TARGET_TORQUE, "target_velocity": TARGET_VELOCITY,
    "torque_actual": TORQUE_ACTUAL, "velocity_actual": VELOCITY_ACTUAL,
    "target_position": TARGET_POSITION, "position_actual": POSITION_ACTUAL,
}

#: Supported drive modes (CiA 402 0x6502, UNSIGNED32): bit k−1 for standard mode k (1..10),
#: bits 16..31 manufacturer-specific.
SUPPORTED_DRIVE_MODES_OBJECT = 0x6502
#: CiA 402's standard modes of operation (0x6060 values), named.
STANDARD_MODE_NAMES: dict[int, str] = {
    1: "profile position (PP, 1)", 2: "velocity (vl, 2)", 3: "profile velocity (PV, 3)",
    4: "profile torque (TQ, 4)", 6: "homing (HM, 6)", 7: "interpolated position (IP, 7)",
    8: "cyclic synchronous position (CSP, 8)", 9: "cyclic synchronous velocity (CSV, 9)",
    10: "cyclic synchronous torque (CST, 10)",
}


def mode_bit(mode: int, emulator: bool = False) -> int | None:
    """The bit of 0x6502 that tells whether the drive offers mode of operation ``mode``:
    CiA 402's for the standard modes 1..10; the emulator's for its vector modes (another
    drive's manufacturer modes have no standard bit: None)."""
    if 1 <= mode <= 10:
        return 1 << (mode - 1)
    if emulator and mode in (OperationMode.CURRENT_VECTOR, OperationMode.VOLTAGE_VECTOR):
        return OperationMode(mode).supported_bit
    return None


def modes_in(supported: int) -> list[int]:
    """The standard modes (1..10) a 0x6502 value offers."""
    return [m for m in range(1, 11) if supported & (1 << (m - 1)) and m != 5]


def describe_mode(mode: int) -> str:
    """A mode of operation for messages: CiA 402's name, or "manufacturer mode N"."""
    return STANDARD_MODE_NAMES.get(mode, f"manufacturer-specific mode {mode}")
