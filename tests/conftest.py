"""Shared pytest helpers.

The project's own pytest plugin (gateway/pytest_plugin.py: the ``drive_run`` fixture, the
``needs_vcan`` marker) is registered here, so that the tests use it whether or not the
package's entry point is installed.

``require_vcan()`` / the ``vcan_channel`` fixture: tests marked ``vcan`` need a SocketCAN
``vcan0`` (run them as ``scripts/vcan-run -- .venv/bin/pytest -m vcan``). Where there is
none they skip with the reason — except under ``CI=true``, where they fail: CI must
never skip them silently (the plugin's rule, :func:`gateway.pytest_plugin.require_vcan`).
"""

from __future__ import annotations

import pytest

pytest_plugins = ["gateway.pytest_plugin"]

VCAN_HINT = "run the vcan tests through scripts/vcan-run -- .venv/bin/pytest -m vcan"


def require_vcan(channel: str = "vcan0", need_candump: bool = False) -> str:
    """Return ``channel`` if usable; else skip (or fail when CI=true) with the reason."""
    from gateway.pytest_plugin import require_vcan as plugin_require_vcan

    return plugin_require_vcan(channel, need_candump, VCAN_HINT)


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
