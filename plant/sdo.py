"""The SDO server of the emulated drive: expedited and segmented access to the dictionary.

CiA 301: the SDO server answers requests on 0x600+n with responses on 0x580+n (not in
STOPPED); a refused access is an abort with a standard abort code. This emulator uses
python-canopen's ``LocalNode``/``SdoServer`` for the protocol and :class:`plant.od.ObjectStore`
for the values and the access rules. Reads of 0x6041 and of the account 0x2300 see the
present state; a successful write stores the value, keeps the mirrored objects in step
(0x6061 = 0x6060, 0x6079 = u_dc in mV) and tells the rest of the device through
:class:`SdoHooks` (the emulator's own objects 0x2xxx only in its own dictionary).

Before a request reaches python-canopen's server, this module enforces what that server
does not: block transfers (initiate upload ccs 5, download ccs 6) are aborted
with 0x05040001 (this server offers none; python-canopen would answer a block upload with
a plain upload); a segmented download is bounded by the size its initiate declared, or
without one by the object's size (a numeric object's length, else
:data:`MAX_SEGMENTED`), and aborted with 0x06070012 at the initiate (declared size beyond
a numeric object's) or at the first segment beyond the bound, so a download that never
ends cannot grow a buffer; a download or upload segment with no such transfer under way is
aborted with 0x05040001. An exception other than an abort in the device's read/write
hooks is answered with the general abort 0x08000000 and then re-raised to the device (an
internal error), not swallowed by python-canopen.
"""

from __future__ import annotations

import struct
from collections.abc import Callable
from dataclasses import dataclass

import can
from canopen import LocalNode
from canopen.objectdictionary import datatypes
from canopen.sdo import SdoAbortedError

from dbc.cia301 import NmtState
from plant import od as odm

ABORT_COMMAND = 0x05040001  #: client/server command specifier not valid or unknown
ABORT_TOO_LONG = 0x06070012  #: data type does not match, length of service parameter too high
ABORT_GENERAL = 0x08000000  #: general error
#: Bound of a segmented download without a declared size to a non-numeric object, bytes.
MAX_SEGMENTED = 1024
_CCS_DOWNLOAD_SEGMENT, _CCS_DOWNLOAD, _CCS_UPLOAD, _CCS_UPLOAD_SEGMENT, _CCS_ABORT = 0, 1, 2, 3, 4
_CCS_BLOCK = (5, 6)  #: block upload, block download


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
        try:
            return self._server.read(index, subindex)
        except SdoAbortedError:
            raise
        except Exception as exc:  # a bug: answered with an abort, then raised to the device
            self._server.failure = exc
            raise SdoAbortedError(ABORT_GENERAL) from exc

    def set_data(self, index: int, subindex: int, data: bytes,
                 check_writable: bool = False) -> None:
        try:
            self._server.write(index, subindex, bytes(data))
        except SdoAbortedError:
            raise
        except Exception as exc:
            self._server.failure = exc
            raise SdoAbortedError(ABORT_GENERAL) from exc


class SdoServer:
    """The SDO server on the object store (see the module docstring)."""

    def __init__(self, store: odm.ObjectStore, sender: Sender, hooks: SdoHooks) -> None:
        self._store = store
        self._values = store.values
        self._hooks = hooks
        self._node = _LocalNode(self, store)
        self._node.sdo.network = sender  # type: ignore[assignment]
        #: the segmented download under way: [bound in bytes, bytes received], or None
        self._download: list[int] | None = None
        self._upload = False  #: a segmented upload under way
        #: an exception a hook raised during the present request (re-raised after it)
        self.failure: Exception | None = None

    def on_request(self, can_id: int, data: bytes) -> None:
        """An SDO request frame (8 bytes, the device checks the NMT state). Raises what a
        read/write hook raised (other than an SDO abort), after the abort went out."""
        if self._refused(data):
            return
        sdo = self._node.sdo
        ccs = data[0] >> 5
        if ccs == _CCS_UPLOAD:
            sdo._buffer = None
        self._node.sdo.on_request(can_id, data, 0.0)
        if ccs != _CCS_UPLOAD_SEGMENT:
            self._upload = ccs == _CCS_UPLOAD and sdo._buffer is not None
        if self.failure is not None:
            exc, self.failure = self.failure, None
            raise exc

    def _abort(self, data: bytes, code: int) -> None:
        """Abort the transfer of the request ``data`` with ``code`` (its index/subindex,
        or the download's under way for a segment)."""
        sdo = self._node.sdo
        if data[0] >> 5 not in (_CCS_DOWNLOAD_SEGMENT, _CCS_UPLOAD_SEGMENT):
            sdo._index, sdo._subindex = struct.unpack_from("<HB", data, 1)
        sdo._buffer = None
        self._download = None
        self._upload = False
        sdo.abort(code)

    def _refused(self, data: bytes) -> bool:
        """Block transfers and unbounded segmented downloads, aborted here (True)."""
        ccs = data[0] >> 5
        if ccs in _CCS_BLOCK:
            self._abort(data, ABORT_COMMAND)
            return True
        if ccs == _CCS_DOWNLOAD:
            self._download = None
            if data[0] & 0x02:  # expedited
                return False
            index, subindex = struct.unpack_from("<HB", data, 1)
            try:
                var = self._store.var(index, subindex)
            except SdoAbortedError as exc:
                self._abort(data, exc.code)
                return True
            numeric = var.data_type in datatypes.NUMBER_TYPES
            bound = len(var) // 8 if numeric else MAX_SEGMENTED
            if data[0] & 0x01:  # size indicated
                declared = struct.unpack_from("<L", data, 4)[0]
                if declared > bound:
                    self._abort(data, ABORT_TOO_LONG)
                    return True
                bound = declared
            self._download = [bound, 0]
        elif ccs == _CCS_DOWNLOAD_SEGMENT:
            d = self._download
            if d is None:
                self._abort(data, ABORT_COMMAND)
                return True
            n = 7 - ((data[0] >> 1) & 0x7)
            if d[1] + n > d[0]:
                self._abort(data, ABORT_TOO_LONG)
                return True
            d[1] += n
            if data[0] & 0x01:  # last segment
                self._download = None
        elif ccs == _CCS_UPLOAD_SEGMENT:
            if not self._upload:
                self._abort(data, ABORT_COMMAND)
                return True
        elif ccs in (_CCS_UPLOAD, _CCS_ABORT):
            self._download = None
        return False

    def read(self, index: int, subindex: int) -> bytes:
        v = self._values
        if index == 0x6041:
            v[(0x6041, 0)] = self._hooks.statusword()
        elif index == odm.ACCOUNT and self._store.own:
            cycles, gaps, faults = self._hooks.counters()
            v[(odm.ACCOUNT, 1)] = cycles & 0xFFFFFFFF
            v[(odm.ACCOUNT, 2)] = gaps & 0xFFFFFFFF
            v[(odm.ACCOUNT, 3)] = faults & 0xFFFFFFFF
        return self._store.read(index, subindex)

    def write(self, index: int, subindex: int, data: bytes) -> None:
        h, own = self._hooks, self._store.own
        value = self._store.check_write(index, subindex, data, h.nmt_state())
        self._values[(index, subindex)] = value
        if index in self._store.parameters:
            h.parameters()
            if index == 0x6060:
                self._values[(0x6061, 0)] = value
            elif own and index == odm.DRIVE and subindex == 1:
                self._values[(0x6079, 0)] = round(value * 1000)
        if index == 0x6040:
            h.controlword(value)
        elif index in (0x1016, 0x1017):
            h.heartbeats()
        elif index == 0x1005:
            h.sync_cob_id(value)
        elif index == 0x1003:
            h.clear_error_history()
        elif own and index == odm.ACCOUNT_CLEAR:
            h.clear_account()
        elif own and 0x2000 <= index < 0x2100:
            h.signal(index)
