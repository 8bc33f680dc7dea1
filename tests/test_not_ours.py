"""Never harm a device that is not ours: before any NMT command or write, the gateway reads
0x1000 and 0x1018 and refuses a device the drive profile does not describe; nothing else is
sent to it. The device here is a plain python-canopen LocalNode (a third party's stack) with
the CiA 402 device type of a frequency converter, as many real inverters report."""

from __future__ import annotations

import itertools
import threading
import time
from pathlib import Path

import can
import canopen
import pytest

from dbc import EDS_PATH
from gateway.cli import main

_channels = itertools.count()


class Device:
    """A CiA 301 node answering SDO from its dictionary, and the bus's frames, recorded."""

    def __init__(self, node: int, device_type: int, vendor: int, product: int,
                 revision: int | None = None) -> None:
        self.channel = f"not-ours-{next(_channels)}-{time.monotonic_ns()}"
        self.network = canopen.Network()
        self.network.connect(interface="virtual", channel=self.channel)
        od = canopen.import_od(str(EDS_PATH), node)
        od[0x1000].default = device_type
        od[0x1018][1].default = vendor
        od[0x1018][2].default = product
        if revision is not None:
            od[0x1018][3].default = revision
        self.node = canopen.LocalNode(node, od)
        self.network.add_node(self.node)
        self.frames: list[can.Message] = []
        self._lock = threading.Lock()
        self.network.notifier.add_listener(self._record)

    def _record(self, msg: can.Message) -> None:
        with self._lock:
            self.frames.append(msg)

    def sent_to_it(self) -> tuple[list[can.Message], list[can.Message]]:
        """The NMT commands and the SDO download requests on the bus."""
        with self._lock:
            frames = list(self.frames)
        nmt = [m for m in frames if m.arbitration_id == 0x000]
        downloads = [m for m in frames if 0x600 < m.arbitration_id < 0x680 and m.data
                     and m.data[0] >> 5 == 1]
        return nmt, downloads

    def close(self) -> None:
        self.network.disconnect()


@pytest.fixture
def device():
    made = []

    def make(**kw):
        d = Device(**kw)
        made.append(d)
        return d

    yield make
    for d in made:
        d.close()


def _run(dev: Device, tmp_path, *args: str) -> int:
    return main(["run", "-i", "virtual", "-c", dev.channel, "--reference",
                 "profiles/quick.toml", "--out", str(tmp_path / "run"), *args])


def test_a_cia402_inverter_of_another_vendor_gets_no_emulator_objects(device, tmp_path,
                                                                      capsys):
    """The emulator's profile (the default of `run`) against a frequency converter of
    another vendor: refused by its identity, no NMT, no SDO write; exit 2."""
    dev = device(node=1, device_type=0x00010192, vendor=0x000000AB, product=0x00001234)
    before = dict(dev.node.data_store)
    assert _run(dev, tmp_path) == 2
    err = capsys.readouterr().err
    assert "not the can-drive-hil emulator" in err and "0x000000AB" in err, err
    assert "Nothing was written" in err and "Traceback" not in err
    nmt, downloads = dev.sent_to_it()
    assert nmt == [] and downloads == [], (nmt, downloads)
    assert dict(dev.node.data_store) == before
    assert not (tmp_path / "run").exists() or not (tmp_path / "run" / "signals.csv").exists()


def test_another_device_type_is_refused_before_any_nmt(device, tmp_path, capsys):
    dev = device(node=1, device_type=0x00000191, vendor=0, product=0x402)
    assert _run(dev, tmp_path) == 2
    err = capsys.readouterr().err
    assert "device type 0x00000191" in err and "expected 0x00010192" in err, err
    nmt, downloads = dev.sent_to_it()
    assert nmt == [] and downloads == []


def test_a_cia301_device_without_a_device_profile_is_told_apart(device, tmp_path, capsys):
    """A device whose 0x1000 is 0 (no device profile) and whose 0x1018 is all zeros, as
    CANopenNode's Linux device `canopend` answers (tests/test_canopend.py runs the real one):
    refused, exit 2; the message names what answered, says it is no CiA 402 drive (so no
    drive profile fits it) and what to do; nothing sent but SDO reads, no run directory."""
    dev = device(node=5, device_type=0, vendor=0, product=0, revision=0)
    assert _run(dev, tmp_path, "--node", "5") == 2
    err = capsys.readouterr().err
    assert ("node 5 (device type 0x00000000, vendor 0x00000000, product 0x00000000, "
            "revision 0x00000000)") in err, err
    assert "no standard device profile: a CiA 301 device, not a CiA 402 drive" in err, err
    assert "expected 0x00010192 (a CiA 402 frequency converter)" in err, err
    assert "Nothing was written to it and no NMT command sent" in err, err
    assert "hil-gateway scan" in err and "--node" in err and "Traceback" not in err, err
    assert "give its own drive profile" not in err, err  # it is no drive: no profile fits
    nmt, downloads = dev.sent_to_it()
    assert nmt == [] and downloads == [], (nmt, downloads)
    assert not (tmp_path / "run").exists()


def test_check_of_a_cia301_device_fails_with_its_identity_in_the_json(device, tmp_path,
                                                                      capsys):
    """`check --json` against the same device: exit 1 (a check failed), one failed check
    naming what answered, with its fix, in the text and the JSON; nothing written."""
    import json

    dev = device(node=5, device_type=0, vendor=0, product=0, revision=0)
    out = tmp_path / "check.json"
    assert main(["check", "-i", "virtual", "-c", dev.channel, "--node", "5",
                 "--json", str(out)]) == 1
    text = capsys.readouterr().out
    assert "[FAIL] the device at the node is the profile's (0x1000, 0x1018)" in text, text
    assert "no standard device profile" in text and "result: FAIL" in text, text
    report = json.loads(out.read_text())
    assert report["ok"] is False and report["node"] == 5, report
    assert [c["ok"] for c in report["checks"]] == [False], report
    check = report["checks"][0]
    assert "device type 0x00000000" in check["detail"] and "hil-gateway scan" in check["fix"]
    assert report["power_stage_enabled"] is False and report["cycles"] == 0
    nmt, downloads = dev.sent_to_it()
    assert nmt == [] and downloads == [], (nmt, downloads)


def test_check_json_into_a_missing_directory_is_refused_before_the_bus(device, tmp_path,
                                                                       capsys):
    """`--json` where it cannot be written: exit 2 at once, said so, no traceback, and not a
    frame sent (it was written after the whole check, and failed with a traceback)."""
    dev = device(node=5, device_type=0, vendor=0, product=0, revision=0)
    assert main(["check", "-i", "virtual", "-c", dev.channel, "--node", "5",
                 "--json", str(tmp_path / "no-such-dir" / "check.json")]) == 2
    err = capsys.readouterr().err
    assert "--json" in err and "does not exist" in err and "Traceback" not in err, err
    time.sleep(0.2)
    with dev._lock:
        assert dev.frames == [], dev.frames


def test_an_empty_node_gets_no_nmt(device, tmp_path, capsys):
    """Nothing at node 5: said so, and no NMT command went to node 5 (nor any write)."""
    dev = device(node=1, device_type=0x00010192, vendor=0, product=0x402)
    assert _run(dev, tmp_path, "--node", "5") == 2
    err = capsys.readouterr().err
    assert "no drive at node 5" in err, err
    assert "Nothing but that read was sent to the node: no write, no NMT command" in err, err
    nmt, downloads = dev.sent_to_it()
    assert nmt == [] and downloads == []


def test_no_drive_is_said_once_on_stderr(tmp_path):
    """The command line, as a user runs it, at a node nobody answers: stderr is the one
    paragraph, not preceded by python-canopen's own ERROR log of the SDO transfer it aborts
    (tests/test_canopend.py: canopend in NMT STOPPED)."""
    import subprocess
    import sys

    p = subprocess.run([sys.executable, "-m", "gateway", "run", "-i", "virtual", "-c",
                        f"nobody-{time.monotonic_ns()}", "--node", "5", "--reference",
                        "profiles/quick.toml", "--out", str(tmp_path / "run")],
                       capture_output=True, text=True, timeout=120, stdin=subprocess.DEVNULL,
                       cwd=Path(__file__).resolve().parents[1])
    assert p.returncode == 2, p.stderr
    lines = p.stderr.strip().splitlines()
    assert len(lines) == 1 and lines[0].startswith("hil-gateway: error: no drive at node 5"), \
        p.stderr
    assert not (tmp_path / "run").exists()


def test_a_drive_that_answers_with_an_abort_is_not_reset(emulator, tmp_path, monkeypatch):
    """At the stop the drive refuses the controlword (SDO abort 0x08000022): it answers,
    so the gateway sends no NMT reset node; the run says the power stage is not confirmed
    off (the drive's own supervision of the gateway's heartbeat then trips it)."""
    from gw_support import run_in_thread, wait_cycles

    from gateway.buslog import read_log
    from gateway.spec import RunSpec
    from gateway.stop import StopSignals
    from plant import od as odm

    refuse = threading.Event()
    real = odm.ObjectStore.check_write

    def check_write(self, index, subindex, data, nmt):
        if refuse.is_set() and index == 0x6040:
            raise canopen.sdo.exceptions.SdoAbortedError(odm.ABORT_STATE)
        return real(self, index, subindex, data, nmt)

    monkeypatch.setattr(odm.ObjectStore, "check_write", check_write)
    emu = emulator()
    signals = StopSignals()
    th, result = run_in_thread(emu, tmp_path, RunSpec(duration=30.0), signals)
    wait_cycles(emu.device, 100)
    refuse.set()
    signals.requested.set()
    signals.reason = "SIGTERM received"
    signals.on_stop(signals.reason)
    th.join(15)
    assert not th.is_alive()
    s = result["summary"]
    steps = " | ".join(s["shutdown"]["steps"])
    assert "SDO abort" in steps and "NMT reset node not sent: the drive answers" in steps, steps
    assert s["shutdown"]["safe"] is False and s["run"]["exit_status"] == 1
    resets = [m for m in read_log(tmp_path / "bus.blf")
              if m.arbitration_id == 0 and bytes(m.data)[:1] == b"\x81"]
    assert resets == []


def test_a_slow_sdo_answer_is_named_as_slow_with_the_option(emulator, tmp_path, capsys,
                                                            monkeypatch):
    """The drive answers the RPDO mapping writes 1 s late (the profile waits 0.5 s): the
    message says no answer came in time and names [timing].sdo_timeout_s, not 'refused'."""
    from gw_support import gateway_run

    from plant import sdo as sdom

    real = sdom.SdoServer.on_request

    def slow(self, can_id, data):
        index = int.from_bytes(bytes(data[1:3]), "little")
        if data[0] >> 5 == 1 and 0x1600 <= index <= 0x1602:
            time.sleep(1.0)
        return real(self, can_id, data)

    monkeypatch.setattr(sdom.SdoServer, "on_request", slow)
    emu = emulator()
    assert gateway_run(emu, tmp_path / "run", "--duration", "0.1s") == 2
    err = capsys.readouterr().err
    assert "no answer within" in err and "sdo_timeout_s" in err and "refused" not in err, err
    assert "Traceback" not in err
    # a failed start leaves no run directory
    assert not (tmp_path / "run").exists(), sorted(p.name for p in (tmp_path / "run").iterdir())
