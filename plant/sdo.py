"""The SDO server of the emulated drive: expedited and segmented access to the dictionary.

CiA 301: the SDO server answers requests on 0x600+n with responses on 0x580+n (not in
STOPPED); a refused access is an abort with a standard abort code. This emulator uses
python-canopen's ``LocalNode``/``SdoServer`` for the protocol and :class:`plant.od.ObjectStore`
for the values and the access rules. Reads of 0x6041 and of the account 0x2300 see the
present state; a successful write stores the value, keeps the mirrored objects in step
(0x6061 = 0x6060, 0x6079 = u_dc in mV) and tells the rest of the device through
:class:`SdoHooks`.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass

import can
from canopen import LocalNode

from dbc.cia301 import NmtState
from plant import od as odm


class Sender:
    """What python-canopen's SDO server needs of a network: ``send_message``."""

    def __init__(self, bus: can.BusABC) -> None:
        self._bus = bus

    def send_message(self, can_id: int, data: bytes | bytearray, remote: bool = False) -> None:
        self._bus.send(can.Message(arbitration_id=can_id, data=bytes(data),
                                   is_extended_id=False))


@dataclass(frozen=True)
class SdoHooks:
    """The device's side of SDO access: the state reads need, the effects of writes."""

    nmt_state: Callable[[], NmtState]  #: the NMT state (write rules)
    statusword: Callable[[], int]  #: 0x6041 now
    counters: Callable[[], tuple[int, int, int]]  #: cycles, SYNC gaps, faults (0x2300)
    parameters: Callable[[], None]  #: a drive model parameter was written
    controlword: Callable[[int], None]  #: 0x6040 written (applied at once)
    heartbeats: Callable[[], None]  #: 0x1016 or 0x1017 written
    sync_cob_id: Callable[[int], None]  #: 0x1005 written
    clear_error_history: Callable[[], None]  #: 0x1003 sub 0 written (with 0)
    clear_account: Callable[[], None]  #: 0x2301 written
    signal: Callable[[int], None]  #: an RPDO signal object 0x20xx written (its index)


class _LocalNode(LocalNode):
    """python-canopen's LocalNode with the device's dictionary rules for SDO access."""

    def __init__(self, server: SdoServer, store: odm.ObjectStore) -> None:
        super().__init__(store.node_id, store.od)
        self._server = server
        self.sdo._index = 0  # an abort before any request must still encode
        self.sdo._subindex = 0

    def get_data(self, index: int, subindex: int, check_readable: bool = False) -> bytes:
        return self._server.read(index, subindex)

    def set_data(self, index: int, subindex: int, data: bytes,
                 check_writable: bool = False) -> None:
        self._server.write(index, subindex, bytes(data))


class SdoServer:
    """The SDO server on the object store (see the module docstring)."""

    def __init__(self, store: odm.ObjectStore, sender: Sender, hooks: SdoHooks) -> None:
        self._store = store
        self._values = store.values
        self._hooks = hooks
        self._node = _LocalNode(self, store)
        self._node.sdo.network = sender  # type: ignore[assignment]

    def on_request(self, can_id: int, data: bytes) -> None:
        """An SDO request frame (8 bytes, the device checks the NMT state)."""
        self._node.sdo.on_request(can_id, data, 0.0)

    def read(self, index: int, subindex: int) -> bytes:
        v = self._values
        if index == 0x6041:
            v[(0x6041, 0)] = self._hooks.statusword()
        elif index == odm.ACCOUNT:
            cycles, gaps, faults = self._hooks.counters()
            v[(odm.ACCOUNT, 1)] = cycles & 0xFFFFFFFF
            v[(odm.ACCOUNT, 2)] = gaps & 0xFFFFFFFF
            v[(odm.ACCOUNT, 3)] = faults & 0xFFFFFFFF
        return self._store.read(index, subindex)

    def write(self, index: int, subindex: int, data: bytes) -> None:
        h = self._hooks
        value = self._store.check_write(index, subindex, data, h.nmt_state())
        self._values[(index, subindex)] = value
        if index in odm.PARAMETER_OBJECTS:
            h.parameters()
            if index == 0x6060:
                self._values[(0x6061, 0)] = value
            elif index == odm.DRIVE and subindex == 1:
                self._values[(0x6079, 0)] = round(value * 1000)
        if index == 0x6040:
            h.controlword(value)
        elif index in (0x1016, 0x1017):
            h.heartbeats()
        elif index == 0x1005:
            h.sync_cob_id(value)
        elif index == 0x1003:
            h.clear_error_history()
        elif index == odm.ACCOUNT_CLEAR:
            h.clear_account()
        elif 0x2000 <= index < 0x2100:
            h.signal(index)
