"""CiA 402 power drive state machine (pure: no I/O, no clock).

States and statusword patterns (0x6041; bit 9 "remote" is always set, bit 4 "voltage
enabled" in the energised states, bit 11 "internal limit active" added by the caller):

=========================  ===========  ================
state                      pattern      value
=========================  ===========  ================
Not ready to switch on     x0xx 0000    0x0200
Switch on disabled         x1xx 0000    0x0240
Ready to switch on         x01x 0001    0x0231
Switched on                x01x 0011    0x0233
Operation enabled          x01x 0111    0x0237
Quick stop active          x00x 0111    0x0217
Fault reaction active      x0xx 1111    0x020F
Fault                      x0xx 1000    0x0208
=========================  ===========  ================

Controlword (0x6040) commands, bits 7, 3..0 (transition numbers of CiA 402-2):
shutdown 0xxx x110 (2, 6, 8), switch on 0xxx 0111 (3, 5), switch on + enable operation
0xxx 1111 (3 + 4, 4, 16), disable voltage 0xxx xx0x (7, 9, 10, 12), quick stop 0xxx x01x
(7, 10, 11), fault reset: rising edge of bit 7 (15).

The emulator's fault reaction (power stage off) is immediate, so "Fault reaction active"
passes straight to "Fault" (transitions 13, 14). Quick stop switches the power stage off
at once (the motor coasts) and stays in "Quick stop active" (as with quick stop option
codes 5..8) until "disable voltage" (12) or "enable operation" (16).
"""

from __future__ import annotations

from enum import IntEnum


class State(IntEnum):
    """CiA 402 states; the value is the statusword without bits 9, 11."""

    NOT_READY_TO_SWITCH_ON = 0x0000
    SWITCH_ON_DISABLED = 0x0040
    READY_TO_SWITCH_ON = 0x0031
    SWITCHED_ON = 0x0033
    OPERATION_ENABLED = 0x0037
    QUICK_STOP_ACTIVE = 0x0017
    FAULT_REACTION_ACTIVE = 0x000F
    FAULT = 0x0008


SW_REMOTE = 0x0200  #: statusword bit 9
SW_INTERNAL_LIMIT = 0x0800  #: statusword bit 11
CW_FAULT_RESET = 0x0080  #: controlword bit 7

_S = State


def _command(cw: int) -> str | None:
    """Decode the controlword command (bits 7, 3..0); None if no command pattern."""
    if cw & 0x0002 == 0:
        return "disable_voltage"
    if cw & 0x0006 == 0x0002:
        return "quick_stop"
    if cw & 0x0007 == 0x0006:
        return "shutdown"
    if cw & 0x000F == 0x0007:
        return "switch_on"
    if cw & 0x000F == 0x000F:
        return "enable_operation"
    return None


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
            if cw & CW_FAULT_RESET and not prev & CW_FAULT_RESET and s is _S.FAULT:
                self.state = _S.SWITCH_ON_DISABLED  # 15
            return self.state
        if s is _S.NOT_READY_TO_SWITCH_ON or cw & CW_FAULT_RESET:
            return self.state  # bit 7 set: fault reset command, not a transition here
        cmd = _command(cw)
        new = s
        if cmd == "disable_voltage":
            new = _S.SWITCH_ON_DISABLED  # 7, 9, 10, 12
        elif cmd == "quick_stop":
            if s is _S.OPERATION_ENABLED:
                new = _S.QUICK_STOP_ACTIVE  # 11
            elif s in (_S.READY_TO_SWITCH_ON, _S.SWITCHED_ON):
                new = _S.SWITCH_ON_DISABLED  # 7, 10
        elif cmd == "shutdown":
            if s in (_S.SWITCH_ON_DISABLED, _S.SWITCHED_ON, _S.OPERATION_ENABLED):
                new = _S.READY_TO_SWITCH_ON  # 2, 6, 8
        elif cmd == "switch_on":
            if s in (_S.READY_TO_SWITCH_ON, _S.OPERATION_ENABLED):
                new = _S.SWITCHED_ON  # 3, 5
        elif cmd == "enable_operation" and s in (_S.READY_TO_SWITCH_ON, _S.SWITCHED_ON,
                                                 _S.QUICK_STOP_ACTIVE):
            new = _S.OPERATION_ENABLED  # 3 + 4, 4, 16
        self.state = new
        return new
