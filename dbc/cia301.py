"""CiA 301 vocabulary both sides use: NMT, COB-ID bases, SYNC, EMCY codes.

Pure constants and enums; no I/O.
"""

from __future__ import annotations

from enum import IntEnum, StrEnum

#: COB-ID function codes (CiA 301 pre-defined connection set): base + node id.
NMT_ID = 0x000
SYNC_ID = 0x080
EMCY_BASE = 0x080
SDO_TX_BASE = 0x580  #: server → client
SDO_RX_BASE = 0x600  #: client → server
HEARTBEAT_BASE = 0x700

#: PDO COB-ID function codes of the pre-defined connection set: code → (is RPDO, number).
PDO_FUNCTIONS: dict[int, tuple[bool, int]] = {
    0x180: (False, 1), 0x200: (True, 1), 0x280: (False, 2), 0x300: (True, 2),
    0x380: (False, 3), 0x400: (True, 3), 0x480: (False, 4), 0x500: (True, 4),
}
#: Communication and mapping parameter indices of PDO 1 (PDO n: + n − 1).
RPDO_COMM, RPDO_MAP, TPDO_COMM, TPDO_MAP = 0x1400, 0x1600, 0x1800, 0x1A00


def pdo_of(cob_id: int) -> tuple[bool, int]:
    """(is RPDO, PDO number 1..4) of a COB-ID of the pre-defined connection set;
    ValueError for any other COB-ID."""
    try:
        return PDO_FUNCTIONS[cob_id & 0x780]
    except KeyError:
        raise ValueError(f"COB-ID 0x{cob_id:03X} is not a PDO of the pre-defined connection "
                         "set (0x180..0x57F)") from None


TIME_ID = 0x100
LSS_IDS = (0x7E4, 0x7E5)  #: LSS slave → master, master → slave


def is_service(cob_id: int) -> bool:
    """Whether an 11-bit COB-ID is one of CiA 301's services of the pre-defined connection
    set (NMT, SYNC, EMCY, TIME, SDO, heartbeat / boot-up, LSS) and so not process data."""
    node = cob_id & 0x7F
    return (cob_id in (NMT_ID, SYNC_ID, TIME_ID, *LSS_IDS)
            or (cob_id & 0x780 in (EMCY_BASE, SDO_TX_BASE, SDO_RX_BASE, HEARTBEAT_BASE)
                and node != 0))


#: The device profile number (0x1000 bits 0..15) of a CiA 402 drive.
DRIVE_PROFILE = 402
#: CiA 402's drive types: 0x1000 bits 16..23 of a drive.
_DRIVE_TYPES = {0x01: "frequency converter", 0x02: "servo drive", 0x03: "stepper motor",
                0xFF: "multiple device module"}


def is_drive(device_type: int) -> bool:
    """Whether a device type (0x1000) names the CiA 402 drive profile."""
    return device_type & 0xFFFF == DRIVE_PROFILE


def describe_device_type(device_type: int) -> str:
    """What a device type (0x1000) says of the device, for a message: its device profile
    (bits 0..15; 0 is none) and, for a CiA 402 drive, its type (bits 16..23)."""
    profile = device_type & 0xFFFF
    if profile == 0:
        return "no standard device profile: a CiA 301 device, not a CiA 402 drive"
    if profile != DRIVE_PROFILE:
        return f"a CiA {profile} device, not a CiA 402 drive"
    kind = (device_type >> 16) & 0xFF
    return f"a CiA 402 {_DRIVE_TYPES.get(kind, f'drive of type 0x{kind:02X}')}"


#: SYNC counter overflow (0x1019) the gateway configures: the counter runs 1..240.
SYNC_OVERFLOW = 240


def sync_counter(k: int) -> int:
    """The SYNC counter of cycle k (k = 1, 2, …): 1..SYNC_OVERFLOW, then 1 again."""
    return ((k - 1) % SYNC_OVERFLOW) + 1


def sync_periods(last: int, counter: int, overflow: int = SYNC_OVERFLOW) -> int:
    """The periods that passed from the SYNC with counter ``last`` to the one with
    ``counter`` (both 1..``overflow``): 1 for the next SYNC, more where the counter skipped
    values (a producer held up skips the SYNCs it could not send: the counter tells the
    time, at most overflow − 1 periods; a counter equal to the last one counts as the
    next)."""
    return (counter - last - 1) % overflow + 1 if counter != last else 1


class NmtCommand(IntEnum):
    """NMT command specifiers (first byte of COB-ID 0x000)."""

    START = 0x01
    STOP = 0x02
    ENTER_PRE_OPERATIONAL = 0x80
    RESET_NODE = 0x81
    RESET_COMMUNICATION = 0x82


class NmtState(StrEnum):
    """NMT states, spelled as python-canopen spells them (``node.nmt.state``)."""

    INITIALISING = "INITIALISING"
    PRE_OPERATIONAL = "PRE-OPERATIONAL"
    OPERATIONAL = "OPERATIONAL"
    STOPPED = "STOPPED"

    @property
    def heartbeat(self) -> int:
        """The state byte of the heartbeat (0x00 is the boot-up message)."""
        return _HEARTBEAT_BYTE[self]

    @classmethod
    def from_heartbeat(cls, byte: int) -> NmtState | None:
        """The state a heartbeat byte reports (bit 7, the toggle bit, ignored); None if none."""
        return _FROM_HEARTBEAT.get(byte & 0x7F)


_HEARTBEAT_BYTE = {
    NmtState.INITIALISING: 0x00,
    NmtState.STOPPED: 0x04,
    NmtState.OPERATIONAL: 0x05,
    NmtState.PRE_OPERATIONAL: 0x7F,
}
_FROM_HEARTBEAT = {v: k for k, v in _HEARTBEAT_BYTE.items()}


class Emcy(IntEnum):
    """The EMCY error codes (CiA 301 table 21, CiA 402) the emulator raises and the
    gateway names."""

    NO_ERROR = 0x0000  #: error reset / no error
    #: generic error: a handler of the emulator raised (a bug; the cause is not known, so
    #: the code names no class)
    INTERNAL = 0x1000
    OVERCURRENT = 0x2310  #: continuous over-current
    #: device software, internal: the emulated motor model reached a non-finite state
    #: (NaN/inf: the numerical model failed, no physical quantity to name)
    MODEL_NON_FINITE = 0x6100
    HEARTBEAT = 0x8130  #: life guard / heartbeat error (the master's heartbeat lost)
    PDO_LENGTH = 0x8210  #: PDO not processed due to length error
    RPDO_TIMEOUT = 0x8250  #: RPDO timeout
    #: CiA 402 (IEC 61800-7-201) 0x8400 velocity speed controller: over-speed |ω| > w_max.
    #: 0x7310 (sensor: speed) would name a faulty speed sensor, not a speed too high.
    OVERSPEED = 0x8400

    @property
    def text(self) -> str:
        """What the code means, for messages."""
        return _EMCY_TEXT[self]

    @classmethod
    def describe(cls, code: int) -> str:
        """The text of any EMCY code (a drive's own codes: by class)."""
        try:
            return cls(code).text
        except ValueError:
            return "drive-specific error"

    @property
    def error_register(self) -> int:
        """Bits of the error register 0x1001 this code sets: generic (bit 0) plus current
        (bit 1), communication (bit 4, 0x81xx/0x82xx) or device profile specific (bit 5,
        CiA 402's 0x84xx) by the code's class."""
        return _ERROR_REGISTER.get(self >> 8, _ERROR_REGISTER.get(self >> 12, 0x01))


_EMCY_TEXT = {
    Emcy.NO_ERROR: "error reset / no error",
    Emcy.INTERNAL: "internal error of the drive (a handler failed)",
    Emcy.OVERCURRENT: "over-current",
    Emcy.MODEL_NON_FINITE: "drive model state not finite (NaN/inf); model reset to rest",
    Emcy.HEARTBEAT: "heartbeat of the master lost",
    Emcy.PDO_LENGTH: "PDO of wrong length",
    Emcy.RPDO_TIMEOUT: "RPDO timeout",
    Emcy.OVERSPEED: "over-speed (|w_m| beyond w_max)",
}
#: Error register 0x1001 bits per EMCY code class (first hex digit, or the first two).
_ERROR_REGISTER = {0x2: 0x03, 0x81: 0x11, 0x82: 0x11, 0x84: 0x21}
