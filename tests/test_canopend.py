"""`hil-gateway check` and `run` against a third party's real CiA 301 stack: `canopend`,
CANopenNode's Linux device (CANopenLinux), at node 5 on vcan0, the bus recorded by
`candump -L`. It is no drive (device type 0, identity 0), so every command must refuse it by
SDO reads alone: no SDO download to it, no NMT command to it or to all nodes, and canopend
still running and answering at the end; each command's exit status and message (what
answered, what to do); no run directory left by a refused `run`.

canopend is not built here: the repository ships no third-party source. Give a `canopend`
binary built from CANopenLinux (its own Makefile) in the environment variable ``CANOPEND``;
without it these tests skip, saying so. A ``CANOPEND`` that does not run is a failure,
never a skip. In-process, tests/test_not_ours.py answers with canopend's identity from a
python-canopen node, so CI covers the same refusals without it.
"""

from __future__ import annotations

import contextlib
import os
import signal
from collections.abc import Iterator
from dataclasses import dataclass
from pathlib import Path

import pytest
from conftest import require_vcan
from peer_support import (
    NODE,
    NODE_SENDS,
    SDO_REQUEST,
    UPLOAD_REQUEST,
    Outcome,
    assert_check_json,
    assert_check_refused,
    assert_no_drive_at_the_node,
    assert_run_refused,
    commands,
    identity,
)
from twoproc_support import (
    PROBE_ID,
    Candump,
    Proc,
    candump,
    candump_lines,
    cansend,
    gateway_cmd,
    run,
    sdo_upload,
    wait_for,
)

pytestmark = [pytest.mark.vcan]

#: canopend's identity: device type 0, vendor, product and revision 0
WHO = identity(0, 0)


def canopend_binary() -> Path:
    """``$CANOPEND``; skipped (with the reason) when unset, a failure when it cannot run."""
    value = os.environ.get("CANOPEND", "")
    if not value:
        pytest.skip("no canopend: set CANOPEND to a canopend binary (CANopenNode's Linux "
                    "device, built from CANopenLinux) to run the tests against it")
    path = Path(value)
    if not (path.is_file() and os.access(path, os.X_OK)):
        pytest.fail(f"CANOPEND={value!r} is not an executable file: give the path of a "
                    "canopend binary built from CANopenLinux")
    return path


@dataclass
class Session:
    """What each command did, and the bus and canopend around them."""

    outcomes: dict[str, Outcome]
    frames: list[tuple[float, int, bytes]]
    canopend_alive: bool
    canopend_log: str
    device_type_after: bytes
    check_json: Path


@contextlib.contextmanager
def canopend(ch: str, d: Path, dump: Candump) -> Iterator[Proc]:
    """canopend at node 5 until its boot-up is on the bus; SIGTERM when the block ends.
    No -c: no command interface (no socket, no stdin); no -r: no reboot on NMT reset node;
    its storage files under ``d`` (-s is a path prefix)."""
    storage = d / "storage"
    storage.mkdir(exist_ok=True)
    co = Proc.start([str(canopend_binary()), ch, "-i", str(NODE), "-s", f"{storage}/"], d,
                    "canopend")
    try:
        wait_for(lambda: any(cob == 0x700 + NODE for _, cob, _ in candump_lines(dump.text())),
                 30, "canopend's boot-up", co)
        yield co
    finally:
        co.signal(signal.SIGTERM)
        co.wait(10)


def _bus(ch: str) -> list[str]:
    return ["-i", "socketcan", "-c", ch, "--node", str(NODE)]


def _gateway(ch: str, d: Path, name: str, args: list[str], out_dir: Path | None) -> Outcome:
    p = run([*gateway_cmd(), *args], d, name.replace(" ", "_"), 120)
    return Outcome(p.popen.returncode, p.stdout(), p.stderr(), out_dir)


@pytest.fixture(scope="module")
def session(tmp_path_factory) -> Iterator[Session]:
    canopend_binary()
    ch = require_vcan("vcan0", need_candump=True)
    d = tmp_path_factory.mktemp("canopend")
    with candump(ch, d) as dump, canopend(ch, d, dump) as co:
        outcomes = {name: _gateway(ch, d, name, args, out_dir)
                    for name, (args, out_dir) in commands(_bus(ch), d).items()}
        alive = co.popen.poll() is None
        device_type = sdo_upload(ch, NODE, 0x1000) if alive else b""
    yield Session(outcomes, candump_lines(dump.text()), alive, co.stderr(), device_type,
                  d / "check.json")


def _from_gateway(frames: list[tuple[float, int, bytes]]) -> list[tuple[float, int, bytes]]:
    return [f for f in frames if f[1] not in NODE_SENDS and f[1] != PROBE_ID]


def test_nothing_is_written_to_canopend_and_nothing_reset(session):
    """From candump's record: no SDO download to node 5, no NMT frame at all; every frame
    the gateway sent is an SDO upload request to node 5 (the identity reads)."""
    frames = session.frames
    downloads = [f for f in frames if f[1] == SDO_REQUEST and f[2] and f[2][0] >> 5 == 1]
    nmt = [f for f in frames if f[1] == 0x000]
    assert downloads == [], downloads
    assert nmt == [], nmt  # neither to node 5 (byte 1 = 5) nor to all nodes (0)
    sent = _from_gateway(frames)
    assert sent, "the gateway sent nothing: it did not identify the device"
    others = [f for f in sent if f[1] != SDO_REQUEST or f[2][:1] != bytes([UPLOAD_REQUEST])]
    assert others == [], others
    read = {int.from_bytes(f[2][1:3], "little") for f in sent}
    assert read == {0x1000, 0x1018}, read
    # canopend booted once: no reset of any kind made it boot again
    boots = [f for f in frames if f[1] == 0x700 + NODE and f[2] == b"\x00"]
    assert len(boots) == 1, boots


def test_canopend_is_still_running_and_answering(session):
    assert session.canopend_alive, session.canopend_log
    assert session.device_type_after == bytes(4), session.device_type_after.hex()


@pytest.mark.parametrize("name", ["check", "check --json", "check --drive standard"])
def test_check_fails_and_says_what_answered(session, name):
    """`check`: exit 1 (a check failed: README), one FAIL naming the device and the fix."""
    assert_check_refused(session.outcomes[name], WHO)


def test_check_json_is_the_failed_list(session):
    assert_check_json(session.check_json, 0)


@pytest.mark.parametrize("name", ["run", "run --drive standard"])
def test_run_is_refused_with_exit_2_and_leaves_no_run_directory(session, name):
    """`run`: refused, exit 2 (README: "the run is refused, exit 2"), one paragraph on
    stderr, no traceback, and no run directory."""
    assert_run_refused(session.outcomes[name], WHO)


# ---------------------------------------------------------------- canopend in NMT STOPPED


@pytest.fixture(scope="module")
def stopped(tmp_path_factory) -> Iterator[tuple[dict[str, Outcome], list, bool]]:
    """canopend put in NMT STOPPED by the test (which answers no SDO), then `run` and
    `check`: (outcomes, the frames from then on, canopend alive at the end)."""
    from canopen.sdo.exceptions import SdoCommunicationError

    canopend_binary()
    ch = require_vcan("vcan0", need_candump=True)
    d = tmp_path_factory.mktemp("canopend-stopped")
    cmds = commands(_bus(ch), d)
    with candump(ch, d) as dump, canopend(ch, d, dump) as co:
        cansend(ch, f"000#02{NODE:02X}")  # NMT stop, node 5

        def no_answer() -> bool:
            try:
                sdo_upload(ch, NODE, 0x1000, timeout=0.3)
            except SdoCommunicationError:
                return True
            return False

        wait_for(no_answer, 10, "canopend in NMT STOPPED (no SDO answer)", co)
        n0 = len(candump_lines(dump.text()))
        outcomes = {name: _gateway(ch, d, name, *cmds[name]) for name in ("run", "check")}
        alive = co.popen.poll() is None
    yield outcomes, candump_lines(dump.text())[n0:], alive


def test_a_stopped_canopend_gets_no_nmt_and_no_write(stopped):
    """No answer: the gateway sends no NMT command to wake or reset it (nor to all nodes)
    and no download; what it sent are its SDO reads of 0x1000 and the aborts that end them
    unanswered (ccs 4). canopend is still running."""
    _, frames, alive = stopped
    assert [f for f in frames if f[1] == 0x000] == []
    sent = _from_gateway(frames)
    assert sent and all(f[1] == SDO_REQUEST for f in sent), sent
    kinds = {f[2][0] >> 5 for f in sent}
    assert kinds <= {2, 4}, sent  # upload request, abort; never a download (1)
    assert alive


@pytest.mark.parametrize("name, code", [("run", 2), ("check", 1)])
def test_a_stopped_canopend_is_no_drive_at_the_node(stopped, name, code):
    """`run` exit 2, `check` exit 1 (README: no drive at the node is a failed check)."""
    outcomes, _, _ = stopped
    assert_no_drive_at_the_node(outcomes[name], code)
