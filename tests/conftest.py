"""Shared pytest helpers.

``require_vcan()`` / the ``vcan_channel`` fixture: tests marked ``vcan`` need a SocketCAN
``vcan0`` (run them as ``scripts/vcan-run -- .venv/bin/pytest -m vcan``). Where there is
none they skip with the reason — except under ``CI=true``, where they fail: CI must
never skip them silently.
"""

from __future__ import annotations

import os
import shutil
import socket

import pytest

VCAN_HINT = "run the vcan tests through scripts/vcan-run -- .venv/bin/pytest -m vcan"


def _in_ci() -> bool:
    return os.environ.get("CI", "").lower() in ("true", "1")


def vcan_problem(channel: str = "vcan0", need_candump: bool = False) -> str | None:
    """Why ``channel`` cannot be used for SocketCAN tests here, or None when it can."""
    af_can = getattr(socket, "AF_CAN", None)
    if af_can is None:
        return "this Python has no socket.AF_CAN (not Linux?)"
    try:
        s = socket.socket(af_can, socket.SOCK_RAW, socket.CAN_RAW)
    except OSError as e:
        return f"this kernel has no SocketCAN (CAN_RAW socket: {e.strerror})"
    try:
        s.bind((channel,))
    except OSError as e:
        return f"SocketCAN interface {channel} is not usable ({e.strerror})"
    finally:
        s.close()
    try:
        with open(f"/sys/class/net/{channel}/operstate") as f:
            state = f.read().strip()
    except OSError:
        state = "unknown"
    if state not in ("up", "unknown"):
        return f"{channel} is {state}, not up"
    if need_candump and shutil.which("candump") is None:
        return "candump not found (apt-get install can-utils)"
    return None


def require_vcan(channel: str = "vcan0", need_candump: bool = False) -> str:
    """Return ``channel`` if usable; else skip (or fail when CI=true) with the reason."""
    problem = vcan_problem(channel, need_candump)
    if problem is not None:
        msg = f"{problem}; {VCAN_HINT}"
        if _in_ci():
            pytest.fail(f"CI=true and no usable {channel}: {msg}", pytrace=False)
        pytest.skip(msg)
    return channel


@pytest.fixture
def vcan_channel() -> str:
    """The SocketCAN channel name ("vcan0") for a two-process test; skips/fails per require_vcan."""
    return require_vcan("vcan0")


@pytest.fixture
def candump_channel() -> str:
    """Like ``vcan_channel``, and ``candump`` (can-utils) must be installed too."""
    return require_vcan("vcan0", need_candump=True)


@pytest.fixture
def emulator():
    """``emulator(mode="ideal", node=1)`` → a started emulated drive on a fresh virtual
    channel (tests/gw_support.py); all are stopped after the test."""
    from gw_support import emulator_factory

    yield from emulator_factory()


@pytest.fixture
def foreign(tmp_path):
    """``foreign(node, gateway_node=0x7F)`` → (drive, channel, profile path): the CiA 402
    drive of tests/foreign_drive.py started on a fresh virtual channel, its EDS, DBC and
    drive profile written into tmp_path; stopped after the test."""
    import itertools
    import time

    import can
    from foreign_drive import ForeignDrive, write_files

    drives = []
    counter = itertools.count()

    def make(node: int, gateway_node: int = 0x7F):
        channel = f"foreign-{next(counter)}-{time.monotonic_ns()}"
        bus = can.Bus(interface="virtual", channel=channel)
        profile = write_files(tmp_path, node, gateway_node)
        drive = ForeignDrive(bus, node, tmp_path / "foreign.eds")
        drive.start()
        drives.append((drive, bus))
        return drive, channel, profile

    yield make
    for drive, bus in drives:
        drive.stop()
        bus.shutdown()
