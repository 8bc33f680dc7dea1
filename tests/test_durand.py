"""`hil-gateway check` and `run` against a third party's CiA 301 stack that CI installs:
a responder node of `durand` (PyPI; tests/durand_node.py) at node 5 on a python-can
``virtual`` channel, every frame on the channel recorded by a second Bus. It is no drive
(device type 0, durand's default; vendor 0x00000D7A, product 0x00005050), so every command
must refuse it by SDO reads alone: no SDO download to it, no NMT frame at all, only SDO
upload requests of 0x1000 and 0x1018 sub 1-3; its dictionary and NMT state unchanged, and
it still answers at the end; each command's exit status and message (what answered, what
to do); no run directory left by a refused `run`.

tests/test_canopend.py asserts the same against canopend (by hand: its binary is not
shipped); tests/test_durand_vcan.py against a durand node in a process of its own on vcan0,
recorded by candump. Without durand these tests skip, saying so, and fail under CI=true.
"""

from __future__ import annotations

import contextlib
import io
import itertools
import time
from collections.abc import Iterator
from dataclasses import dataclass
from pathlib import Path

import can
import pytest
from durand_node import HEARTBEAT_MS, PRODUCT, VENDOR
from peer_support import (
    NODE,
    NODE_SENDS,
    PRE_OPERATIONAL,
    SDO_REQUEST,
    Frame,
    Outcome,
    assert_check_json,
    assert_check_refused,
    assert_dictionary_unchanged,
    assert_no_drive_at_the_node,
    assert_only_identity_reads,
    assert_run_refused,
    commands,
    identity,
    require_durand,
)
from twoproc_support import sdo_upload

from gateway.cli import main

WHO = identity(VENDOR, PRODUCT)
_channels = itertools.count()


@dataclass
class Session:
    outcomes: dict[str, Outcome]
    frames: list[Frame]  # all on the channel, from before durand's boot-up
    before: dict
    after: dict
    nmt_state: int
    device_type_after: bytes
    vendor_after: bytes
    check_json: Path


def _gateway(args: list[str], out_dir: Path | None) -> Outcome:
    """``hil-gateway ARGS`` in this process, its stdout and stderr captured."""
    out, err = io.StringIO(), io.StringIO()
    t0 = time.monotonic()
    with contextlib.redirect_stdout(out), contextlib.redirect_stderr(err):
        code = main(args)
    return Outcome(code, out.getvalue(), err.getvalue(), out_dir, time.monotonic() - t0)


def _drain(bus: can.BusABC) -> list[Frame]:
    frames = []
    while (m := bus.recv(0)) is not None:
        frames.append((m.timestamp, m.arbitration_id, bytes(m.data)))
    return frames


@pytest.fixture(scope="module")
def session(tmp_path_factory) -> Iterator[Session]:
    require_durand()
    from durand_node import DurandNode

    ch = f"durand-{next(_channels)}-{time.monotonic_ns()}"
    d = tmp_path_factory.mktemp("durand")
    recorder = can.Bus(interface="virtual", channel=ch)  # listening before durand boots
    node = DurandNode("virtual", ch, NODE)
    try:
        before = node.snapshot()
        bus = ["-i", "virtual", "-c", ch, "--node", str(NODE)]
        outcomes = {name: _gateway(args, out_dir)
                    for name, (args, out_dir) in commands(bus, d).items()}
        time.sleep(0.1)  # durand's last answers delivered
        frames = _drain(recorder)
        after = node.snapshot()
        nmt_state = node.nmt_state()
        # python-canopen's RemoteNode, a master of its own, after all the commands
        device_type = sdo_upload(ch, NODE, 0x1000, interface="virtual")
        vendor = sdo_upload(ch, NODE, 0x1018, 1, interface="virtual")
    finally:
        node.close()
        recorder.shutdown()
    yield Session(outcomes, frames, before, after, nmt_state, device_type, vendor,
                  d / "check.json")


def test_durand_is_the_device_described(session):
    """The peer is what the module says: durand's own dictionary, device type 0, the
    identity given, its heartbeat on."""
    assert len(session.before) > 1000, len(session.before)  # 128 SDO servers, 512 PDOs...
    assert session.before["1017.00"] == HEARTBEAT_MS
    heartbeats = [f for f in session.frames if f[1] == 0x700 + NODE]
    assert heartbeats[0][2] == b"\x00" and len(heartbeats) >= 2, heartbeats  # boot-up first


def test_nothing_is_written_to_durand_and_nothing_reset(session):
    """No download, no NMT frame, one boot-up, heartbeat pre-operational throughout; the
    gateway's frames are the SDO upload requests of 0x1000 and 0x1018 sub 1-3 alone."""
    assert_only_identity_reads(session.frames)


def test_durands_dictionary_and_state_are_unchanged(session):
    """Every writable entry of durand's dictionary as before the commands; still
    pre-operational (as it booted); still answering an SDO upload, with what it said."""
    assert_dictionary_unchanged(session.before, session.after)
    assert session.nmt_state == PRE_OPERATIONAL
    assert session.device_type_after == bytes(4)
    assert session.vendor_after == VENDOR.to_bytes(4, "little")


@pytest.mark.parametrize("name", ["check", "check --json", "check --drive standard"])
def test_check_fails_and_says_what_answered(session, name):
    assert_check_refused(session.outcomes[name], WHO)


def test_check_json_is_the_failed_list(session):
    assert_check_json(session.check_json, VENDOR)


@pytest.mark.parametrize("name", ["run", "run --drive standard"])
def test_run_is_refused_with_exit_2_and_leaves_no_run_directory(session, name):
    assert_run_refused(session.outcomes[name], WHO)


def test_each_refusal_is_quick(session):
    """Refused by a handful of SDO reads: no command waits out a timeout."""
    slow = {n: round(o.seconds, 2) for n, o in session.outcomes.items() if o.seconds > 10}
    assert slow == {}, slow


# ------------------------------------------------------------------- durand in NMT STOPPED


@pytest.fixture(scope="module")
def stopped(tmp_path_factory) -> Iterator[tuple[dict[str, Outcome], list[Frame], int]]:
    """durand put in NMT STOPPED by itself (no NMT frame on the bus; in STOPPED it answers
    no SDO), then `run` and `check`: (outcomes, the frames from then on, its NMT state at the
    end). The CI-runnable form of tests/test_canopend.py's canopend in NMT STOPPED."""
    require_durand()
    from durand.services.nmt import StateEnum
    from durand_node import DurandNode

    ch = f"durand-stopped-{next(_channels)}-{time.monotonic_ns()}"
    d = tmp_path_factory.mktemp("durand-stopped")
    recorder = can.Bus(interface="virtual", channel=ch)
    node = DurandNode("virtual", ch, NODE)
    try:
        node.node.nmt.set_state(StateEnum.STOPPED)
        bus = ["-i", "virtual", "-c", ch, "--node", str(NODE)]
        cmds = commands(bus, d)
        outcomes = {name: _gateway(*cmds[name]) for name in ("run", "check")}
        time.sleep(0.1)
        frames = _drain(recorder)
        state = node.nmt_state()
    finally:
        node.close()
        recorder.shutdown()
    yield outcomes, frames, state


def test_a_stopped_durand_gets_no_nmt_and_no_write(stopped):
    """No answer: no NMT command to wake or reset it (nor to all nodes), no download; what
    the gateway sent are its SDO reads of 0x1000 and the aborts that end them unanswered
    (ccs 4). durand is still in STOPPED."""
    _, frames, state = stopped
    assert [f for f in frames if f[1] == 0x000] == []
    sent = [f for f in frames if f[1] not in NODE_SENDS]
    assert sent and all(f[1] == SDO_REQUEST for f in sent), sent
    assert {f[2][0] >> 5 for f in sent} <= {2, 4}, sent  # upload request, abort; never 1
    reads = {int.from_bytes(f[2][1:3], "little") for f in sent if f[2][0] >> 5 == 2}
    assert reads == {0x1000}, sent  # (python-canopen's abort names index 0, not 0x1000)
    boots = [f for f in frames if f[1] == 0x700 + NODE and f[2] == b"\x00"]
    assert len(boots) == 1, boots  # when it was built: nothing made it boot again
    assert state == 4  # STOPPED


@pytest.mark.parametrize("name, code", [("run", 2), ("check", 1)])
def test_a_stopped_durand_is_no_drive_at_the_node(stopped, name, code):
    """`run` exit 2, `check` exit 1: the message says no SDO answer, names NMT STOPPED as a
    cause and what was sent; nothing of python-canopen's own log, no traceback, no run
    directory."""
    outcomes, _, _ = stopped
    assert_no_drive_at_the_node(outcomes[name], code)
