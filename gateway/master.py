"""The CANopen master side of the gateway: bring a CiA 402 drive up, watch it, bring it down.

python-canopen does NMT, SDO, heartbeat and EMCY; the cyclic PDO exchange is done by
:mod:`gateway.loop` with the fast codec, on the same bus and the same notifier thread.

Sequence (:meth:`DriveMaster.connect` … :meth:`DriveMaster.shutdown`):

1. identify the device at the node by SDO reads only (:meth:`DriveMaster.identify`:
   0x1000 device type, 0x1018 vendor/product/revision) against the profile; a device that
   is not the profile's (or, for the emulator's profile, not the emulator) is refused
   before any NMT command or write. Then heartbeat/boot-up callbacks registered, NMT
   *reset communication*, wait for the boot-up;
2. SDO: configure in PRE-OPERATIONAL:
   cycle period 0x1006, synchronous window 0x1007, producer heartbeat 0x1017, consumer
   heartbeat 0x1016 (the gateway's own heartbeat), PDO mappings and transmission types
   (every SYNC), RPDO deadline 0x140x.5, mode of operation 0x6060, emulator objects;
3. NMT OPERATIONAL; the gateway's heartbeat producer starts; the watch is armed once the
   drive's heartbeat reports OPERATIONAL;
4. CiA 402 enable sequence on 0x6040/0x6041 (shutdown → switch on → enable operation);
5. shutdown (:meth:`DriveMaster.shutdown`), on every exit path: the power stage off
   through the CiA 402 state machine, confirmed by an SDO read of the statusword; if the
   drive does not answer SDO (NMT STOPPED), NMT PRE-OPERATIONAL and again; if still not
   confirmed and the drive is one the gateway configured that stopped answering, NMT
   *reset node* and its boot-up (never for a drive that answers with an SDO abort, nor one
   not identified or configured). The drive's supervision of the gateway
   (0x1016) is switched off only once the power stage is confirmed off; otherwise the
   gateway's heartbeat stops with the supervision on, so the drive trips by itself, and
   the run is reported unsafe.

While the watch is armed, an EMCY, a lost drive heartbeat, a boot-up or an NMT state
other than OPERATIONAL sets :attr:`DriveMaster.fault` (with a :class:`FaultEvent` naming
it), which the loop checks every cycle.
"""

from __future__ import annotations

import contextlib
import logging
import math
import struct
import threading
import time
from collections.abc import Callable, Iterable
from dataclasses import dataclass, field

import can
import canopen
from canopen.pdo.base import PdoMap
from canopen.sdo.exceptions import SdoAbortedError, SdoCommunicationError

from dbc.cia301 import (
    EMCY_BASE,
    HEARTBEAT_BASE,
    NMT_ID,
    Emcy,
    NmtCommand,
    NmtState,
    describe_device_type,
    is_drive,
    pdo_of,
)
from dbc.cia402 import (
    CONTROLWORD,
    ENABLE_SEQUENCE,
    MODES_OF_OPERATION,
    STATUSWORD,
    SUPPORTED_DRIVE_MODES_OBJECT,
    SW_FAULT,
    Controlword,
    State,
    describe_mode,
    mode_bit,
    modes_in,
)
from dbc.edsfile import read_eds
from dbc.timing import LOCKSTEP_BACKSTOP_S
from gateway.drive_profile import DriveProfile
from gateway.eds import find_object, object_for
from gateway.errors import UserError
from gateway.process_data import Pdo, ProcessData
from gateway.stop import StopReason

#: CiA 301: bit 31 of a PDO's COB-ID (sub-index 1): the PDO is not valid (not sent).
PDO_NOT_VALID = 1 << 31

log = logging.getLogger(__name__)


@dataclass
class FaultEvent:
    """Something that stops the loop: an EMCY, a lost heartbeat, a boot-up or NMT change.

    time: ``time.monotonic()``; kind: 'EMCY', 'heartbeat', 'boot-up', 'NMT'; code: the EMCY
    code; reason: the stop reason it gives the run.
    """

    time: float
    kind: str
    code: int | None = None
    text: str = ""
    reason: StopReason = StopReason.DRIVE_FAULT

    def describe(self) -> str:
        code = "" if self.code is None else f" 0x{self.code:04X}"
        return f"{self.kind}{code}: {self.text}"


@dataclass(frozen=True)
class Identity:
    """What answered at the node: device type (0x1000) and 0x1018 vendor, product and
    revision (None: the device aborted the read, it has no such object)."""

    device_type: int | None
    vendor: int | None = None
    product: int | None = None
    revision: int | None = None

    def describe(self) -> str:
        def hx(x: int | None) -> str:
            return "none" if x is None else f"0x{x:08X}"
        return (f"device type {hx(self.device_type)}, vendor {hx(self.vendor)}, product "
                f"{hx(self.product)}, revision {hx(self.revision)}")


class DeviceRefusedError(UserError):
    """The device at the node is not the one the drive profile describes (or answers no
    identity): refused by SDO reads alone, before any NMT command or write. ``fix`` says
    what to do, in a few words (a check's "fix" line)."""

    def __init__(self, message: str, fix: str) -> None:
        super().__init__(message)
        self.fix = fix


@dataclass
class MasterState:
    """What the master saw of the drive."""

    faults: list[FaultEvent] = field(default_factory=list)
    last_heartbeat: float = 0.0
    nmt_state: NmtState | None = None
    #: the gateway's heartbeats the bus refused (bus-off, a full queue); it goes on
    heartbeat_send_errors: int = 0


@dataclass
class ShutdownReport:
    """What the shutdown did and whether the drive's power stage was confirmed off.

    safe: confirmed off (by statusword, or by the boot-up after a reset node). state: the
    last CiA 402 state read (name), or None. steps: what was done, in order.
    supervision_off: 0x1016 was switched off (only when safe).
    """

    safe: bool = False
    state: str | None = None
    steps: list[str] = field(default_factory=list)
    supervision_off: bool = False

#: How long the shutdown retries while the bus refuses frames (a controller recovering
#: from bus-off), s.
BUS_OFF_RETRY_S = 3.0

#: CiA 402 states in which the power stage applies no voltage to the motor.
POWER_OFF_STATES = (State.NOT_READY_TO_SWITCH_ON, State.SWITCH_ON_DISABLED,
                    State.READY_TO_SWITCH_ON, State.SWITCHED_ON, State.FAULT)


def keep_sending(task: can.broadcastmanager.CyclicSendTaskABC,
                 refused: Callable[[Exception], bool]) -> can.broadcastmanager.CyclicSendTaskABC:
    """``task``, going on across sends the bus refuses (a bus-off, a full queue): python-can's
    cyclic thread stops at the first one unless told otherwise; ``refused(exc)`` is told
    each and returns True to go on. (The kernel's broadcast manager, on SocketCAN, goes on
    by itself.)"""
    if isinstance(task, can.broadcastmanager.ThreadBasedCyclicSendTask):
        task.on_error = refused
    return task


def _objects_text(mapped: list[tuple[int, int, int]]) -> str:
    """Mapped objects as "0xIIII.S/bits, …"."""
    return ", ".join(f"0x{i:04X}.{s}/{b}" for i, s, b in mapped) or "none"


class DriveMaster:
    """NMT, SDO configuration, CiA 402 enable/disable and monitoring of one drive."""

    def __init__(self, bus: can.BusABC, profile: DriveProfile, node_id: int | None = None,
                 gateway_node: int | None = None) -> None:
        self.bus = bus
        self.profile = profile
        self.node_id = node_id or profile.node
        self.gateway_node = gateway_node or profile.gateway_node
        if self.gateway_node == self.node_id:
            raise UserError(f"the gateway's node id {self.gateway_node} (its heartbeat) is the "
                            f"drive's: choose another with --gateway-node or [drive].gateway_node "
                            f"in {profile.source}")
        #: what the configuration left out (objects the drive has not), for the account
        self.notes: list[str] = []
        self.network = canopen.Network(bus)
        self.network.NOTIFIER_CYCLE = 0.1
        try:
            self.node = canopen.RemoteNode(self.node_id, read_eds(profile.eds, self.node_id).od)
        except UserError as exc:
            raise UserError(f"drive profile {profile.source}: {exc}") from None
        self.node.sdo.RESPONSE_TIMEOUT = profile.sdo_timeout_s
        self.network.add_node(self.node)
        self.state = MasterState()
        self.fault = threading.Event()
        self._booted = threading.Event()
        self._operational = threading.Event()  # an OPERATIONAL heartbeat since start()
        self._heartbeat_task: can.broadcastmanager.CyclicSendTaskABC | None = None
        self._watchdog: threading.Thread | None = None
        self._stop_watchdog = threading.Event()
        self._connected = False
        self._configured = False  # we wrote to it (configure())
        self._refused = False  # the shutdown's SDO was answered with an abort
        self._send_refused = False  # the bus refused the shutdown's frames (bus-off)
        self.identity: Identity | None = None  #: the device at the node, once identified
        self._armed = False  # the NMT watch: set by start(), cleared by shutdown()
        self._lockstep = False  # the loop's time is the SYNC count (start())
        self.shutdown_report: ShutdownReport | None = None

    # ------------------------------------------------------------------ connection

    def connect(self, listeners: list[can.Listener] | None = None) -> None:
        """Start the notifier (with extra ``listeners``, e.g. the bus log), subscribe to
        heartbeat and EMCY, identify the device at the node (:meth:`identify`: SDO reads
        only), and only then reset its communication and await the boot-up. A device that
        is not the profile's is refused before anything is sent to it."""
        self.network.connect()
        self._connected = True
        for listener in listeners or []:
            self.network.notifier.add_listener(listener)
        self.network.subscribe(HEARTBEAT_BASE + self.node_id, self._on_heartbeat)
        self.network.subscribe(EMCY_BASE + self.node_id, self._on_emcy)
        self.identity = self.identify()
        self._booted.clear()
        # reset communication (callbacks already registered)
        self.nmt_command(NmtCommand.RESET_COMMUNICATION)
        if not self._booted.wait(self.profile.boot_timeout_s):
            raise UserError(
                f"node {self.node_id} ({self.identity.describe()}) sent no boot-up within "
                f"{self.profile.boot_timeout_s:g} s after an NMT reset communication. Check "
                "that its heartbeat/boot-up is not disabled and the bitrate.")

    def nmt_command(self, command: NmtCommand) -> None:
        """Send an NMT command to the drive (python-canopen's NMT object is not used: its
        bookkeeping fails on a heartbeat byte it does not know)."""
        self.network.send_message(NMT_ID, bytes([command, self.node_id]))

    def _on_heartbeat(self, can_id: int, data: bytearray, timestamp: float) -> None:
        if not data:
            return
        state = NmtState.from_heartbeat(data[0])
        self.state.last_heartbeat = time.monotonic()
        self.state.nmt_state = state
        if state is NmtState.INITIALISING:  # the boot-up message
            self._booted.set()
        elif state is NmtState.OPERATIONAL:
            self._operational.set()
        if not self._armed or state is NmtState.OPERATIONAL:
            return
        if state is NmtState.INITIALISING:
            self._raise(FaultEvent(time.monotonic(), "boot-up", None,
                                   f"drive node {self.node_id} rebooted during the run",
                                   StopReason.DRIVE_STATE))
        else:
            shown = state or f"0x{data[0]:02X}"
            self._raise(FaultEvent(time.monotonic(), "NMT", None,
                                   f"drive node {self.node_id} left OPERATIONAL: {shown}",
                                   StopReason.DRIVE_STATE))

    def _on_emcy(self, can_id: int, data: bytearray, timestamp: float) -> None:
        if len(data) < 2:
            return
        code = struct.unpack_from("<H", data)[0]
        if code == Emcy.NO_ERROR:
            return  # error reset
        self._raise(FaultEvent(time.monotonic(), "EMCY", code, Emcy.describe(code)))

    def _raise(self, event: FaultEvent) -> None:
        self.state.faults.append(event)
        log.warning("drive fault: %s", event.describe())
        self.fault.set()

    @property
    def first_fault(self) -> FaultEvent | None:
        """The first fault seen while armed (the cause; later ones are consequences)."""
        return self.state.faults[0] if self.state.faults else None

    def _read_identity(self, index: int, sub: int) -> int | None:
        """One identity object by SDO: its value, None when the device aborts (an answer:
        it has no such object); no answer at all raises :class:`SdoCommunicationError`."""
        try:
            return int(self._entry(index, sub).raw)
        except SdoAbortedError:
            return None
        except KeyError:  # not in the profile's EDS: ask the device anyway
            try:
                return int.from_bytes(self.node.sdo.upload(index, sub)[:4], "little")
            except SdoAbortedError:
                return None

    def identify(self) -> Identity:
        """Which device answers at the node, by SDO reads only (0x1000, 0x1018 vendor,
        product, revision), checked against the drive profile before any NMT command or
        write: the device type must be the profile's; the vendor and product must be those
        its EDS states (where it states them), and for a profile of the emulator
        (``emulator = true``, whose own objects 0x2202 … are written) the emulator's, always.
        Refused with what answered and why; nothing was sent to the device then."""
        try:
            device_type = self._read_identity(0x1000, 0)
        except SdoCommunicationError as exc:
            raise UserError(
                f"no drive at node {self.node_id} on the bus: no SDO answer to a read of "
                f"0x1000 (device type) within {self.profile.sdo_timeout_s:g} s ({exc}). "
                "Nothing but that read was sent to the node: no write, no NMT command. "
                "Check the node id (--node), that the drive is powered, connected and not in "
                "NMT STOPPED (which answers no SDO), the bitrate, and for the emulator that "
                "`hil-plant run` is running on the same channel (`hil-gateway scan` lists the "
                "nodes present).") from exc
        ident = Identity(device_type,
                         *(self._read_identity(0x1018, sub) for sub in (1, 2, 3)))
        where = f"node {self.node_id} ({ident.describe()})"
        nothing = "Nothing was written to it and no NMT command sent."
        other_profile = (f"check --node, or give the drive's own profile with --drive "
                         f"(profile used: {self.profile.source})")
        fix = f"{nothing} Check --node, or give its own drive profile with --drive " \
              f"(profile used: {self.profile.source})."
        expected = self.profile.device_type
        if device_type is None:
            raise DeviceRefusedError(f"{where} aborted the read of its device type (0x1000): it "
                                f"is not a CiA 301 device the profile describes. {fix}",
                                other_profile)
        if expected is not None and device_type != expected:
            if is_drive(device_type):
                what_to_do, short = fix, other_profile
            else:  # not a drive at all: no drive profile fits it
                short = ("check --node (`hil-gateway scan` lists each node with its device "
                         "type; a drive's has the profile number 402, 0x192)")
                what_to_do = (f"{nothing} No drive profile fits a device that is not a "
                              f"CiA 402 drive: {short}.")
            raise DeviceRefusedError(
                f"{where} is not the drive the profile describes: device type "
                f"0x{device_type:08X} (0x1000: {describe_device_type(device_type)}), "
                f"expected 0x{expected:08X} ({describe_device_type(expected)}). "
                f"{what_to_do}", short)
        want = self._eds_identity()
        if self.profile.emulator:
            if (ident.vendor, ident.product) != want:
                raise DeviceRefusedError(
                    f"{where} is not the can-drive-hil emulator that the profile names "
                    f"(vendor 0x{want[0]:08X}, product 0x{want[1]:08X} in 0x1018): the "
                    f"emulator's own objects (model, RPDO apply, internal rate, time base) "
                    f"exist on no other device. {fix}", other_profile)
        else:
            for what, got, exp in (("vendor", ident.vendor, want[0]),
                                   ("product", ident.product, want[1])):
                if exp and got is not None and got != exp:
                    raise DeviceRefusedError(f"{where} is not the drive the profile describes: "
                                        f"{what} 0x{got:08X} (0x1018), its EDS states "
                                        f"0x{exp:08X}. {fix}", other_profile)
            if not any(want) or ident.vendor is None:
                self.notes.append(f"node {self.node_id} identified by its device type only "
                                  f"({ident.describe()}; the EDS states no vendor/product)")
        return ident

    def _eds_identity(self) -> tuple[int, int]:
        """(vendor, product) as the profile's EDS states them in 0x1018 (0: not stated)."""
        out = []
        for sub in (1, 2):
            try:
                var = self.node.object_dictionary[0x1018][sub]
                out.append(int(var.default or 0))
            except (KeyError, TypeError, ValueError):
                out.append(0)
        return out[0], out[1]

    # -------------------------------------------------------------------------- SDO

    def _entry(self, index: int, sub: int):
        obj = self.node.sdo[index]
        return obj[sub] if isinstance(obj, canopen.sdo.Record | canopen.sdo.Array) else obj

    def _sdo_failure(self, exc: BaseException) -> str:
        """Why an SDO transfer failed, for a message: refused (an abort: the drive answered,
        with its code) or not answered in time (slow or gone; where to give it longer)."""
        if isinstance(exc, SdoCommunicationError):
            return (f"no answer within {self.profile.sdo_timeout_s:g} s ({exc}): the drive is "
                    "slow or gone; if it is slow, raise [timing].sdo_timeout_s in the drive "
                    f"profile ({self.profile.source})")
        return f"refused: {exc}"

    def sdo_read(self, index: int, sub: int = 0) -> int | float:
        """Read one object; failures become :class:`UserError` naming the object."""
        try:
            return self._entry(index, sub).raw
        except (SdoAbortedError, SdoCommunicationError, KeyError) as exc:
            raise UserError(f"SDO read of 0x{index:04X}.{sub} from node {self.node_id}: "
                            f"{self._sdo_failure(exc)}") from exc

    def sdo_write(self, index: int, sub: int, value: int | float, what: str = "") -> None:
        """Write one object; an abort becomes a :class:`UserError` saying what was configured."""
        label = f" ({what})" if what else ""
        try:
            self._entry(index, sub).raw = value
        except ValueError as exc:
            raise UserError(
                f"configuring node {self.node_id}: {value!r} does not fit object "
                f"0x{index:04X}.{sub}{label} of the EDS ({exc}); check the drive profile "
                f"({self.profile.source})") from exc
        except SdoCommunicationError as exc:
            raise UserError(
                f"configuring node {self.node_id} failed: SDO write of {value!r} to "
                f"0x{index:04X}.{sub}{label}: {self._sdo_failure(exc)}.") from exc
        except (SdoAbortedError, KeyError) as exc:
            raise UserError(
                f"configuring node {self.node_id} failed: SDO write of {value!r} to "
                f"0x{index:04X}.{sub}{label} was refused: {exc}. Check the drive profile "
                f"({self.profile.source}) against the drive's EDS, and that the drive is in "
                "PRE-OPERATIONAL.") from exc

    def find_object(self, name: str) -> canopen.objectdictionary.ODVariable | None:
        """The EDS variable of that ParameterName (an object or a sub-index); None if the
        drive's EDS has none."""
        return find_object(self.node.object_dictionary, name)

    def write_by_name(self, name: str, value: int | float) -> bool:
        """Write an object found by its EDS name; False if the drive has no such object."""
        var = self.find_object(name)
        if var is None:
            return False
        self.sdo_write(var.index, var.subindex, value, name)
        return True

    # ------------------------------------------------------------------ configuration

    def has(self, index: int) -> bool:
        """The drive's EDS has object ``index``."""
        return index in self.node.object_dictionary

    def _optional(self, index: int, sub: int, value: int, what: str) -> bool:
        """Write an optional communication object only where the EDS has it; else noted."""
        if not self.has(index):
            self.notes.append(f"0x{index:04X} ({what}) not written: the drive's EDS has none")
            return False
        self.sdo_write(index, sub, value, what)
        return True

    def configure(self, period: float, pd: ProcessData, remap: bool, mode: int,
                  emulator_objects: dict[str, int | float], sync_overflow: int = 0) -> bool:
        """PRE-OPERATIONAL configuration by SDO (see the module docstring); returns whether
        SYNC carries a counter (0x1019 written).

        pd: the drive's process data; remap: write each PDO's mapping (else read it back
        and check it against the DBC). mode: 0x6060 value. emulator_objects: EDS name →
        value for the emulator's own objects (ignored on drives without them). Optional
        objects (0x1006, 0x1007, 0x1016, 0x1017, 0x1019) are written only where the EDS has
        them; what was left out is in :attr:`notes`.
        """
        self._configured = True
        self.nmt_command(NmtCommand.ENTER_PRE_OPERATIONAL)
        p = self.profile
        for name, value in emulator_objects.items():  # f_pwm first: 0x1006 must fit it
            self.write_by_name(name, value)
        self._startup_writes()
        self._check_mode(mode)
        counter = False
        if sync_overflow and self.has(0x1019):
            try:
                self._entry(0x1019, 0).raw = sync_overflow
            except SdoAbortedError:  # CiA 301: 0x1019 may only change while 0x1006 = 0
                self.sdo_write(0x1006, 0, 0, "cycle period 0 while 0x1019 changes")
                self.sdo_write(0x1019, 0, sync_overflow, "SYNC counter overflow value")
            counter = True
        elif sync_overflow:
            self.notes.append("0x1019 (SYNC counter overflow) not written: the drive's EDS has "
                              "none; SYNC carries no counter")
        self._optional(0x1006, 0, round(period * 1e6), "communication cycle period, µs")
        self._optional(0x1007, 0, 0, "synchronous window length, µs (0 = off)")
        self._optional(0x1017, 0, p.heartbeat_ms, "producer heartbeat time, ms")
        self._optional(0x1016, 1, (self.gateway_node << 16) | p.heartbeat_timeout_ms,
                       "consumer heartbeat of the gateway")
        for pdo in pd.pdos:
            if remap:
                self._map_pdo(pdo)
            else:
                self._check_mapping(pdo)
        if remap:
            self._disable_unused(pd)
        self.sdo_write(MODES_OF_OPERATION, 0, mode, "modes of operation")
        return counter

    def _startup_writes(self) -> None:
        """The drive profile's [[sdo]] list, in order: each written, then read back and
        compared; a refusal or a different read-back is a :class:`UserError` naming it."""
        for w in self.profile.sdo:
            self.sdo_write(w.index, w.sub, w.value, w.note or "start-up write")
            back = self.sdo_read(w.index, w.sub)
            same = (math.isclose(float(back), float(w.value), rel_tol=1e-6, abs_tol=1e-9)
                    if isinstance(back, float) or isinstance(w.value, float) else back == w.value)
            if not same:
                raise UserError(f"node {self.node_id}: the start-up write {w.describe()} was "
                                f"accepted but reads back {back!r}; the drive changed or "
                                f"limited the value: check it against the drive's manual "
                                f"([[sdo]] in {self.profile.source})")

    def _check_mode(self, mode: int) -> None:
        """Where the EDS has 0x6502 (supported drive modes), the drive must offer ``mode``
        (CiA 402's bit of a standard mode; the emulator's bits of its vector modes)."""
        bit = mode_bit(mode, emulator=self.profile.emulator)
        if bit is None or not self.has(SUPPORTED_DRIVE_MODES_OBJECT):
            return
        supported = int(self.sdo_read(SUPPORTED_DRIVE_MODES_OBJECT, 0))
        if not supported & bit:
            offered = ", ".join(describe_mode(m) for m in modes_in(supported)) or "none"
            raise UserError(f"node {self.node_id} does not offer mode of operation "
                            f"{describe_mode(mode)}: its 0x6502 (supported drive modes) is "
                            f"0x{supported:08X}, which offers {offered}; choose one of those "
                            f"in [modes] of {self.profile.source} or another --drive-mode")

    def _pdo_map(self, pdo: Pdo) -> PdoMap:
        """python-canopen's map object of that PDO (number from the COB-ID)."""
        rx, n = pdo_of(pdo.cob_id)
        maps = self.node.rpdo if rx else self.node.tpdo
        try:
            return maps[n]
        except KeyError:
            raise UserError(f"{pdo.name}: the drive's EDS has no {'R' if rx else 'T'}PDO {n} "
                            f"(COB-ID 0x{pdo.cob_id:03X}); check the drive profile "
                            f"({self.profile.source})") from None

    def object_of(self, signal: str, role: str, message: str = ""
                  ) -> canopen.objectdictionary.ODVariable | None:
        """The EDS object a PDO signal of ``message`` maps (:func:`gateway.eds.object_for`;
        the profile's [objects] entry first)."""
        return object_for(self.node.object_dictionary, signal, role,
                          self.profile.objects.get(f"{message}.{signal}"))

    def _objects_of(self, pdo: Pdo) -> list[tuple[int, int, int]]:
        """The EDS objects a PDO maps: named like its DBC signals (CiA 402's controlword and
        statusword by index). A CiA 301 mapping packs objects back to back, little-endian:
        a DBC message with gaps or Motorola signals cannot be written so."""
        bit = 0
        for spec in pdo.codec.signals:
            start = bit if spec.start is None else spec.start
            if spec.big_endian or start != bit:
                raise UserError(
                    f"{pdo.name}.{spec.name}: the DBC lays it out "
                    + ("in Motorola byte order" if spec.big_endian else
                       f"at bit {start}, not right after the signal before (bit {bit})")
                    + ", which a PDO mapping written by SDO cannot reproduce (objects back to "
                    "back, Intel order): map the PDO on the drive and set remap = false in "
                    f"{self.profile.source}")
            bit += spec.bits
        entries = []
        for (signal, role), spec in zip(pdo.signals, pdo.codec.signals, strict=True):
            var = self.object_of(signal, role, pdo.name)
            if var is None:
                raise UserError(
                    f"the drive's EDS ({self.profile.eds}) has no object named {signal!r} for "
                    f"{pdo.name}.{signal}: name it in the drive profile's [objects] "
                    f"(\"{pdo.name}.{signal}\" = \"0xIIII.S\"), name the object like the DBC "
                    "signal, or set remap = false in the drive profile and configure the "
                    "mapping on the drive")
            entries.append((var.index, var.subindex, spec.bits))
        return entries

    def _map_pdo(self, pdo: Pdo) -> None:
        """Write one PDO's mapping with python-canopen's map object (CiA 301 procedure:
        disable, map, enable), synchronous every SYNC, RPDO deadline from the profile
        where the communication record has an event timer (sub-index 5)."""
        m = self._pdo_map(pdo)
        where = (f"configuring node {self.node_id}: mapping {pdo.name} (COB-ID "
                 f"0x{pdo.cob_id:03X})")
        try:
            entries = self._objects_of(pdo)
            self._check_records(pdo, m, len(entries))
            m.read(from_od=True)
            m.clear()
            for index, sub, bits in entries:
                m.add_variable(index, sub, bits)
            m.cob_id = pdo.cob_id
            m.trans_type = self.profile.transmission_type  # synchronous, every n-th SYNC
            m.rtr_allowed = True  # leave bit 30 clear, as the EDS defaults have it
            if not pdo.tx and 5 in m.com_record.od:
                m.event_timer = self.profile.rpdo_timeout_ms
            elif not pdo.tx:
                self.notes.append(
                    f"{pdo.name}: 0x{m.com_record.od.index:04X} has no sub-index 5 (event "
                    "timer) in the EDS, so the drive is not given the RPDO deadline "
                    f"({self.profile.rpdo_timeout_ms} ms)")
            m.enabled = True
            m.save()
        except SdoCommunicationError as exc:
            raise UserError(f"{where}: {self._sdo_failure(exc)}.") from exc
        except SdoAbortedError as exc:
            raise UserError(f"{where} was refused: {exc}. Check the drive profile "
                            f"({self.profile.source}) against the drive's EDS.") from exc
        except KeyError as exc:  # python-canopen: a sub-index the EDS does not have
            raise UserError(f"{where}: the drive's EDS ({self.profile.eds}) lacks an entry "
                            f"it needs ({exc}); check its 0x{m.com_record.od.index:04X} and "
                            f"0x{m.map_array.od.index:04X} records") from None
        finally:  # the loop decodes PDOs itself: no python-canopen PDO callbacks
            with contextlib.suppress(KeyError, ValueError):  # not subscribed if it failed
                self.network.unsubscribe(pdo.cob_id, m.on_message)

    def _disable_unused(self, pd: ProcessData) -> None:
        """Set the not-valid bit (31 of sub-index 1) of every PDO of the pre-defined
        connection set (RPDO/TPDO 1..4) the EDS has and the profile does not use, where the
        drive has it valid: its frames would take bus time every cycle for nothing (a lean
        mapping). A profile using them all writes nothing."""
        used = {pdo_of(p.cob_id) for p in pd.pdos}
        for rx, base in ((True, 0x1400), (False, 0x1800)):
            for n in range(1, 5):
                index = base + n - 1
                if (rx, n) in used or not self.has(index):
                    continue
                what = f"{'R' if rx else 'T'}PDO{n} not used by the profile: disabled"
                cob_id = int(self.sdo_read(index, 1))
                if not cob_id & PDO_NOT_VALID:
                    self.sdo_write(index, 1, cob_id | PDO_NOT_VALID, what)

    def _check_records(self, pdo: Pdo, m: PdoMap, n_objects: int) -> None:
        """The EDS's communication record has sub-indices 1 and 2 and its mapping record
        sub-indices 0..``n_objects``; a :class:`UserError` naming what is missing."""
        com, mapping = m.com_record.od, m.map_array.od
        missing = [f"0x{com.index:04X}.{k}" for k in (1, 2) if k not in com]
        if 0 not in mapping:
            missing.append(f"0x{mapping.index:04X}.0")
        if missing:
            raise UserError(f"{pdo.name}: the drive's EDS ({self.profile.eds}) has no "
                            f"{', '.join(missing)}, which a PDO needs (CiA 301: COB-ID, "
                            "transmission type, number of mapped objects)")
        gaps = [k for k in range(1, n_objects + 1) if k not in mapping]
        if gaps:
            raise UserError(f"{pdo.name}: the DBC message has {n_objects} signals but the "
                            f"drive's mapping record 0x{mapping.index:04X} has no sub-index "
                            f"{', '.join(map(str, gaps))} in the EDS; split the message or "
                            f"check the EDS ({self.profile.eds})")

    def _check_mapping(self, pdo: Pdo) -> None:
        """remap = false: read the drive's mapping of that PDO and check it carries the
        objects of the DBC message's roles, in order and size, on its COB-ID."""
        problems = self.mapping_problems(pdo)
        if problems:
            raise UserError(f"{pdo.name} on node {self.node_id} does not match the drive "
                            f"profile's DBC ({'; '.join(problems)}): map it on the drive as "
                            f"the DBC says, or set remap = true ({self.profile.source})")

    def read_mapping(self, pdo: Pdo) -> PdoMap:
        """The drive's mapping of that PDO, read by SDO (python-canopen's map object)."""
        m = self._pdo_map(pdo)
        try:
            m.read(from_od=False)
        except (SdoAbortedError, SdoCommunicationError) as exc:
            raise UserError(f"reading the mapping of {pdo.name} from node {self.node_id}: "
                            f"{self._sdo_failure(exc)}") from exc
        except KeyError as exc:  # python-canopen: a sub-index the EDS does not have
            raise UserError(f"reading the mapping of {pdo.name} from node {self.node_id}: "
                            f"the drive's EDS ({self.profile.eds}) lacks an entry of "
                            f"0x{m.com_record.od.index:04X} or 0x{m.map_array.od.index:04X} "
                            f"({exc}) that the drive uses") from None
        finally:  # the map subscribed on the COB-ID it read, which may not be the DBC's
            for cob_id in {pdo.cob_id, (m.cob_id or 0) & 0x7FF}:
                with contextlib.suppress(KeyError, ValueError):
                    self.network.unsubscribe(cob_id, m.on_message)
        return m

    def mapping_problems(self, pdo: Pdo) -> list[str]:
        """Read the drive's mapping of that PDO by SDO and compare it with the DBC message:
        COB-ID, enable bit, and each mapped object (index, sub-index, length) against the
        object the signal's role should carry (:meth:`object_of`: the profile's [objects]
        first); the differences ([] if none)."""
        m = self.read_mapping(pdo)
        problems = []
        if (m.cob_id or 0) & 0x7FF != pdo.cob_id:
            problems.append(f"COB-ID 0x{(m.cob_id or 0) & 0x7FF:03X}, the DBC says "
                            f"0x{pdo.cob_id:03X}")
        if not m.enabled:
            problems.append("not enabled")
        mapped = [(v.index, v.subindex, v.length) for v in m.map]
        want = []
        for (signal, role), spec in zip(pdo.signals, pdo.codec.signals, strict=True):
            var = self.object_of(signal, role, pdo.name)
            want.append((signal, None if var is None else (var.index, var.subindex), spec.bits))
        if len(mapped) != len(want):
            problems.append(f"{len(mapped)} objects mapped ({_objects_text(mapped)}), the DBC "
                            f"has {len(want)} signals ({', '.join(w[0] for w in want)})")
            return problems
        for k, ((index, sub, bits), (signal, obj, want_bits)) in enumerate(
                zip(mapped, want, strict=True), 1):
            where = f"entry {k} ({pdo.name}.{signal})"
            if obj is None:
                problems.append(f"{where}: the EDS names no object for it, so what the drive "
                                f"maps there (0x{index:04X}.{sub}) cannot be checked; name it "
                                f"in [objects] as \"{pdo.name}.{signal}\" = \"0xIIII.S\"")
            elif (index, sub) != obj:
                problems.append(f"{where}: the drive maps 0x{index:04X}.{sub}, the role needs "
                                f"0x{obj[0]:04X}.{obj[1]}")
            elif bits != want_bits:
                problems.append(f"{where}: 0x{index:04X}.{sub} mapped with {bits} bits, the "
                                f"DBC's signal has {want_bits}")
        return problems

    # ------------------------------------------------------------------ operation

    @property
    def heartbeat_period(self) -> float:
        """The gateway's heartbeat producer period, s: three in the drive's consumer time."""
        return max(0.01, self.profile.heartbeat_timeout_ms / 3000.0)

    def start(self, lockstep: bool = False, alive_ids: Iterable[int] = ()) -> None:
        """NMT OPERATIONAL and the gateway's heartbeat producer; once the drive's heartbeat
        reports OPERATIONAL, the watch is armed and the watchdog starts.

        The watch waits for that confirmation: a heartbeat the drive sent before it acted on
        the NMT command (still PRE-OPERATIONAL) may arrive after the command went out, and
        is not a drive leaving OPERATIONAL. No confirmation within the heartbeat watch time
        is an error naming the state the drive last reported.

        ``lockstep``: the loop's time is the SYNC count, not the wall clock. A drive that
        answers every SYNC is alive whatever its heartbeat timer does on a loaded host, so
        the frames ``alive_ids`` (its TPDOs) count as heartbeats, and the watch is only the
        backstop for a drive that answers nothing for :data:`LOCKSTEP_BACKSTOP_S` (or the
        profile's time if longer).
        """
        self._lockstep = lockstep
        for cob_id in alive_ids:
            self.network.subscribe(cob_id, self._on_alive)
        msg = can.Message(arbitration_id=HEARTBEAT_BASE + self.gateway_node,
                          data=[NmtState.OPERATIONAL.heartbeat], is_extended_id=False)
        self._heartbeat_task = keep_sending(self.bus.send_periodic(msg, self.heartbeat_period),
                                            self._heartbeat_refused)
        self._operational.clear()
        self.nmt_command(NmtCommand.START)
        limit = self._watch_limit()
        if not self._operational.wait(limit):
            last = self.state.nmt_state
            raise UserError(
                f"drive node {self.node_id} did not report OPERATIONAL within {limit:g} s of "
                f"the NMT start command (its last heartbeat: {last or 'none'}). Check the "
                "drive's error log (0x1003) and its NMT error behaviour (0x1029), and that "
                "its heartbeat (0x1017) is on.")
        self.state.last_heartbeat = time.monotonic()
        self._stop_watchdog.clear()
        self._watchdog = threading.Thread(target=self._watch, name="drive-watchdog",
                                          daemon=True)
        self._watchdog.start()
        self._armed = True

    def _heartbeat_refused(self, exc: Exception) -> bool:
        """A heartbeat the bus refused: counted; the heartbeat goes on (True)."""
        self.state.heartbeat_send_errors += 1
        return True

    def _on_alive(self, can_id: int, data: bytearray, timestamp: float) -> None:
        """A frame that only a live drive sends (lockstep: a TPDO answering our SYNC)."""
        self.state.last_heartbeat = time.monotonic()

    def _watch_limit(self) -> float:
        """The drive heartbeat consumer time, s: the profile's ``drive_heartbeat_timeout_ms``,
        at least 3 producer periods (in lockstep at least :data:`LOCKSTEP_BACKSTOP_S`)."""
        limit = max(self.profile.drive_heartbeat_timeout_ms, 3 * self.profile.heartbeat_ms) / 1e3
        return max(limit, LOCKSTEP_BACKSTOP_S) if self._lockstep else limit

    def _watch(self) -> None:
        """Drive heartbeat consumer: no heartbeat (in lockstep: nor TPDO) within the watch
        limit → fault. A wake-up of this thread that came late by half the limit means this
        process was held up (a loaded host): the drive's frames may still wait in the
        receive queue, so that turn does not judge the drive."""
        limit = self._watch_limit()
        last_wake = time.monotonic()
        while not self._stop_watchdog.wait(limit / 4):
            now = time.monotonic()
            held_up = now - last_wake > 0.75 * limit
            last_wake = now
            if held_up:
                continue
            if now - self.state.last_heartbeat > limit and not self.fault.is_set():
                what = "no heartbeat and no TPDO" if self._lockstep else "no heartbeat"
                self._raise(FaultEvent(now, "heartbeat", None,
                                       f"drive node {self.node_id} silent for {limit:g} s "
                                       f"({what})"))

    def statusword(self) -> int:
        """0x6041 by SDO."""
        return int(self.sdo_read(STATUSWORD, 0))

    def _await_state(self, state: State, timeout: float = 1.0) -> int:
        t_end = time.monotonic() + timeout
        sw = self.statusword()
        while State.from_statusword(sw) is not state and time.monotonic() < t_end:
            time.sleep(0.005)
            sw = self.statusword()
        return sw

    def enable(self) -> None:
        """CiA 402: (fault reset) → shutdown → switch on → enable operation, checked."""
        sw = self.statusword()
        if sw & SW_FAULT:
            self.sdo_write(CONTROLWORD, 0, Controlword.DISABLE_VOLTAGE, "controlword")
            self.sdo_write(CONTROLWORD, 0, Controlword.FAULT_RESET, "controlword fault reset")
        for cw, state in ENABLE_SEQUENCE:
            self.sdo_write(CONTROLWORD, 0, cw, "controlword")
            sw = self._await_state(state)
            if State.from_statusword(sw) is not state:
                name = state.name.replace("_", " ").capitalize()
                raise UserError(
                    f"node {self.node_id} did not reach the CiA 402 state {name!r}: statusword "
                    f"0x{sw:04X} after controlword 0x{cw:04X}. The drive may be in fault or "
                    "refuse to enable (check its EMCY messages and DC link).")

    def _power_off_confirmed(self, report: ShutdownReport) -> bool:
        """Controlword 'disable voltage' by SDO, then the statusword until the power stage is
        off (at most 1 s); False when the drive does not answer or stays on."""
        try:
            self._entry(CONTROLWORD, 0).raw = Controlword.DISABLE_VOLTAGE
            report.steps.append("controlword disable voltage (SDO)")
            t_end = time.monotonic() + 1.0
            while True:
                state = State.from_statusword(int(self._entry(STATUSWORD, 0).raw))
                report.state = state.name if state is not None else None
                if state in POWER_OFF_STATES:
                    report.steps.append(f"statusword confirms {state.name}")
                    return True
                if time.monotonic() > t_end:
                    report.steps.append(f"statusword still {report.state} after 1 s")
                    return False
                time.sleep(0.005)
        except SdoAbortedError as exc:  # an answer: the drive is there and refused
            report.steps.append(f"SDO abort ({exc})")
            self._refused = True
            log.warning("disable voltage on node %d refused: %s", self.node_id, exc)
            return False
        except can.CanError as exc:  # the bus refused the frame: bus-off, adapter gone
            if not any(s.startswith("the bus refused") for s in report.steps):
                report.steps.append(f"the bus refused the SDO request ({exc})")
            self._send_refused = True
            return False
        except Exception as exc:
            report.steps.append(f"no SDO answer ({type(exc).__name__}: {exc})")
            log.warning("disable voltage on node %d failed: %s", self.node_id, exc)
            return False

    def _reset_node_confirmed(self, report: ShutdownReport) -> bool:
        """NMT reset node: the drive restarts with its power stage off; confirmed by its
        boot-up message."""
        self._booted.clear()
        try:
            self.nmt_command(NmtCommand.RESET_NODE)
        except Exception as exc:
            report.steps.append(f"NMT reset node not sent: {exc}")
            return False
        report.steps.append("NMT reset node")
        if self._booted.wait(max(1.0, self.profile.boot_timeout_s)):
            report.steps.append("boot-up confirms the reset")
            report.state = None
            return True
        report.steps.append("no boot-up after the reset")
        return False

    def _across_bus_off(self, report: ShutdownReport) -> bool:
        """The bus refuses to send (bus-off): retry the power-off every 50 ms for
        :data:`BUS_OFF_RETRY_S` while the controller recovers."""
        t_end = time.monotonic() + BUS_OFF_RETRY_S
        tries = 0
        while time.monotonic() < t_end:
            time.sleep(0.05)
            tries += 1
            self._send_refused = False
            if self._power_off_confirmed(report):
                report.steps.insert(len(report.steps) - 2, f"the bus took frames again after "
                                    f"{tries} retries (bus-off recovered)")
                return True
            if not self._send_refused:  # it sends again, but the drive did not confirm
                return False
        report.steps.append(f"the bus still refused frames after {BUS_OFF_RETRY_S:g} s")
        return False

    def bring_down(self) -> ShutdownReport:
        """Power stage off, confirmed (see the module docstring, step 5). NMT reset node is
        the last resort, only for a drive the gateway configured and that stopped answering
        SDO; a drive that answers with an SDO abort is not reset."""
        report = ShutdownReport()
        self._refused = False
        self._send_refused = False
        reset = False
        safe = self._power_off_confirmed(report)
        if not safe and self._send_refused:
            safe = self._across_bus_off(report)
        if not safe:
            try:
                self.nmt_command(NmtCommand.ENTER_PRE_OPERATIONAL)
                report.steps.append("NMT pre-operational")
            except Exception as exc:
                report.steps.append(f"NMT pre-operational not sent: {exc}")
            safe = self._power_off_confirmed(report)
        if not safe and self._refused:
            report.steps.append("NMT reset node not sent: the drive answers (an SDO abort is "
                                "an answer, not silence)")
        elif not safe and not self._configured:
            report.steps.append("NMT reset node not sent: the gateway had not configured the "
                                "drive")
        elif not safe:  # the last resort, for a drive we configured that stopped answering
            safe = reset = self._reset_node_confirmed(report)
        report.safe = safe
        if safe and not reset:
            try:
                self.nmt_command(NmtCommand.ENTER_PRE_OPERATIONAL)
                report.steps.append("NMT pre-operational")
                # confirmed off: the drive need no longer watch the gateway's heartbeat
                if self.has(0x1016):
                    self._entry(0x1016, 1).raw = 0
                    report.supervision_off = True
                    report.steps.append("0x1016:1 = 0")
            except Exception as exc:
                report.steps.append(f"NMT pre-operational / 0x1016 off failed: "
                                    f"{type(exc).__name__}: {exc}")
        elif not safe:
            report.steps.append("power stage NOT confirmed off: the gateway's heartbeat stops "
                                "with the drive's supervision on, so the drive trips itself")
        return report

    def shutdown(self) -> ShutdownReport | None:
        """Bring the drive down safely (:meth:`bring_down`), stop the heartbeat and the
        notifier; returns the report (None if the bus was never connected).

        Safe to call twice and after partial start-up; does not shut the bus down.
        """
        self._stop_watchdog.set()
        self._armed = False
        if self._connected and self.identity is not None and self.shutdown_report is None:
            # a device not identified as the profile's is never written to nor reset
            self.shutdown_report = self.bring_down()
        if self._heartbeat_task is not None:
            try:
                self._heartbeat_task.stop()
            except Exception as exc:
                log.warning("stopping the heartbeat failed: %s", exc)
            self._heartbeat_task = None
        if self._connected and self.network.notifier is not None:
            self.network.notifier.stop(1.0)
            self.network.notifier = None
        self._connected = False
        return self.shutdown_report
