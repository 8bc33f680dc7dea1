"""The CANopen master side of the gateway: bring a CiA 402 drive up, watch it, bring it down.

python-canopen does NMT, SDO, heartbeat and EMCY; the cyclic PDO exchange is done by
:mod:`gateway.loop` with the fast codec, on the same bus and the same notifier thread.

Sequence (:meth:`DriveMaster.connect` … :meth:`DriveMaster.shutdown`):

1. heartbeat/boot-up callbacks registered, then NMT *reset communication*; wait for the
   boot-up (a drive that does not answer → "no drive at node N");
2. SDO: check 0x1000 (device type) against the profile; configure in PRE-OPERATIONAL:
   cycle period 0x1006, synchronous window 0x1007, producer heartbeat 0x1017, consumer
   heartbeat 0x1016 (the gateway's own heartbeat), PDO mappings and transmission types
   (every SYNC), RPDO deadline 0x140x.5, mode of operation 0x6060, emulator objects;
3. NMT OPERATIONAL; the gateway's heartbeat producer starts;
4. CiA 402 enable sequence on 0x6040/0x6041 (shutdown → switch on → enable operation);
5. shutdown: controlword "disable voltage", NMT PRE-OPERATIONAL, heartbeat stopped.

A lost drive heartbeat or an EMCY sets :attr:`DriveMaster.fault`, which stops the loop.
"""

from __future__ import annotations

import logging
import struct
import threading
import time
from dataclasses import dataclass, field

import can
import canopen
from canopen.sdo.exceptions import SdoAbortedError, SdoCommunicationError

from dbc.cia301 import (
    EMCY_BASE,
    HEARTBEAT_BASE,
    RPDO_COMM,
    RPDO_MAP,
    TPDO_COMM,
    TPDO_MAP,
    Emcy,
    NmtCommand,
    NmtState,
    pdo_of,
)
from dbc.cia402 import (
    CONTROLWORD,
    ENABLE_SEQUENCE,
    MODES_OF_OPERATION,
    STATUSWORD,
    SW_FAULT,
    Controlword,
    State,
)
from gateway.drive_profile import DriveProfile
from gateway.errors import UserError

log = logging.getLogger(__name__)

#: The gateway's own node id for its heartbeat (0x700 + id); 0x7F is conventional for masters.
GATEWAY_NODE_ID = 0x7F


@dataclass
class FaultEvent:
    """Something that stops the loop: an EMCY or a lost heartbeat."""

    time: float
    kind: str
    code: int | None = None
    text: str = ""

    def describe(self) -> str:
        code = "" if self.code is None else f" 0x{self.code:04X}"
        return f"{self.kind}{code}: {self.text}"


@dataclass
class MasterState:
    """What the master saw of the drive."""

    faults: list[FaultEvent] = field(default_factory=list)
    last_heartbeat: float = 0.0
    nmt_state: NmtState | None = None


class DriveMaster:
    """NMT, SDO configuration, CiA 402 enable/disable and monitoring of one drive."""

    def __init__(self, bus: can.BusABC, profile: DriveProfile, node_id: int | None = None) -> None:
        self.bus = bus
        self.profile = profile
        self.node_id = node_id or profile.node
        self.network = canopen.Network(bus)
        self.network.NOTIFIER_CYCLE = 0.1
        try:
            self.node = canopen.RemoteNode(self.node_id, str(profile.eds))
        except Exception as exc:
            raise UserError(f"cannot load the EDS {str(profile.eds)!r} of drive profile "
                            f"{profile.source}: {exc}") from exc
        self.node.sdo.RESPONSE_TIMEOUT = profile.sdo_timeout_s
        self.network.add_node(self.node)
        self.state = MasterState()
        self.fault = threading.Event()
        self._booted = threading.Event()
        self._heartbeat_task: can.broadcastmanager.CyclicSendTaskABC | None = None
        self._watchdog: threading.Thread | None = None
        self._stop_watchdog = threading.Event()
        self._connected = False

    # ------------------------------------------------------------------ connection

    def connect(self, listeners: list[can.Listener] | None = None) -> None:
        """Start the notifier (with extra ``listeners``, e.g. the bus log), subscribe to
        heartbeat and EMCY, reset communication and await the boot-up."""
        self.network.connect()
        self._connected = True
        for listener in listeners or []:
            self.network.notifier.add_listener(listener)
        self.network.subscribe(HEARTBEAT_BASE + self.node_id, self._on_heartbeat)
        self.network.subscribe(EMCY_BASE + self.node_id, self._on_emcy)
        self._booted.clear()
        # reset communication (callbacks already registered)
        self.node.nmt.send_command(NmtCommand.RESET_COMMUNICATION)
        if not self._booted.wait(self.profile.boot_timeout_s):
            raise UserError(
                f"no drive at node {self.node_id} on the bus: no boot-up within "
                f"{self.profile.boot_timeout_s:g} s after an NMT reset communication. Check the "
                "node id (--node), that the drive is powered and connected, the bitrate, and "
                "for the emulator that `hil-plant run` is running on the same channel "
                "(`hil-gateway scan` lists the nodes present).")
        self.check_device_type()

    def _on_heartbeat(self, can_id: int, data: bytearray, timestamp: float) -> None:
        if not data:
            return
        state = NmtState.from_heartbeat(data[0])
        self.state.last_heartbeat = time.monotonic()
        self.state.nmt_state = state
        if state is NmtState.INITIALISING:  # the boot-up message
            self._booted.set()

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

    def check_device_type(self) -> None:
        """SDO read of 0x1000 against the profile's device type."""
        value = self.sdo_read(0x1000, 0)
        expected = self.profile.device_type
        if expected is not None and value != expected:
            raise UserError(
                f"node {self.node_id} is not the drive the profile describes: device type "
                f"0x{value:08X} (0x1000), expected 0x{expected:08X} ({self.profile.source}). "
                "Check --node, or give the right drive profile with --drive.")

    # -------------------------------------------------------------------------- SDO

    def _entry(self, index: int, sub: int):
        obj = self.node.sdo[index]
        return obj[sub] if isinstance(obj, canopen.sdo.Record | canopen.sdo.Array) else obj

    def sdo_read(self, index: int, sub: int = 0) -> int | float:
        """Read one object; failures become :class:`UserError` naming the object."""
        try:
            return self._entry(index, sub).raw
        except (SdoAbortedError, SdoCommunicationError, KeyError) as exc:
            raise UserError(f"SDO read of 0x{index:04X}.{sub} from node {self.node_id} failed: "
                            f"{exc}") from exc

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
        except (SdoAbortedError, SdoCommunicationError, KeyError) as exc:
            raise UserError(
                f"configuring node {self.node_id} failed: SDO write of {value!r} to "
                f"0x{index:04X}.{sub}{label} was refused: {exc}. Check the drive profile "
                f"({self.profile.source}) against the drive's EDS, and that the drive is in "
                "PRE-OPERATIONAL.") from exc

    def find_object(self, name: str) -> canopen.objectdictionary.ODVariable | None:
        """The EDS variable of that ParameterName (an object or a sub-index); None if the
        drive's EDS has none."""
        od = self.node.object_dictionary
        try:
            obj = od[name]
        except KeyError:
            obj = None
        if isinstance(obj, canopen.objectdictionary.ODVariable):
            return obj
        for o in od.values():
            if isinstance(o, canopen.objectdictionary.ODRecord | canopen.objectdictionary.ODArray):
                for var in o.values():
                    if var.name == name:
                        return var
        return None

    def write_by_name(self, name: str, value: int | float) -> bool:
        """Write an object found by its EDS name; False if the drive has no such object."""
        var = self.find_object(name)
        if var is None:
            return False
        self.sdo_write(var.index, var.subindex, value, name)
        return True

    # ------------------------------------------------------------------ configuration

    def configure(self, period: float, pdo_map: dict[str, list[tuple[int, int, int]]],
                  cob_ids: dict[str, int], mode: int, emulator_objects: dict[str, int | float],
                  sync_overflow: int = 0) -> None:
        """PRE-OPERATIONAL configuration by SDO (see the module docstring).

        pdo_map: for each PDO ('RPDO1', 'TPDO2', ...), the mapped (index, sub, bits).
        cob_ids: the COB-ID of each PDO. mode: 0x6060 value. emulator_objects: EDS name →
        value for the emulator's own objects (ignored on drives without them).
        """
        self.node.nmt.state = NmtState.PRE_OPERATIONAL
        p = self.profile
        for name, value in emulator_objects.items():  # f_pwm first: 0x1006 must fit it
            self.write_by_name(name, value)
        if sync_overflow and 0x1019 in self.node.object_dictionary:
            try:
                self._entry(0x1019, 0).raw = sync_overflow
            except SdoAbortedError:  # CiA 301: 0x1019 may only change while 0x1006 = 0
                self.sdo_write(0x1006, 0, 0, "cycle period 0 while 0x1019 changes")
                self.sdo_write(0x1019, 0, sync_overflow, "SYNC counter overflow value")
        self.sdo_write(0x1006, 0, round(period * 1e6), "communication cycle period, µs")
        self.sdo_write(0x1007, 0, 0, "synchronous window length, µs (0 = off)")
        self.sdo_write(0x1017, 0, p.heartbeat_ms, "producer heartbeat time, ms")
        self.sdo_write(0x1016, 1, (GATEWAY_NODE_ID << 16) | p.heartbeat_timeout_ms,
                       "consumer heartbeat of the gateway")
        for name, entries in pdo_map.items():
            self._map_pdo(name, entries, cob_ids[name])
        self.sdo_write(MODES_OF_OPERATION, 0, mode, "modes of operation")

    def _map_pdo(self, name: str, entries: list[tuple[int, int, int]], cob_id: int) -> None:
        """Write one PDO's communication and mapping parameters (CiA 301 procedure)."""
        try:
            rx, n = pdo_of(cob_id)
        except ValueError as exc:
            raise UserError(f"{name}: {exc}; check the drive profile ({self.profile.source})"
                            ) from None
        comm = (RPDO_COMM if rx else TPDO_COMM) + n - 1
        mapping = (RPDO_MAP if rx else TPDO_MAP) + n - 1
        self.sdo_write(comm, 1, cob_id | 0x80000000, f"{name} COB-ID, disabled for mapping")
        self.sdo_write(mapping, 0, 0, f"{name} mapping count 0")
        for k, (index, sub, bits) in enumerate(entries, start=1):
            self.sdo_write(mapping, k, (index << 16) | (sub << 8) | bits, f"{name} entry {k}")
        self.sdo_write(mapping, 0, len(entries), f"{name} mapping count")
        self.sdo_write(comm, 2, 1, f"{name} transmission type: synchronous, every SYNC")
        if rx:
            self.sdo_write(comm, 5, self.profile.rpdo_timeout_ms, f"{name} deadline, ms")
        self.sdo_write(comm, 1, cob_id, f"{name} COB-ID, enabled")

    # ------------------------------------------------------------------ operation

    def start(self) -> None:
        """NMT OPERATIONAL and the gateway's heartbeat producer; the watchdog starts."""
        hb_period = max(0.01, self.profile.heartbeat_timeout_ms / 3000.0)
        msg = can.Message(arbitration_id=HEARTBEAT_BASE + GATEWAY_NODE_ID,
                          data=[NmtState.OPERATIONAL.heartbeat], is_extended_id=False)
        self._heartbeat_task = self.bus.send_periodic(msg, hb_period)
        self.node.nmt.state = NmtState.OPERATIONAL
        self.state.last_heartbeat = time.monotonic()
        self._stop_watchdog.clear()
        self._watchdog = threading.Thread(target=self._watch, name="drive-watchdog",
                                          daemon=True)
        self._watchdog.start()

    def _watch(self) -> None:
        """Drive heartbeat consumer: no heartbeat within the profile's
        ``drive_heartbeat_timeout_ms`` (at least 3 producer periods) → fault."""
        limit = max(self.profile.drive_heartbeat_timeout_ms, 3 * self.profile.heartbeat_ms) / 1e3
        while not self._stop_watchdog.wait(limit / 4):
            if time.monotonic() - self.state.last_heartbeat > limit and not self.fault.is_set():
                self._raise(FaultEvent(time.monotonic(), "heartbeat", None,
                                       f"drive node {self.node_id} silent for {limit:g} s"))

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

    def disable(self) -> None:
        """Controlword 'disable voltage' (power stage off); best effort, never raises."""
        try:
            self._entry(CONTROLWORD, 0).raw = Controlword.DISABLE_VOLTAGE
        except Exception as exc:
            log.warning("disable voltage on node %d failed: %s", self.node_id, exc)

    def shutdown(self) -> None:
        """Disable voltage, NMT PRE-OPERATIONAL, stop the heartbeat and the notifier.

        Safe to call twice and after partial start-up; does not shut the bus down.
        """
        self._stop_watchdog.set()
        if self._connected:
            self.disable()
            try:
                self.node.nmt.state = NmtState.PRE_OPERATIONAL
                # the gateway's heartbeat is about to stop: the drive no longer watches it
                self._entry(0x1016, 1).raw = 0
            except Exception as exc:
                log.warning("NMT pre-operational / heartbeat consumer off failed: %s", exc)
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
