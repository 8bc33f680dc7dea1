"""Each shipped bus-fault scenario between two processes over SocketCAN: `hil-plant run` on
vcan1, `hil-gateway bridge` forwarding between vcan0 and vcan1 with the faults, and
`hil-gateway run` on vcan0 — neither side modified. Run through scripts/vcan-run."""

from __future__ import annotations

import json
import signal

import pytest
from conftest import require_vcan
from twoproc_support import Proc, gateway_cmd, plant, run, wait_for

pytestmark = pytest.mark.vcan

#: scenario → (run.stop, exit status, what else the summary shows). Over a bridge the
#: gateway's own sends always succeed: a bus-off cuts the drive's segment off for its 0.1 s,
#: so the cycle in flight is lost and the next SYNC (the lockstep backstop's) finds the bus
#: back; the drive's heartbeat-stop is watched in lockstep by its TPDOs.
CASES = {
    "bus-drop": ("END_OF_PROFILE", 0, lambda s: s["run"]["missed_cycles"] == 1),
    "bus-delay": ("END_OF_PROFILE", 0, lambda s: s["run"]["missed_cycles"] >= 1),
    "bus-duplicate": ("END_OF_PROFILE", 0,
                      lambda s: s["run"]["tpdo_events"].get("TPDO2 duplicate", 0) >= 5),
    "bus-reorder": ("END_OF_PROFILE", 0, lambda s: s["run"]["missed_cycles"] == 0),
    "bus-corrupt": ("END_OF_PROFILE", 0, lambda s: s["run"]["missed_cycles"] == 0),
    "bus-dlc": ("BAD_FRAME", 1, lambda s: "expected 7" in s["run"]["stop_reason"]),
    "bus-sync-late": ("END_OF_PROFILE", 0, lambda s: s["run"]["missed_cycles"] == 0),
    "bus-sync-jitter": ("END_OF_PROFILE", 0, lambda s: s["run"]["missed_cycles"] == 0),
    "bus-sync-missing": ("END_OF_PROFILE", 0, lambda s: s["run"]["missed_cycles"] == 1),
    "bus-off": ("END_OF_PROFILE", 0, lambda s: s["run"]["missed_cycles"] >= 1),
    "bus-babble": ("FOREIGN_WRITER", 1, lambda s: "0x301" in s["run"]["stop_reason"]),
    "bus-heartbeat-stop": ("END_OF_PROFILE", 0, lambda s: True),
    "bus-second-master": ("FOREIGN_SYNC", 1, lambda s: True),
}


def _vcan_pair() -> tuple[str, str]:
    return require_vcan("vcan0"), require_vcan("vcan1")


@pytest.mark.parametrize("scenario", sorted(CASES))
def test_each_fault_between_two_processes(tmp_path, scenario):
    gw_ch, drive_ch = _vcan_pair()
    stop, exit_status, check = CASES[scenario]
    with plant(drive_ch, tmp_path, name="plant"):
        bridge = Proc.start([*gateway_cmd(), "bridge", "--plant", scenario, "-i", "socketcan",
                             "-c", gw_ch, "--to", drive_ch, "--json",
                             str(tmp_path / "bridge.json")], tmp_path, "bridge")
        try:
            wait_for(lambda: "bridge:" in bridge.stdout(), 60, "the bridge's ready line",
                     bridge)
            gw = run([*gateway_cmd(), "run", "-i", "socketcan", "-c", gw_ch, "--reference",
                      "profiles/quick.toml", "--out", str(tmp_path / "run")], tmp_path,
                     "gateway", 600)
        finally:
            bridge.signal(signal.SIGTERM)
            bridge.wait(30)
    s = json.loads((tmp_path / "run" / "summary.json").read_text())
    assert gw.popen.returncode == exit_status, gw.describe()
    assert s["run"]["stop"] == stop, s["run"]["stop_reason"]
    assert check(s), s["run"]
    assert s["shutdown"]["safe"], s["shutdown"]
    account = json.loads((tmp_path / "bridge.json").read_text())
    assert account["bus_faults"][0]["acted"] >= 1, account


def test_error_frames_are_refused_where_the_interface_cannot_carry_them(tmp_path):
    """vcan does not deliver error frames a process sends (only a CAN controller makes
    them): the bridge refuses the error-frames scenario by name, exit 2, before forwarding
    anything (in one process, `sim`, they are injected: tests/test_bus_faults.py)."""
    gw_ch, drive_ch = _vcan_pair()
    bridge = run([*gateway_cmd(), "bridge", "--plant", "bus-error-frames", "-i", "socketcan",
                  "-c", gw_ch, "--to", drive_ch], tmp_path, "bridge", 60)
    assert bridge.popen.returncode == 2, bridge.describe()
    err = bridge.stderr()
    assert "does not deliver error frames" in err and "hil-gateway sim" in err
    assert "Traceback" not in err
