"""Why a run stopped, and the exit status that follows from it."""

from __future__ import annotations

from enum import StrEnum


class StopReason(StrEnum):
    """The cause of the end of a run; :attr:`exit_status` is the process's exit status."""

    END_OF_PROFILE = "end of the profile"
    INTERRUPTED = "interrupted"  #: SIGINT/SIGTERM, or stopped during start-up
    DRIVE_FAULT = "drive fault"  #: an EMCY or a lost heartbeat
    DRIVE_LOST = "drive lost"  #: cycles without the drive's TPDOs
    CONTROL_ERROR = "error in the control cycle"

    @property
    def exit_status(self) -> int:
        """0 only when the profile ran to its end; 130 when interrupted; 1 otherwise."""
        if self is StopReason.END_OF_PROFILE:
            return 0
        return 130 if self is StopReason.INTERRUPTED else 1
