"""Why a run stopped, the exit status that follows from it, and the signals that stop it."""

from __future__ import annotations

import signal
import threading
from collections.abc import Callable, Iterator
from contextlib import contextmanager
from enum import StrEnum
from typing import Any


class StopReason(StrEnum):
    """The cause of the end of a run; :attr:`exit_status` is the process's exit status.

    Every cause but the end of the profile and an interruption is a failure (exit 1); the
    README's fault table lists how fast each is detected and what the gateway does.
    """

    END_OF_PROFILE = "end of the profile"
    INTERRUPTED = "interrupted"  #: SIGINT/SIGTERM, or stopped during start-up
    DRIVE_FAULT = "drive fault"  #: an EMCY, the statusword's fault bit, a lost heartbeat
    DRIVE_STATE = "drive state"  #: left Operation enabled, rebooted or changed NMT state
    FOREIGN_SYNC = "foreign SYNC"  #: another SYNC producer on the bus
    BAD_FRAME = "bad frame"  #: a TPDO of the wrong length, or undecodable
    IMPLAUSIBLE = "implausible measurement"  #: beyond the drive's ranges, or not finite
    DIVERGED = "diverged"  #: the loop left the envelope of the profile's demand
    DRIVE_LOST = "drive lost"  #: cycles without the drive's TPDOs (in a row, or too many)
    BUS_OFF = "bus off"  #: the gateway could not send: its controller left the bus
    BUS_ERRORS = "bus errors"  #: error frames beyond the limit
    FOREIGN_WRITER = "foreign writer"  #: another node sends on the gateway's RPDO COB-ID
    CONTROL_ERROR = "error in the control cycle"
    UNSAFE = "drive not confirmed safe"  #: the shutdown could not confirm the power stage off

    @property
    def exit_status(self) -> int:
        """0 only when the profile ran to its end; 130 when interrupted; 1 otherwise."""
        if self is StopReason.END_OF_PROFILE:
            return 0
        return 130 if self is StopReason.INTERRUPTED else 1


class StopSignals:
    """SIGINT/SIGTERM → a stop request; a second signal during shutdown is refused politely.

    The drive is brought down by the normal shutdown path; a second Ctrl-C cannot skip it
    and leave the drive enabled.
    """

    def __init__(self) -> None:
        self.requested = threading.Event()
        self.reason = ""
        self.on_stop: Callable[[str], None] | None = None
        self.shutting_down = False
        self._old: dict[int, Any] = {}

    def _handler(self, signum: int, frame: Any) -> None:
        name = signal.Signals(signum).name
        if self.requested.is_set():
            print(f"\n{name} again: shutting the drive down safely, please wait", flush=True)
            return
        self.reason = f"{name} received"
        self.requested.set()
        if self.on_stop is not None:
            self.on_stop(self.reason)
        elif not self.shutting_down:
            raise KeyboardInterrupt  # start-up: abort into the shutdown path

    def request(self, reason: str) -> None:
        """Ask the run to stop as a signal would, from any thread (a campaign's time limit
        of a point); ``reason`` says why. A second request changes nothing."""
        if self.requested.is_set():
            return
        self.reason = reason
        self.requested.set()
        if self.on_stop is not None:
            self.on_stop(reason)

    @contextmanager
    def installed(self) -> Iterator[StopSignals]:
        if threading.current_thread() is not threading.main_thread():
            yield self
            return
        for sig in (signal.SIGINT, signal.SIGTERM):
            self._old[sig] = signal.signal(sig, self._handler)
        try:
            yield self
        finally:
            for sig, old in self._old.items():
                signal.signal(sig, old)
