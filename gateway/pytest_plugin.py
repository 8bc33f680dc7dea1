"""The pytest plugin of can-drive-hil: drive tests of your own, in a few lines.

Installed with the package (entry point ``pytest11``), it gives every pytest run

* the fixture ``drive_run``: ``drive_run("quick", where="sim", controller="ifoc", …)``
  runs a scenario (:func:`gateway.drivetest.run_scenario`: in this process, over the
  in-process bus, or over vcan against `hil-plant run`) with its files in the test's
  ``tmp_path`` and returns the run (signals, summary, stop reason);
* the marker ``needs_vcan`` (``@pytest.mark.needs_vcan`` or ``needs_vcan("vcan1")``): the
  test needs that SocketCAN channel; without it the test is skipped with the reason, and
  fails instead under ``CI=true`` (CI must never skip silently). ``drive_run(where="vcan")``
  applies the same rule by itself;
* the checks of :mod:`gateway.drivecheck` to import (settling, overshoot, steady-state
  error, current peak, no fault).

It imports nothing of the project until a test uses it: loading it costs every pytest run
nothing. Switch it off with ``-p no:gateway.pytest_plugin``.
"""

from __future__ import annotations

from collections.abc import Callable
from pathlib import Path
from typing import Any

import pytest

#: What to do when vcan is missing, for a user's test.
VCAN_HINT = ("create it: sudo modprobe vcan; sudo ip link add dev vcan0 type vcan; sudo ip "
             "link set up vcan0 — or run pytest inside scripts/vcan-run (README, \"Two "
             "processes over vcan\")")


def pytest_configure(config: pytest.Config) -> None:
    config.addinivalue_line(
        "markers", "needs_vcan(channel='vcan0'): the test needs a usable SocketCAN channel; "
                   "skipped with the reason without it, failed instead when CI=true")


def require_vcan(channel: str = "vcan0", need_candump: bool = False,
                 hint: str = VCAN_HINT) -> str:
    """``channel`` when it is usable; else skip the test with the reason and ``hint`` —
    or fail it when ``CI=true`` (:func:`gateway.vcan.in_ci`)."""
    from gateway.vcan import in_ci, vcan_problem

    problem = vcan_problem(channel, need_candump)
    if problem is not None:
        msg = f"{problem}; {hint}"
        if in_ci():
            pytest.fail(f"CI=true and no usable {channel}: {msg}", pytrace=False)
        pytest.skip(msg)
    return channel


def pytest_runtest_setup(item: pytest.Item) -> None:
    for mark in item.iter_markers("needs_vcan"):
        require_vcan(*mark.args, **mark.kwargs)


@pytest.fixture
def drive_run(tmp_path: Path) -> Callable[..., Any]:
    """``drive_run(profile="quick", *, where="simulate"|"sim"|"vcan", **options)`` → a
    :class:`gateway.drivetest.DriveRun`: the scenario run with its files in a new
    directory under the test's ``tmp_path`` (named in every failure message of
    :mod:`gateway.drivecheck`); ``options`` as :func:`gateway.drivetest.run_scenario`
    takes them (controller, plant, duration, drive_mode, period, …). Over vcan, a missing
    channel skips the test with the reason (fails it under CI=true)."""
    count = 0

    def run(profile: str | Path = "quick", *, where: str = "simulate", **options: Any) -> Any:
        nonlocal count
        from gateway.drivetest import Where, run_scenario

        if str(where) == Where.VCAN.value:
            require_vcan(options.get("channel", "vcan0"))
        count += 1
        return run_scenario(profile, where=where, out=tmp_path / f"run{count}-{where}",
                            **options)

    return run
