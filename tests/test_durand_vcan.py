"""`hil-gateway check` and `run` as processes against a durand node in a process of its
own (tests/durand_node.py: durand's CiA 301 responder, not ours) at node 5 on SocketCAN
vcan0, the bus recorded by `candump -L`: what tests/test_durand.py asserts in-process, from
candump's record, with the processes a user would run. durand writes its dictionary's
writable entries at the start and when told to stop (SIGTERM): they must be the same.
Run it as ``scripts/vcan-run -- .venv/bin/pytest -m vcan tests/test_durand_vcan.py``."""

from __future__ import annotations

import contextlib
import json
import signal
import sys
from collections.abc import Iterator
from dataclasses import dataclass
from pathlib import Path

import pytest
from conftest import require_vcan
from durand_node import PRODUCT, VENDOR
from peer_support import (
    NODE,
    PRE_OPERATIONAL,
    Frame,
    Outcome,
    assert_check_json,
    assert_check_refused,
    assert_dictionary_unchanged,
    assert_only_identity_reads,
    assert_run_refused,
    commands,
    identity,
    require_durand,
)
from twoproc_support import (
    PROBE_ID,
    REPO,
    Candump,
    Proc,
    candump,
    candump_lines,
    gateway_cmd,
    run,
    sdo_upload,
    wait_for,
)

pytestmark = [pytest.mark.vcan]

WHO = identity(VENDOR, PRODUCT)
END_OF_COMMANDS = 0x03  #: the probe frame's tag that ends the gateway's part of the record


@dataclass
class Session:
    outcomes: dict[str, Outcome]
    frames: list[Frame]  # from before durand's boot-up to the end of the last command
    state: dict  # durand's: {"before": ..., "after": ..., "nmt_state": ...}
    exit: int  # durand's, after SIGTERM
    device_type_after: bytes
    vendor_after: bytes
    check_json: Path


@contextlib.contextmanager
def durand_process(ch: str, d: Path, dump: Candump) -> Iterator[Proc]:
    """tests/durand_node.py at node 5 until its boot-up is on the bus; SIGTERM when the
    block ends (it then writes d/durand-state.json)."""
    p = Proc.start([sys.executable, str(REPO / "tests" / "durand_node.py"), "-i", "socketcan",
                    "-c", ch, "--node", str(NODE), "--state", str(d / "durand-state.json")],
                   d, "durand")
    try:
        wait_for(lambda: any(cob == 0x700 + NODE for _, cob, _ in candump_lines(dump.text())),
                 30, "durand's boot-up", p)
        yield p
    finally:
        if p.popen.poll() is None:
            p.signal(signal.SIGTERM)
            with contextlib.suppress(AssertionError):
                p.wait(15)
        p.kill()


@pytest.fixture(scope="module")
def session(tmp_path_factory) -> Iterator[Session]:
    require_durand()
    ch = require_vcan("vcan0", need_candump=True)
    d = tmp_path_factory.mktemp("durand-vcan")
    bus = ["-i", "socketcan", "-c", ch, "--node", str(NODE)]
    with candump(ch, d) as dump, durand_process(ch, d, dump) as node:
        outcomes = {}
        for name, (args, out_dir) in commands(bus, d).items():
            p = run([*gateway_cmd(), *args], d, name.replace(" ", "_"), 120)
            outcomes[name] = Outcome(p.popen.returncode, p.stdout(), p.stderr(), out_dir)
        dump.mark(END_OF_COMMANDS)
        assert node.popen.poll() is None, f"durand ended: {node.describe()}"
        device_type = sdo_upload(ch, NODE, 0x1000)  # python-canopen, a master of its own
        vendor = sdo_upload(ch, NODE, 0x1018, 1)
        node.signal(signal.SIGTERM)
        code = node.wait(15)
        record = candump_lines(dump.text())
    end = record.index(next(f for f in record if f[1] == PROBE_ID
                            and f[2] == bytes([END_OF_COMMANDS])))
    frames = [f for f in record[:end] if f[1] != PROBE_ID]
    state = json.loads((d / "durand-state.json").read_text())
    yield Session(outcomes, frames, state, code, device_type, vendor, d / "check.json")


def test_nothing_is_written_to_durand_and_nothing_reset(session):
    """From candump's record: no download, no NMT frame, one boot-up, its heartbeat
    pre-operational throughout; the gateway's frames are the SDO upload requests of 0x1000
    and 0x1018 sub 1-3 alone."""
    assert_only_identity_reads(session.frames)


def test_durand_is_unchanged_and_still_answering(session):
    """durand's dictionary (every writable entry) as it started, still pre-operational,
    answering SDO after all the commands, and it ended as told (exit 0 on SIGTERM)."""
    before, after = session.state["before"], session.state["after"]
    assert len(before) > 1000, len(before)
    assert_dictionary_unchanged(before, after)
    assert session.state["nmt_state"] == PRE_OPERATIONAL
    assert session.device_type_after == bytes(4)
    assert session.vendor_after == VENDOR.to_bytes(4, "little")
    assert session.exit == 0


@pytest.mark.parametrize("name", ["check", "check --json", "check --drive standard"])
def test_check_fails_and_says_what_answered(session, name):
    assert_check_refused(session.outcomes[name], WHO)


def test_check_json_is_the_failed_list(session):
    assert_check_json(session.check_json, VENDOR)


@pytest.mark.parametrize("name", ["run", "run --drive standard"])
def test_run_is_refused_with_exit_2_and_leaves_no_run_directory(session, name):
    assert_run_refused(session.outcomes[name], WHO)
