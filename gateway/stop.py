"""Why a run stopped, and the exit status that follows from it."""

from __future__ import annotations

from enum import StrEnum


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
    CONTROL_ERROR = "error in the control cycle"
    UNSAFE = "drive not confirmed safe"  #: the shutdown could not confirm the power stage off

    @property
    def exit_status(self) -> int:
        """0 only when the profile ran to its end; 130 when interrupted; 1 otherwise."""
        if self is StopReason.END_OF_PROFILE:
            return 0
        return 130 if self is StopReason.INTERRUPTED else 1
