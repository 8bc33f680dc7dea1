"""The emulator's CiA 402 power drive state machine (pure: no I/O, no clock).

States, statusword patterns and controlword commands are the contract's
(:mod:`dbc.cia402`). This module is the device's behaviour: which command moves which
state (transition numbers of CiA 402-2) and when the power stage may apply voltage.

The emulator's fault reaction (power stage off) is immediate, so "Fault reaction active"
passes straight to "Fault" (transitions 13, 14). Quick stop switches the power stage off
at once (the motor coasts) and stays in "Quick stop active" (as with quick stop option
codes 5..8) until "disable voltage" (12) or "enable operation" (16).
"""

from __future__ import annotations

from dbc.cia402 import CW_FAULT_RESET_BIT, SW_INTERNAL_LIMIT, SW_REMOTE, Command, State

__all__ = ["PowerStateMachine", "State"]

_S = State
_C = Command


class PowerStateMachine:
    """The CiA 402 state machine; :attr:`power` says whether the power stage may apply voltage."""

    def __init__(self) -> None:
        self.state = State.NOT_READY_TO_SWITCH_ON
        self.controlword = 0

    def boot(self) -> None:
        """Transition 0 + 1: initialisation done → Switch on disabled."""
        self.state = State.SWITCH_ON_DISABLED
        self.controlword = 0

    @property
    def power(self) -> bool:
        """The power stage applies voltage (Operation enabled only)."""
        return self.state is State.OPERATION_ENABLED

    def statusword(self, limit_active: bool = False) -> int:
        """0x6041 for the present state."""
        return int(self.state) | SW_REMOTE | (SW_INTERNAL_LIMIT if limit_active else 0)

    def fault(self) -> None:
        """Transitions 13 + 14: a fault (from any state) → Fault reaction active → Fault."""
        if self.state is not State.NOT_READY_TO_SWITCH_ON:
            self.state = State.FAULT

    def command(self, cw: int) -> State:
        """Process a controlword written by SDO or received by RPDO; returns the new state."""
        cw &= 0xFFFF
        prev, self.controlword = self.controlword, cw
        s = self.state
        if s is _S.FAULT or s is _S.FAULT_REACTION_ACTIVE:
            if cw & CW_FAULT_RESET_BIT and not prev & CW_FAULT_RESET_BIT and s is _S.FAULT:
                self.state = _S.SWITCH_ON_DISABLED  # 15
            return self.state
        if s is _S.NOT_READY_TO_SWITCH_ON or cw & CW_FAULT_RESET_BIT:
            return self.state  # bit 7 set: fault reset command, not a transition here
        cmd = _C.decode(cw)
        new = s
        if cmd is _C.DISABLE_VOLTAGE:
            new = _S.SWITCH_ON_DISABLED  # 7, 9, 10, 12
        elif cmd is _C.QUICK_STOP:
            if s is _S.OPERATION_ENABLED:
                new = _S.QUICK_STOP_ACTIVE  # 11
            elif s in (_S.READY_TO_SWITCH_ON, _S.SWITCHED_ON):
                new = _S.SWITCH_ON_DISABLED  # 7, 10
        elif cmd is _C.SHUTDOWN:
            if s in (_S.SWITCH_ON_DISABLED, _S.SWITCHED_ON, _S.OPERATION_ENABLED):
                new = _S.READY_TO_SWITCH_ON  # 2, 6, 8
        elif cmd is _C.SWITCH_ON:
            if s in (_S.READY_TO_SWITCH_ON, _S.OPERATION_ENABLED):
                new = _S.SWITCHED_ON  # 3, 5
        elif cmd is _C.ENABLE_OPERATION and s in (_S.READY_TO_SWITCH_ON, _S.SWITCHED_ON,
                                                 _S.QUICK_STOP_ACTIVE):
            new = _S.OPERATION_ENABLED  # 3 + 4, 4, 16
        self.state = new
        return new
