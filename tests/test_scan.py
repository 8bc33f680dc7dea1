"""`hil-gateway scan` (gateway/scan.py) on python-can's virtual bus.

Remote nodes are python-canopen ``LocalNode``s built from ``dbc/drive.eds`` on their own
Bus object of the same virtual channel (and, when it exists, the emulated drive).
"""

from __future__ import annotations

import argparse
import threading
import time
import uuid
from collections.abc import Callable, Iterator
from pathlib import Path

import can
import canopen
import pytest

from dbc import EDS_PATH
from gateway import scan as scanmod
from gateway.drive_profile import DriveProfile, load_drive_profile
from gateway.scan import NodeInfo, format_table, scan

TIMEOUT = 0.3
SDO_TIMEOUT = 0.1

MINIMAL_EDS = """\
[FileInfo]
FileName=minimal.eds
[DeviceInfo]
VendorName=test
ProductName=minimal
[MandatoryObjects]
SupportedObjects=3
1=0x1000
2=0x1017
3=0x1018
[1000]
ParameterName=Device type
ObjectType=0x7
DataType=0x0007
AccessType=ro
DefaultValue=0x00010192
PDOMapping=0
[1017]
ParameterName=Producer heartbeat time
ObjectType=0x7
DataType=0x0006
AccessType=rw
DefaultValue=0
PDOMapping=0
[1018]
ParameterName=Identity object
ObjectType=0x9
SubNumber=5
[1018sub0]
ParameterName=Highest sub-index supported
ObjectType=0x7
DataType=0x0005
AccessType=ro
DefaultValue=4
PDOMapping=0
[1018sub1]
ParameterName=Vendor-ID
ObjectType=0x7
DataType=0x0007
AccessType=ro
DefaultValue=0x00000000
PDOMapping=0
[1018sub2]
ParameterName=Product code
ObjectType=0x7
DataType=0x0007
AccessType=ro
DefaultValue=0x00000402
PDOMapping=0
[1018sub3]
ParameterName=Revision number
ObjectType=0x7
DataType=0x0007
AccessType=ro
DefaultValue=0x00010000
PDOMapping=0
[1018sub4]
ParameterName=Serial number
ObjectType=0x7
DataType=0x0007
AccessType=ro
DefaultValue=0x00000001
PDOMapping=0
"""


@pytest.fixture(scope="module")
def eds(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """The drive's EDS, or a minimal one with the same 0x1000/0x1018 while it is missing."""
    if EDS_PATH.is_file():
        return EDS_PATH
    path = tmp_path_factory.mktemp("eds") / "minimal.eds"
    path.write_text(MINIMAL_EDS)
    return path


@pytest.fixture(scope="module")
def profile(eds: Path) -> DriveProfile:
    """The built-in emulator profile (with the EDS above)."""
    try:
        prof = load_drive_profile(None)
    except Exception:  # the built-in EDS may not exist yet
        prof = DriveProfile(name="emulator", source="<test>", eds=eds, dbc=eds)
    return prof


@pytest.fixture
def channel() -> str:
    return f"test-scan-{uuid.uuid4().hex[:8]}"


@pytest.fixture
def bus(channel: str) -> Iterator[can.BusABC]:
    """The scanner's bus."""
    b = can.Bus(interface="virtual", channel=channel)
    yield b
    b.shutdown()


@pytest.fixture
def remote(channel: str, eds: Path) -> Iterator[Callable[..., canopen.LocalNode]]:
    """Factory of LocalNodes on another Bus of the channel: (node_id, heartbeat_ms, **od)."""
    rbus = can.Bus(interface="virtual", channel=channel)
    network = canopen.Network(rbus)
    network.NOTIFIER_CYCLE = 0.1
    network.connect()
    nodes: list[canopen.LocalNode] = []

    def make(node_id: int, heartbeat_ms: int = 50, state: str = "PRE-OPERATIONAL",
             device_type: int | None = None) -> canopen.LocalNode:
        od = canopen.import_od(str(eds), node_id)
        if device_type is not None:
            od[0x1000].default = device_type
        od[0x1017].default = heartbeat_ms  # started by the boot into PRE-OPERATIONAL
        node = canopen.LocalNode(node_id, od)
        network.add_node(node)
        node.nmt.state = "PRE-OPERATIONAL"
        if state != "PRE-OPERATIONAL":
            node.nmt.state = state
        nodes.append(node)
        return node

    yield make
    for node in nodes:
        node.nmt.stop_heartbeat()
    assert network.notifier is not None
    network.notifier.stop(1.0)
    rbus.shutdown()


def by_id(infos: list[NodeInfo]) -> dict[int, NodeInfo]:
    return {i.node_id: i for i in infos}


def test_local_node_with_heartbeat(bus, remote, profile) -> None:
    remote(5, heartbeat_ms=50)
    t0 = time.monotonic()
    infos = scan(bus, TIMEOUT, profile, sdo_timeout=SDO_TIMEOUT)
    # it listens TIMEOUT, then asks each node found; a loaded host is late, not 5 s late
    assert time.monotonic() - t0 < TIMEOUT + 5.0
    assert [i.node_id for i in infos] == [5]
    n = infos[0]
    assert n.nmt_state == "PRE-OPERATIONAL"
    assert {"heartbeat", "SDO"} <= n.seen
    assert n.device_type == 0x00010192
    assert (n.vendor_id, n.product_code, n.revision, n.serial) == (0, 0x402, 0x00010000, 1)
    assert n.sdo_error == ""
    assert n.matches is True and n.mismatch == ""
    table = format_table(infos)
    assert "0x00010192 (CiA 402)" in table and "PRE-OPERATIONAL" in table
    assert table.splitlines()[1].split()[0] == "5" and table.rstrip().endswith("yes")


def test_several_nodes_states_and_mismatch(bus, remote, profile) -> None:
    remote(1, heartbeat_ms=50, state="OPERATIONAL")
    remote(2, heartbeat_ms=0)  # no heartbeat: found by the SDO search only
    remote(3, heartbeat_ms=50, device_type=0x00020191)  # another kind of device
    nodes = by_id(scan(bus, TIMEOUT, profile, sdo_timeout=SDO_TIMEOUT))
    assert sorted(nodes) == [1, 2, 3]
    assert nodes[1].nmt_state == "OPERATIONAL" and nodes[1].matches
    assert nodes[2].nmt_state is None and nodes[2].seen == {"SDO"} and nodes[2].matches
    assert nodes[3].matches is False
    assert "device type 0x00020191 ≠ 0x00010192" in nodes[3].mismatch
    assert nodes[3].profile_text().startswith("no: device type")


def test_without_profile_nothing_is_matched(bus, remote) -> None:
    remote(7)
    (n,) = scan(bus, TIMEOUT, None, sdo_timeout=SDO_TIMEOUT)
    assert n.matches is None and n.profile_text() == "-"
    assert n.device_type == 0x00010192


def test_heartbeat_only_node_and_boot_up(bus, channel, profile) -> None:
    """A master's heartbeat (no SDO server) and a boot-up during the scan are listed too."""
    other = can.Bus(interface="virtual", channel=channel)
    task = other.send_periodic(can.Message(arbitration_id=0x77F, data=b"\x05",
                                           is_extended_id=False), 0.05)
    timer = threading.Timer(0.1, lambda: other.send(
        can.Message(arbitration_id=0x70A, data=b"\x00", is_extended_id=False)))
    try:
        timer.start()
        nodes = by_id(scan(bus, TIMEOUT, profile, sdo_timeout=SDO_TIMEOUT))
    finally:
        timer.cancel()
        task.stop()
        other.shutdown()
    assert sorted(nodes) == [10, 127]
    assert nodes[127].nmt_state == "OPERATIONAL"
    assert nodes[127].device_type is None and "no SDO answer" in nodes[127].sdo_error
    assert nodes[127].matches is False and "device type unknown" in nodes[127].mismatch
    assert nodes[10].seen == {"boot-up"} and nodes[10].nmt_state == "PRE-OPERATIONAL"


def test_empty_bus(bus) -> None:
    t0 = time.monotonic()
    assert scan(bus, 0.2, None, sdo_timeout=SDO_TIMEOUT) == []
    assert 0.2 <= time.monotonic() - t0 < 5.0  # its listen time, late on a loaded host


def test_scan_sends_no_nmt(bus, channel, profile) -> None:
    """Scanning must not disturb a running system: only SDO requests to 0x601..0x67F."""
    spy = can.Bus(interface="virtual", channel=channel)
    try:
        scan(bus, 0.1, profile, sdo_timeout=SDO_TIMEOUT)
        seen = []
        while (m := spy.recv(0.05)) is not None:
            seen.append(m)
    finally:
        spy.shutdown()
    assert len(seen) == 127
    assert {m.arbitration_id for m in seen} == set(range(0x601, 0x680))
    assert all(bytes(m.data) == b"\x40\x00\x10\x00\x00\x00\x00\x00" for m in seen)


def _parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(prog="hil-gateway")
    sub = parser.add_subparsers(dest="command")
    scanmod.add_parser(sub)
    return parser


def test_cli(channel, remote, capsys: pytest.CaptureFixture[str]) -> None:
    if not EDS_PATH.is_file():
        pytest.skip("dbc/drive.eds is not there yet: the built-in profile cannot load")
    remote(1)
    args = _parser().parse_args(["scan", "--timeout", "0.3", "--sdo-timeout", "0.1",
                                 "-i", "virtual", "-c", channel])
    assert args.func(args) == 0
    out = capsys.readouterr().out
    assert "1 node(s) on virtual:" in out
    assert "0x00010192 (CiA 402)" in out and "note:" not in out


def test_cli_none_found(channel, capsys: pytest.CaptureFixture[str]) -> None:
    if not EDS_PATH.is_file():
        pytest.skip("dbc/drive.eds is not there yet: the built-in profile cannot load")
    args = _parser().parse_args(["scan", "--timeout", "0.2", "-i", "virtual", "-c", channel])
    assert args.func(args) == 1
    assert "no CANopen node on virtual:" in capsys.readouterr().err


def test_emulated_drive(bus, channel, profile) -> None:
    device_mod = pytest.importorskip("plant.device",
                                     reason="plant.device (the emulated drive) is not there yet")
    dbus = can.Bus(interface="virtual", channel=channel)
    device = device_mod.DriveDevice(dbus, node_id=4)
    try:
        device.start()
        (n,) = scan(bus, TIMEOUT, profile, sdo_timeout=SDO_TIMEOUT)
    finally:
        device.stop()
        dbus.shutdown()
    assert n.node_id == 4
    assert n.device_type == profile.device_type
    assert n.matches is True, n.mismatch
    assert n.sdo_error == ""
    assert n.nmt_state == "PRE-OPERATIONAL"
