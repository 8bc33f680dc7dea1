"""`hil-gateway check`: commissioning without power (gateway/check.py)."""

from __future__ import annotations

import itertools
import json
import threading
import time

import pytest

from dbc.cia402 import State
from gateway.cli import main

_channels = itertools.count()


class _StateWatch:
    """Polls the emulator's CiA 402 state while the check runs."""

    def __init__(self, device) -> None:
        self.device, self.states = device, set()
        self._stop = threading.Event()
        self._t = threading.Thread(target=self._run, daemon=True)
        self._t.start()

    def _run(self) -> None:
        while not self._stop.is_set():
            self.states.add(self.device.cia402_state)
            self.states.add("enabled" if self.device.drive.enabled else "off")
            time.sleep(0.0005)

    def stop(self) -> set:
        self._stop.set()
        self._t.join()
        return self.states


def test_the_emulator_passes_without_power(emulator, tmp_path, capsys):
    emu = emulator("current-loop")
    watch = _StateWatch(emu.device)
    rc = main(["check", "-i", "virtual", "-c", emu.channel, "--cycles", "200",
               "--json", str(tmp_path / "check.json")])
    states = watch.stop()
    out = capsys.readouterr().out
    assert rc == 0, out
    assert State.OPERATION_ENABLED not in states and "enabled" not in states
    report = json.loads((tmp_path / "check.json").read_text())
    assert report["ok"] and all(c["ok"] for c in report["checks"]), out
    assert not report["power_stage_enabled"]
    assert report["cycles"] == 200 and report["complete_cycles"] >= 160  # a run tolerates it
    assert set(report["latency"]) >= {"TPDO1", "TPDO2"}
    for lat in report["latency"].values():
        assert lat["received"] >= 160 and 0 < lat["median_us"] <= lat["p99_us"]
    assert "PASS" in out and "median" in out
    assert emu.device.nmt_state != "OPERATIONAL"


@pytest.mark.parametrize("node, gateway_node", [(42, 0x7F), (127, 100)])
def test_the_foreign_drive_passes_with_its_profile(foreign, tmp_path, capsys, node,
                                                   gateway_node):
    drive, channel, profile = foreign(node, gateway_node)
    rc = main(["check", "-i", "virtual", "-c", channel, "--drive", str(profile),
               "--cycles", "100", "--json", str(tmp_path / "c.json")])
    out = capsys.readouterr().out
    assert rc == 0, out
    report = json.loads((tmp_path / "c.json").read_text())
    assert report["node"] == node and report["cycles"] == 100
    assert set(report["latency"]) == {"TX1", "TX2", "TX3"}
    assert report["complete_cycles"] >= 80
    assert drive.cycles >= 100 and drive.state != 0x0237
    assert drive.nmt == "PRE-OPERATIONAL"
    # the object checks name the drive's own objects
    assert "0x3100.0 'Phase current A'" in out


def test_a_signal_size_not_the_drives_fails_naming_it(foreign, tmp_path, capsys):
    drive, channel, profile = foreign(42)
    dbc = tmp_path / "foreign.dbc"
    # Udc as 32 bits in the DBC: the drive maps 16
    text = dbc.read_text().replace("BO_ 682 TX2: 6 DRIVE", "BO_ 682 TX2: 8 DRIVE").replace(
        "SG_ Udc : 32|16@1+", "SG_ Udc : 32|32@1+")
    dbc.write_text(text)
    rc = main(["check", "-i", "virtual", "-c", channel, "--drive", str(profile),
               "--cycles", "20"])
    out = capsys.readouterr().out
    assert rc == 1
    assert "[FAIL] object of TX2.Udc" in out and "16 bits, the DBC signal 32" in out
    assert "[FAIL] mapping of TX2" in out and "[16, 16, 16]" in out and "fix:" in out
    assert drive.cycles == 0  # not configured, no SYNC


def test_a_cob_id_not_the_drives_fails_naming_it(foreign, tmp_path, capsys):
    _, channel, profile = foreign(42)
    dbc = tmp_path / "foreign.dbc"
    dbc.write_text(dbc.read_text().replace("BO_ 682 TX2:", "BO_ 683 TX2:"))  # 0x2AB
    rc = main(["check", "-i", "virtual", "-c", channel, "--drive", str(profile),
               "--cycles", "20"])
    out = capsys.readouterr().out
    assert rc == 1 and "mapping of TX2" in out and "COB-ID 0x2AA, the DBC says 0x2AB" in out


def test_a_missing_role_fails_naming_it(foreign, tmp_path, capsys):
    _, channel, profile = foreign(42)
    profile.write_text(profile.read_text().replace('u_sa = "TX2.Ualpha"\n', ""))
    rc = main(["check", "-i", "virtual", "-c", channel, "--drive", str(profile),
               "--cycles", "20"])
    out = capsys.readouterr().out
    assert rc == 1
    assert "[FAIL] roles of the current-fed law" in out and "u_sa" in out
    assert "fix: map the missing roles" in out


def test_no_drive_at_the_node_is_a_failed_check(foreign, capsys):
    _, channel, profile = foreign(42)
    rc = main(["check", "-i", "virtual", "-c", channel, "--drive", str(profile),
               "--node", "43"])
    out = capsys.readouterr().out
    assert rc == 1 and "no drive at node 43" in out, out
    assert "[FAIL] the device at the node is the profile's" in out  # before any NMT


def test_bad_input_exits_2(tmp_path, capsys):
    rc = main(["check", "-i", "virtual", "-c", "x", "--drive", str(tmp_path / "none.toml")])
    err = capsys.readouterr().err
    assert rc == 2 and "cannot read the drive profile" in err and "Traceback" not in err
