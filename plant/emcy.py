"""The EMCY producer of the emulated drive (CiA 301 emergency object, CiA 402 0x603F).

CiA 301: an EMCY frame (COB-ID 0x1014, default 0x80+n; bit 31 set = no EMCY) carries the
emergency error code (2 bytes), the error register 0x1001 and 5 manufacturer-specific bytes;
it is sent in PRE-OPERATIONAL and OPERATIONAL only. 0x1003 (pre-defined error field) lists
the codes newest first; writing 0 to sub 0 clears it. This emulator: on each error the
error register gains the bits of the code's class (:attr:`dbc.cia301.Emcy.error_register`:
generic, plus current or communication), 0x603F (CiA 402 error code) holds the code,
0x1003 shifts (up to 8 entries) and the EMCY frame goes out with 5 zero bytes; clearing
the errors (fault reset) zeroes 0x1001 and 0x603F and sends EMCY 0x0000 (0x1003 keeps its
history).
"""

from __future__ import annotations

import struct
from collections.abc import Callable
from typing import Any

from dbc.cia301 import Emcy, NmtState
from plant import od as odm


class EmcyProducer:
    """Error register, 0x1003, 0x603F and the EMCY frame (see the module docstring).

    ``values`` is the object store's values, ``send(can_id, data)`` puts a frame on the bus,
    ``nmt_state()`` names the present NMT state, ``history`` is the number of entries of
    0x1003 (8; a twin's file may declare fewer, or none).
    """

    def __init__(self, values: dict[odm.Key, Any], send: Callable[[int, bytes], None],
                 nmt_state: Callable[[], NmtState], history: int = 8) -> None:
        self._values = values
        self._send = send
        self._nmt_state = nmt_state
        self._history = history
        self.error_register = 0

    def reset(self) -> None:
        """Power-on / reset node: no error (0x1001 is written by :meth:`restore`)."""
        self.error_register = 0

    def restore(self) -> None:
        """Reset communication: 0x1001 (back to its default) shows the error register again."""
        self._values[(0x1001, 0)] = self.error_register

    def error(self, code: Emcy) -> None:
        """An error occurred: error register, 0x603F, 0x1003, EMCY ``code``."""
        self.error_register |= code.error_register
        v = self._values
        v[(0x1001, 0)] = self.error_register
        v[(0x603F, 0)] = code
        n = self._history
        if n:
            for k in range(n, 1, -1):
                v[(0x1003, k)] = v[(0x1003, k - 1)]
            v[(0x1003, 1)] = code
            v[(0x1003, 0)] = min(v[(0x1003, 0)] + 1, n)
        self.send(code)

    def clear(self) -> None:
        """The errors are gone (fault reset): 0x1001 and 0x603F zero, EMCY 0x0000."""
        self.error_register = 0
        self._values[(0x1001, 0)] = 0
        self._values[(0x603F, 0)] = 0
        self.send(Emcy.NO_ERROR)

    def clear_history(self) -> None:
        """0x1003 sub 0 written (with 0): the pre-defined error field is emptied."""
        for k in range(1, self._history + 1):
            self._values[(0x1003, k)] = 0

    def send(self, code: Emcy) -> None:
        """The EMCY frame for ``code``, if the NMT state and 0x1014 allow it."""
        cob = self._values[(0x1014, 0)]
        talking = self._nmt_state() in (NmtState.PRE_OPERATIONAL, NmtState.OPERATIONAL)
        if talking and not cob & odm.COB_INVALID:
            self._send(cob & 0x7FF, struct.pack("<HB5x", code, self.error_register))
