"""`hil-plant run --eds FILE --node 23` as a process on SocketCAN vcan0 and python-canopen's
BaseNode402 in this one as the master: the twin of tests/standard_eds.py's servo answers
with that drive's identity and runs CSV over its default PDOs. Run it where vcan0 exists,
e.g. ``scripts/vcan-run -- .venv/bin/pytest -m vcan tests/test_twin_two_process.py``."""

from __future__ import annotations

import math
import re

import pytest
from node402_support import Master402
from standard_eds import INCREMENTS, PRODUCT, REVISION, SERIAL, VENDOR, write_drive_file
from twoproc_support import plant, wait_for

pytestmark = pytest.mark.vcan

NODE = 23
VELOCITY_UNIT = 2 * math.pi / INCREMENTS


def test_a_twin_in_its_own_process_is_identified_and_driven_in_csv(vcan_channel, tmp_path):
    eds = write_drive_file(tmp_path / "servo.eds")
    with plant(vcan_channel, tmp_path, "--eds", str(eds), "--node", str(NODE)) as proc:
        wait_for(lambda: "0x6073 Max current" in proc.stdout(), 30, "the twin's listing", proc)
        m = Master402(None, NODE, eds, interface="socketcan", channel=vcan_channel)
        try:
            sdo = m.node.sdo
            assert [sdo[0x1018][k].raw for k in (1, 2, 3, 4)] == [VENDOR, PRODUCT, REVISION,
                                                                  SERIAL]
            assert sdo[0x1008].raw == "Std servo 402"
            m.configure("CYCLIC SYNCHRONOUS VELOCITY", 0x60FF, period_us=None)
            errors = []
            for k in range(1500):
                t = k * 1e-3
                w_ref = min(max(t - 0.5, 0.0), 0.5) * 100.0  # to 50 rad/s at 100 rad/s²
                sw = m.cycle(round(w_ref / VELOCITY_UNIT))
                assert sw & 0x6F == 0x27, f"left Operation enabled at {t:.3f} s: 0x{sw:04X}"
                errors.append((t, w_ref - m.value(0x606C) * VELOCITY_UNIT))
            assert max(abs(e) for t, e in errors if 0.7 <= t <= 1.0) < 1.0
            assert abs(errors[-1][1]) < 0.05
        finally:
            m.close()
    account = re.search(r"stopped; (\d+) cycles, (\d+) SYNC gaps, (\d+) faults", proc.stdout())
    assert account is not None, proc.stdout()
    assert int(account[1]) >= 1500 and account[3] == "0", account[0]


def test_a_profile_written_from_the_eds_runs_its_twin_over_vcan(vcan_channel, tmp_path):
    """The user's path to a standard drive before the hardware arrives: `profile new-drive`
    on the drive's EDS at node 23 writes a profile and DBC that load and pass `profile
    check`; against `hil-plant run --eds FILE --node 23` in its own process they pass
    `check` and `run` the quick profile in CSV, with the figures of target against actual."""
    import json

    from twoproc_support import gateway_cmd, run

    eds = write_drive_file(tmp_path / "servo.eds")
    prof = tmp_path / "servo.toml"
    for args, name in ((["profile", "new-drive", "--eds", str(eds), "--node", str(NODE), "-o",
                         str(prof)], "new-drive"), (["profile", "check", str(prof)], "pcheck")):
        p = run([*gateway_cmd(), *args], tmp_path, name, 120)
        assert p.popen.returncode == 0, p.describe()
    with plant(vcan_channel, tmp_path, "--eds", str(eds), "--node", str(NODE)) as proc:
        wait_for(lambda: "0x6073 Max current" in proc.stdout(), 30, "the twin's listing", proc)
        check = run([*gateway_cmd(), "check", "-i", "socketcan", "-c", vcan_channel, "--drive",
                     str(prof), "--json", str(tmp_path / "check.json")], tmp_path, "check",
                    300)
        assert check.popen.returncode == 0, check.describe()
        gw = run([*gateway_cmd(), "run", "-i", "socketcan", "-c", vcan_channel, "--drive",
                  str(prof), "--reference", "profiles/quick.toml", "--out",
                  str(tmp_path / "run")], tmp_path, "run", 600)
        assert gw.popen.returncode == 0, gw.describe()
    s = json.loads((tmp_path / "run" / "summary.json").read_text())
    assert s["run"]["stop"] == "END_OF_PROFILE" and s["run"]["cycles"] == 500
    assert s["configuration"]["drive_mode"] == "velocity"
    assert s["configuration"]["controller"]["name"] == "stream"
    assert s["truth"].startswith("TPDO1.velocity_actual, the drive's measured speed")
    assert s["speed_error"]["rms"] < 5.0 and abs(s["speed_error"]["final"]) < 0.5
    assert "flux_error" not in s and s["shutdown"]["safe"]
    assert (tmp_path / "run" / "fig1_references.png").is_file()
