"""`hil-gateway scan`: which CANopen nodes are on the bus, what they are.

Scanning does not disturb a running system: no NMT command is sent. The scan listens for
heartbeats, boot-ups, EMCY, TPDOs and SDO responses for ``timeout`` seconds, and sends
python-canopen's ``NodeScanner.search()`` (an SDO upload request of 0x1000 to each node
1..127, standard CiA practice) at the start. Each node found is then asked by SDO for its
device type (0x1000) and identity (0x1018 sub 1..4) with a short timeout, and compared with
the drive profile: device type equal to the profile's ``device_type`` and, where the
profile's EDS gives a non-zero default for 0x1018.1 (vendor id) or 0x1018.2 (product
code), equal to those.
"""

from __future__ import annotations

import argparse
import functools
import logging
import sys
import threading
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import can
import canopen
from canopen.sdo.exceptions import SdoAbortedError, SdoCommunicationError

from dbc.bus import add_bus_options, bus_config, open_bus
from dbc.cia301 import HEARTBEAT_BASE, NmtState
from dbc.edsfile import read_eds
from gateway.drive_profile import DriveProfile, load_drive_profile
from gateway.errors import UserError

log = logging.getLogger(__name__)

#: The identity object's sub-indices.
IDENTITY = {1: "vendor_id", 2: "product_code", 3: "revision", 4: "serial"}
#: What reveals a node: function code (COB-ID & 0x780) → source.
_SOURCES = {0x700: "heartbeat", 0x580: "SDO", 0x080: "EMCY", 0x180: "PDO", 0x280: "PDO",
            0x380: "PDO", 0x480: "PDO"}


@dataclass
class NodeInfo:
    """One node found on the bus."""

    node_id: int
    #: From the last heartbeat ('PRE-OPERATIONAL' after a boot-up); None without heartbeat.
    nmt_state: NmtState | str | None = None
    #: How the node showed itself: 'heartbeat', 'boot-up', 'SDO', 'PDO', 'EMCY'.
    seen: set[str] = field(default_factory=set)
    device_type: int | None = None
    vendor_id: int | None = None
    product_code: int | None = None
    revision: int | None = None
    serial: int | None = None
    #: SDO problem (no answer, abort), '' if all reads succeeded.
    sdo_error: str = ""
    #: Matches the drive profile (None when no profile was given).
    matches: bool | None = None
    #: Why it does not match ('' when it does).
    mismatch: str = ""

    def profile_text(self) -> str:
        """'yes', 'no: <why>' or '-'."""
        if self.matches is None:
            return "-"
        return "yes" if self.matches else f"no: {self.mismatch}"


class _Watcher(can.Listener):
    """Heartbeats/boot-ups (NMT state) and other node-revealing frames, per node id."""

    def __init__(self) -> None:
        self.lock = threading.Lock()
        self.state: dict[int, int] = {}
        self.seen: dict[int, set[str]] = {}

    def on_message_received(self, msg: can.Message) -> None:
        if msg.is_extended_id or msg.is_error_frame or msg.is_remote_frame:
            return
        func, node = msg.arbitration_id & 0x780, msg.arbitration_id & 0x7F
        source = _SOURCES.get(func)
        if node == 0 or source is None:
            return
        with self.lock:
            if func == HEARTBEAT_BASE:
                if msg.dlc < 1:
                    return
                code = msg.data[0] & 0x7F
                if code == NmtState.INITIALISING.heartbeat:
                    source = "boot-up"
                    # after the boot-up a node is PRE-OPERATIONAL (CiA 301)
                    code = NmtState.PRE_OPERATIONAL.heartbeat
                self.state[node] = code
            self.seen.setdefault(node, set()).add(source)


@functools.cache
def _eds_identity(eds: Path) -> tuple[int | None, int | None]:
    """(vendor id, product code) defaults of 0x1018 in an EDS; None where absent or zero."""
    try:
        od = read_eds(eds).od
    except UserError as exc:
        raise UserError(f"{exc}; fix the file or the drive profile's [drive].eds") from None
    out: list[int | None] = []
    for sub in (1, 2):
        try:
            value = od[0x1018][sub].default
        except (KeyError, TypeError):
            value = None
        out.append(int(value) if value else None)
    return out[0], out[1]


def _expectations(profile: DriveProfile) -> dict[str, int]:
    exp: dict[str, int] = {}
    if profile.device_type is not None:
        exp["device_type"] = profile.device_type
    vendor, product = _eds_identity(profile.eds)
    if vendor is not None:
        exp["vendor_id"] = vendor
    if product is not None:
        exp["product_code"] = product
    return exp


def _match(info: NodeInfo, expected: dict[str, int]) -> None:
    why = []
    for key, want in expected.items():
        got = getattr(info, key)
        if got is None:
            why.append(f"{key.replace('_', ' ')} unknown")
        elif got != want:
            why.append(f"{key.replace('_', ' ')} 0x{got:08X} ≠ 0x{want:08X}")
    info.matches = not why
    info.mismatch = ", ".join(why)


def _search(network: canopen.Network, limit: int = 127) -> None:
    """python-canopen's SDO search; paced retry when the TX queue is full (ENOBUFS)."""
    try:
        network.scanner.search(limit)
        return
    except can.CanError as exc:
        log.debug("fast SDO search failed (%s); sending paced", exc)
    request = b"\x40\x00\x10\x00\x00\x00\x00\x00"
    for node_id in range(1, limit + 1):
        for _ in range(20):
            try:
                network.send_message(0x600 + node_id, request)
                break
            except can.CanError:
                time.sleep(0.005)


def _u32(data: bytes) -> int:
    return int.from_bytes(bytes(data[:4]), "little")


def _read_sdo(network: canopen.Network, info: NodeInfo, sdo_timeout: float) -> None:
    node = canopen.RemoteNode(info.node_id, canopen.ObjectDictionary())
    network.add_node(node)
    node.sdo.RESPONSE_TIMEOUT = sdo_timeout
    node.sdo.MAX_RETRIES = 1
    try:
        info.device_type = _u32(node.sdo.upload(0x1000, 0))
    except SdoCommunicationError as exc:
        info.sdo_error = f"no SDO answer ({exc})"
        return  # no SDO server: no point in asking for the identity
    except SdoAbortedError as exc:
        info.sdo_error = f"0x1000: {exc}"
    errors = []
    for sub, name in IDENTITY.items():
        try:
            setattr(info, name, _u32(node.sdo.upload(0x1018, sub)))
        except (SdoAbortedError, SdoCommunicationError) as exc:
            errors.append(f"0x1018.{sub}: {exc}")
    info.sdo_error = "; ".join(([info.sdo_error] if info.sdo_error else []) + errors)


def scan(bus: can.BusABC, timeout: float = 1.0, profile: DriveProfile | None = None, *,
         sdo_timeout: float = 0.2, search: bool = True) -> list[NodeInfo]:
    """The CANopen nodes on ``bus``, by node id.

    Listens ``timeout`` seconds (after sending the SDO search unless ``search=False``),
    then reads 0x1000 and 0x1018.1..4 of every node found, ``sdo_timeout`` per request.
    Sends no NMT command. The caller owns the bus; it must have no other
    :class:`can.Notifier` while this runs.
    """
    expected = _expectations(profile) if profile is not None else None
    network = canopen.Network(bus)
    network.NOTIFIER_CYCLE = 0.1
    watcher = _Watcher()
    network.listeners.append(watcher)
    network.connect()
    try:
        if search:
            _search(network)
        time.sleep(timeout)
        with watcher.lock:
            ids = set(watcher.seen) | {n for n in network.scanner.nodes if 1 <= n <= 127}
        infos = []
        for node_id in sorted(ids):
            info = NodeInfo(node_id)
            _read_sdo(network, info, sdo_timeout)
            with watcher.lock:
                code = watcher.state.get(node_id)
                info.seen = set(watcher.seen.get(node_id, ()))
            if node_id in network.scanner.nodes and not info.seen:
                info.seen.add("SDO")
            info.nmt_state = None if code is None else (NmtState.from_heartbeat(code)
                                                        or f"0x{code:02X}")
            if expected is not None:
                _match(info, expected)
            infos.append(info)
        return infos
    finally:
        if network.notifier is not None:
            network.notifier.stop(1.0)
            network.notifier = None


# ------------------------------------------------------------------------------- CLI


def _hex(value: int | None) -> str:
    return "-" if value is None else f"0x{value:08X}"


def _device_type(value: int | None) -> str:
    if value is None:
        return "-"
    profile = value & 0xFFFF
    return f"0x{value:08X}" + (f" (CiA {profile})" if profile else "")


def format_table(infos: list[NodeInfo]) -> str:
    """The scan result as a text table, one node per line."""
    head = ("node", "NMT state", "device type", "vendor id", "product", "revision", "serial",
            "profile")
    rows = [head]
    for i in infos:
        rows.append((str(i.node_id), i.nmt_state or "-", _device_type(i.device_type),
                     _hex(i.vendor_id), _hex(i.product_code), _hex(i.revision), _hex(i.serial),
                     i.profile_text()))
    widths = [max(len(r[k]) for r in rows) for k in range(len(head) - 1)]
    lines = ["  ".join(c.ljust(w) for c, w in zip(r[:-1], widths, strict=True)) + "  " + r[-1]
             for r in rows]
    return "\n".join(line.rstrip() for line in lines)


def cmd_scan(args: argparse.Namespace) -> int:
    """`hil-gateway scan`: print the nodes found; 0 if any, 1 if none."""
    from gateway.units import format_duration, parse_duration

    timeout = parse_duration(args.timeout, "--timeout")
    sdo_timeout = parse_duration(args.sdo_timeout, "--sdo-timeout")
    profile = load_drive_profile(args.drive)
    cfg = bus_config(args)
    bus = open_bus(cfg, receive_own_messages=False)
    try:
        infos = scan(bus, timeout, profile, sdo_timeout=sdo_timeout)
    finally:
        bus.shutdown()
    if not infos:
        print(f"no CANopen node on {cfg.label()} within {format_duration(timeout)}: no heartbeat "
              "and no answer to the SDO search. Check the channel, the bitrate (-b), wiring and "
              "termination, that the nodes are powered, or scan longer with --timeout.",
              file=sys.stderr)
        return 1
    print(f"{len(infos)} node(s) on {cfg.label()}; drive profile: {profile.name} "
          f"({profile.source}, node {profile.node})")
    print(format_table(infos))
    for i in infos:
        if i.sdo_error:
            print(f"node {i.node_id}: {i.sdo_error}")
    if not any(i.node_id == profile.node and i.matches for i in infos):
        others = [i.node_id for i in infos if i.matches]
        hint = (f"; a matching node is at {', '.join(map(str, others))} (use --node)" if others
                else "")
        print(f"note: no node matching the profile at node {profile.node}{hint}")
    return 0


def add_parser(sub: Any) -> None:
    """Register `scan` on the subcommand parsers of `hil-gateway`."""
    p = sub.add_parser(
        "scan", help="list the CANopen nodes on the bus (listen only, SDO reads)",
        description="List the CANopen nodes present without disturbing a running system: "
                    "listen for heartbeats and boot-ups, send the standard SDO search (read "
                    "0x1000 on nodes 1..127; no NMT command), then read each node's device "
                    "type (0x1000) and identity (0x1018) and compare them with the drive "
                    "profile. Exit status 0 if a node was found, 1 if none.")
    p.add_argument("--timeout", default="1", metavar="S",
                   help="how long to listen for heartbeats and SDO answers (default 1 s)")
    p.add_argument("--sdo-timeout", default="0.2", metavar="S",
                   help="timeout of each SDO read (default 0.2 s)")
    p.add_argument("--drive", metavar="PROFILE",
                   help="drive profile (TOML) to compare with; default: the built-in emulator")
    add_bus_options(p)
    p.set_defaults(func=cmd_scan)

