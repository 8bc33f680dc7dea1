"""What the gateway must do against a CiA 301 device that is not its drive, at node 5: the
commands run against it and the assertions on the bus and on their messages, shared by
tests/test_durand.py (in-process, virtual bus), tests/test_durand_vcan.py (processes,
vcan0, candump) and tests/test_canopend.py (canopend, by hand). Frames are (time, COB-ID,
data) as :func:`twoproc_support.candump_lines` gives them."""

from __future__ import annotations

import os
from dataclasses import dataclass
from pathlib import Path

import pytest

NODE = 5
SDO_REQUEST = 0x600 + NODE
#: What node 5 itself sends (EMCY, TPDOs, SDO answers, boot-up/heartbeat): not the gateway.
NODE_SENDS = {0x080 + NODE, 0x180 + NODE, 0x280 + NODE, 0x380 + NODE, 0x480 + NODE,
              0x580 + NODE, 0x700 + NODE}
UPLOAD_REQUEST = 0x40  #: SDO initiate upload request (ccs 2), no data
#: The objects the gateway reads to identify a device, and nothing else.
IDENTITY_READS = {(0x1000, 0), (0x1018, 1), (0x1018, 2), (0x1018, 3)}
STANDARD = "gateway/drives/emulator-standard.toml"  # the shipped standard CiA 402 profile
PRE_OPERATIONAL = 127

Frame = tuple[float, int, bytes]


def require_durand() -> None:
    """Skip (with the reason) where durand is not installed; fail under CI=true (the rule of
    tests/conftest.py's require_vcan: CI never skips these silently)."""
    from durand_node import durand_missing

    why = durand_missing()
    if why is None:
        return
    if os.environ.get("CI", "").lower() == "true":
        pytest.fail(f"CI=true: {why}; CI must not skip the third-party device tests")
    pytest.skip(why)


def commands(bus: list[str], d: Path) -> dict[str, tuple[list[str], Path | None]]:
    """Each command by name: (its arguments after ``hil-gateway``, the run directory it is
    told to write, or None). ``bus``: -i, -c and --node."""
    run_args = ["--reference", "profiles/quick.toml", "--out"]
    return {
        "check": (["check", *bus, "--cycles", "10"], None),
        "check --json": (["check", *bus, "--cycles", "10", "--json",
                          str(d / "check.json")], None),
        "check --drive standard": (["check", *bus, "--drive", STANDARD, "--cycles", "10"],
                                   None),
        "run": (["run", *bus, *run_args, str(d / "run")], d / "run"),
        "run --drive standard": (["run", *bus, "--drive", STANDARD, "--drive-mode", "velocity",
                                  "--controller", "stream", *run_args, str(d / "run-std")],
                                 d / "run-std"),
    }


@dataclass
class Outcome:
    exit: int
    stdout: str
    stderr: str
    out_dir: Path | None = None
    seconds: float = 0.0


def identity(vendor: int, product: int) -> str:
    """How the gateway names a device of type 0 at node 5 with this identity."""
    return (f"node {NODE} (device type 0x00000000, vendor 0x{vendor:08X}, "
            f"product 0x{product:08X}, revision 0x00000000)")


def assert_only_identity_reads(frames: list[Frame]) -> None:
    """No SDO download to node 5, no NMT frame at all, one boot-up, the node's heartbeat
    pre-operational throughout; every frame the gateway sent is an SDO upload request to
    node 5, of 0x1000 and 0x1018 sub 1-3 exactly."""
    downloads = [f for f in frames if f[1] == SDO_REQUEST and f[2] and f[2][0] >> 5 == 1]
    assert downloads == [], downloads
    nmt = [f for f in frames if f[1] == 0x000]
    assert nmt == [], nmt  # neither to node 5 (byte 1 = 5) nor to all nodes (0)
    sent = [f for f in frames if f[1] not in NODE_SENDS]
    assert sent, "the gateway sent nothing: it did not identify the device"
    others = [f for f in sent if f[1] != SDO_REQUEST or f[2][:1] != bytes([UPLOAD_REQUEST])]
    assert others == [], others
    read = {(int.from_bytes(f[2][1:3], "little"), f[2][3]) for f in sent}
    assert read == IDENTITY_READS, sorted(read)
    # the node booted once: nothing made it boot again
    boots = [f for f in frames if f[1] == 0x700 + NODE and f[2] == b"\x00"]
    assert len(boots) == 1, boots
    # its heartbeat said pre-operational throughout: no NMT state change
    states = {f[2] for f in frames if f[1] == 0x700 + NODE and f[2] != b"\x00"}
    assert states == {bytes([PRE_OPERATIONAL])}, states


def assert_check_refused(o: Outcome, who: str) -> None:
    """`check`: exit 1 (a check failed: README), the one FAIL naming the device (``who``,
    :func:`identity`) and the fix; no traceback."""
    assert o.exit == 1, (o.stdout, o.stderr)
    assert "Traceback" not in o.stdout + o.stderr
    assert "[FAIL] the device at the node is the profile's (0x1000, 0x1018)" in o.stdout
    assert who in o.stdout, o.stdout
    assert "no standard device profile: a CiA 301 device, not a CiA 402 drive" in o.stdout
    assert "Nothing was written to it and no NMT command sent" in o.stdout, o.stdout
    assert "fix: check --node (`hil-gateway scan` lists each node" in o.stdout, o.stdout
    assert o.stdout.rstrip().endswith("result: FAIL"), o.stdout
    assert o.stdout.count("[FAIL]") == 1 and "[PASS]" not in o.stdout, o.stdout  # the one


def assert_check_json(path: Path, vendor: int) -> None:
    import json

    report = json.loads(path.read_text())
    assert report["ok"] is False and report["node"] == NODE
    assert [c["ok"] for c in report["checks"]] == [False], report["checks"]
    check = report["checks"][0]
    assert f"vendor 0x{vendor:08X}" in check["detail"], check
    assert "device type 0x00000000" in check["detail"] and "hil-gateway scan" in check["fix"]
    assert report["cycles"] == 0 and report["power_stage_enabled"] is False


def assert_run_refused(o: Outcome, who: str) -> None:
    """`run`: refused, exit 2 (README), one paragraph on stderr naming what answered
    (device type, vendor) and what to do; no traceback, nothing on stdout but the bus time
    per cycle, no run directory."""
    assert o.exit == 2, (o.stdout, o.stderr)
    assert "Traceback" not in o.stdout + o.stderr
    err = o.stderr
    assert err.startswith(f"hil-gateway: error: {who} is not the drive the profile "
                          "describes"), err
    # stdout: at most the bus-time line printed before the bus opens
    assert len(err.strip().splitlines()) == 1, err
    assert all("bus time per cycle" in line for line in o.stdout.splitlines()), o.stdout
    assert "(0x1000: no standard device profile: a CiA 301 device, not a CiA 402 drive)" in err
    assert "expected 0x00010192 (a CiA 402 frequency converter)" in err, err
    assert "Nothing was written to it and no NMT command sent" in err, err
    assert "hil-gateway scan" in err and "check --node" in err, err
    assert "give its own drive profile" not in err, err  # it is no drive: no profile fits
    assert o.out_dir is not None and not o.out_dir.exists(), sorted(o.out_dir.iterdir())


def assert_dictionary_unchanged(before: dict, after: dict) -> None:
    """Every writable entry of the node's dictionary as it was before the commands."""
    changed = {k: (v, after.get(k)) for k, v in before.items() if after.get(k) != v}
    assert changed == {} and after.keys() == before.keys(), changed


def assert_no_drive_at_the_node(o: Outcome, code: int) -> None:
    """A node in NMT STOPPED (which answers no SDO): `run` exit 2, `check` exit 1 (README:
    no drive at the node is a failed check); the message says no SDO answer, names NMT
    STOPPED as a cause and what was sent; nothing of python-canopen's own log, no
    traceback, no run directory."""
    assert o.exit == code, (o.stdout, o.stderr)
    text = o.stdout + o.stderr
    assert f"no drive at node {NODE} on the bus: no SDO answer to a read of 0x1000" in text
    assert "not in NMT STOPPED (which answers no SDO)" in text, text
    assert "Nothing but that read was sent to the node: no write, no NMT command" in text
    assert "canopen.sdo" not in text and "Traceback" not in text, text
    if o.out_dir is not None:
        assert not o.out_dir.exists()
