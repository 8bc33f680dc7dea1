"""The PDO runtime of the emulated drive: RPDOs received, TPDOs sent, SYNC consumer state.

CiA 301: PDOs are exchanged only in OPERATIONAL; each is described by its communication
parameters (0x14xx/0x18xx: COB-ID with bit 31 = not valid, transmission type, event timer)
and its mapping (0x16xx/0x1Axx). A synchronous TPDO of transmission type n (1..240) is sent
on every n-th SYNC; an RPDO's event timer (sub 5, ms) is the deadline for its next
reception. The SYNC consumer listens on 0x1005.

This emulator: on entering OPERATIONAL the runtime is built once from the present
dictionary (valid RPDOs, valid non-empty TPDOs of every PDO record it has, their codecs:
the emulator's own signal objects by ``dbc/drive.dbc``, every other object as the raw
integer of its data type; the cycle period 0x1006 and RPDO apply 0x2203) and dropped on
leaving it. A received RPDO of the wrong length is rejected (the device then faults);
otherwise its raw values go into the dictionary and the cycle count of its reception is
kept for the deadline, which counts SYNC periods of simulated time. Sampling writes the
statusword and every TPDO signal object the dictionary has; a TPDO carries the present
values of the objects it maps.
"""

from __future__ import annotations

from collections.abc import Iterator
from dataclasses import dataclass
from typing import Any

import can
from canopen.objectdictionary import datatypes

from dbc import MessageCodec, message_codec
from dbc.codec import SignalSpec, signal_specs
from dbc.modes import RpdoApply, SetpointFrame
from dbc.signals import FRAME, LOAD, SETPOINTS, TX, setpoint_frame_of
from plant import od as odm
from plant.drive import Measurement
from plant.rpdo import tpdo_signals


def raw_spec(name: str, var: Any) -> SignalSpec:
    """A raw integer signal (factor 1) of an object's data type (an ODVariable)."""
    return SignalSpec(name, 1.0, len(var), var.data_type in datatypes.SIGNED_TYPES)


SETPOINT_SIGNALS = frozenset({*FRAME, *(n for names in SETPOINTS.values() for n in names)})


@dataclass
class Rpdo:
    """A valid RPDO while OPERATIONAL."""

    config: odm.PdoConfig
    codec: MessageCodec
    timeout: float  #: s, deadline (0 = off)
    last: int | None = None  #: cycles completed when last received
    controlword: bool = False  #: maps the controlword
    setpoints: bool = False  #: maps eps_0, w_0 or a current/voltage reference
    frame: bool = False  #: maps eps_0 or w_0 (the (d, q) frame)
    load: bool = False  #: maps T_L


@dataclass
class Tpdo:
    """A valid TPDO with a mapping while OPERATIONAL."""

    config: odm.PdoConfig
    codec: MessageCodec


class PdoRuntime:
    """RPDOs and TPDOs of the present OPERATIONAL period (see the module docstring).

    ``sync_id``, ``rpdos`` (by COB-ID), ``tpdos`` and ``last_counter`` (the last SYNC
    counter received) are cleared by :meth:`clear`; ``period`` (s), ``apply`` (0x2203)
    and ``frame_names`` (the setpoint signals of the mapped frame) are set by :meth:`build`.
    """

    def __init__(self, store: odm.ObjectStore, bus: can.BusABC) -> None:
        self._store = store
        self._values: dict[odm.Key, Any] = store.values
        self._bus = bus
        signals = store.signals
        tx = tuple(n for n in TX if n in signals)
        self._tx_codec = message_codec("TX", 0, tx)
        self._tx_keys = tuple(signals[n] for n in tx)
        self._statusword = "statusword" not in signals and (0x6041, 0) in store.vars
        self._setpoint_keys = frozenset(signals[n] for n in SETPOINT_SIGNALS if n in signals)
        self._frame_keys = frozenset(signals[n] for n in FRAME if n in signals)
        self._load_keys = frozenset(signals[n] for n in LOAD if n in signals)
        self.period = 0.0
        self.apply = RpdoApply.AT_NEXT_SYNC
        self.frame_names = SETPOINTS[SetpointFrame.DQ]
        self.clear()

    def clear(self) -> None:
        """No PDOs (not OPERATIONAL); the SYNC COB-ID from 0x1005."""
        self.sync_id: int = self._values[(0x1005, 0)] & 0x7FF
        self.rpdos: dict[int, Rpdo] = {}
        self.tpdos: list[Tpdo] = []
        self.last_counter: int | None = None

    def set_sync_id(self, cob_id: int) -> None:
        """0x1005 written."""
        self.sync_id = cob_id & 0x7FF

    def build(self) -> None:
        """Entering OPERATIONAL: the runtime from the present dictionary."""
        self.clear()
        v, store = self._values, self._store
        self.period = store.period
        self.apply = RpdoApply(v[(odm.RPDO_APPLY, 0)] if store.own else 0)
        mapped: set[str] = set()
        for comm in store.rpdos:
            cfg = store.pdo(comm)
            if not cfg.valid:
                continue
            keys = set(cfg.entries)
            mapped |= {n for n, k in store.signals.items() if k in keys}
            self.rpdos[cfg.cob_id] = Rpdo(
                cfg, self._codec(f"RPDO{cfg.number}", cfg),
                timeout=cfg.event_timer_ms / 1000.0, controlword=(0x6040, 0) in keys,
                setpoints=bool(keys & self._setpoint_keys),
                frame=bool(keys & self._frame_keys), load=bool(keys & self._load_keys))
        self.frame_names = SETPOINTS[setpoint_frame_of(mapped)]
        for comm in store.tpdos:
            cfg = self._store.pdo(comm)
            if cfg.valid and cfg.entries:
                self.tpdos.append(Tpdo(cfg, self._codec(f"TPDO{cfg.number}", cfg)))

    def _codec(self, name: str, cfg: odm.PdoConfig) -> MessageCodec:
        """The layout of a mapping: the emulator's own signal objects as their DBC signal
        (scaled), every other object as the raw integer of the size and sign of its data
        type (the standard objects, in the units of the drive's EDS)."""
        specs, signals = signal_specs(), self._store.signals
        return MessageCodec(name, cfg.cob_id, [
            specs[n] if signals.get(n) == key else raw_spec(n, self._store.vars[key])
            for n, key in zip(cfg.names, cfg.entries, strict=True)])

    def receive(self, r: Rpdo, data: bytes, cycles: int) -> bool:
        """An RPDO frame after ``cycles`` completed cycles; False if its length is wrong."""
        if len(data) != r.codec.length:
            return False
        v = self._values
        for key, raw in zip(r.config.entries, r.codec.decode_raw(data), strict=True):
            v[key] = raw
        r.last = cycles
        return True

    def expired(self, m: int) -> Iterator[Rpdo]:
        """The RPDOs whose deadline has passed at the end of cycle ``m`` (each once: its
        deadline is re-armed by the next reception)."""
        T = self.period
        for r in self.rpdos.values():
            if r.timeout and r.last is not None and (m - r.last) * T > r.timeout + 1e-12:
                r.last = None
                yield r

    def sample(self, meas: Measurement, statusword: int, counter: int) -> None:
        """Write the statusword and every TPDO signal object for one sample."""
        raws = self._tx_codec.raw(tpdo_signals(meas, statusword, counter))
        v = self._values
        for key, raw in zip(self._tx_keys, raws, strict=True):
            v[key] = raw
        if self._statusword:
            v[(0x6041, 0)] = statusword

    def transmit(self, m: int) -> None:
        """The TPDOs due on the ``m``-th SYNC, in order."""
        v = self._values
        send = self._bus.send
        for t in self.tpdos:
            tt = t.config.trans_type
            if tt == 1 or m % tt == 0:
                data = t.codec.pack(*[v[e] for e in t.config.entries])
                send(can.Message(arbitration_id=t.config.cob_id, data=data,
                                 is_extended_id=False))

