"""Whether this host can run a test over SocketCAN (a ``vcan0``), and whether it runs in CI.

The one answer for the project's own vcan tests (tests/conftest.py) and for the pytest
plugin's ``needs_vcan`` marker (:mod:`gateway.pytest_plugin`): where the channel is
missing a test skips with the reason, except in CI (``CI=true``), where it fails — CI must
never skip a test silently.
"""

from __future__ import annotations

import os
import shutil
import socket


def in_ci() -> bool:
    """``CI`` is set to true (or 1), as CI systems do."""
    return os.environ.get("CI", "").lower() in ("true", "1")


def vcan_problem(channel: str = "vcan0", need_candump: bool = False) -> str | None:
    """Why ``channel`` cannot be used for SocketCAN here, or None when it can
    (``need_candump``: can-utils' candump must be installed too)."""
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
