"""The emulated drive's object dictionary: values, SDO access rules, PDO layouts.

The dictionary is a :class:`Dictionary`: the emulator's own, ``dbc/drive.eds`` (loaded with
``canopen.import_od``), or a twin's, another drive's EDS/DCF (:mod:`plant.twin`).
:class:`ObjectStore` holds the present value of every sub-object as a Python value (int,
float, str, bytes; PDO signal objects as their raw integers) and checks SDO writes: access
type, length, NMT state (communication setup and 0x6060 only in PRE-OPERATIONAL, and the
emulator's parameters), value range from the file's LowLimit/HighLimit (the emulator's REAL32
parameters: :data:`REAL32_LIMITS`) and the object-specific rules of CiA 301 (PDO COB-ID/mapping
procedure), of CiA 402 (0x6060 takes the modes the device offers) and of the emulator
(consistent motor and drive parameters). Writes that break a rule raise
:class:`canopen.SdoAbortedError` with the standard abort code.

The emulator's manufacturer objects (0x2xxx of ``drive.eds``: motor, drive and model
parameters, RPDO apply, time base, account, the vector signals) mean what
``tools/gen_eds.py`` says only in its own dictionary; in a twin an object at those indices
is the other drive's, served as the file describes it.

REAL32 parameters keep the exact value given to :class:`plant.device.DriveDevice` until an
SDO write replaces them with a 32-bit float, so a default emulator equals the pure model
bit for bit.
"""

from __future__ import annotations

import math
from collections.abc import Iterator, Mapping
from dataclasses import dataclass, field
from typing import Any

import canopen
from canopen.objectdictionary import ODArray, ODRecord, ODVariable, datatypes
from canopen.sdo import SdoAbortedError

from dbc import EDS_PATH, signal_specs
from dbc.cia402 import OperationMode
from dbc.edsfile import configured
from dbc.timing import INTERNAL_RATE_MAX, PERIOD_MAX, PERIOD_MIN, internal_rate

Key = tuple[int, int]

# ---- SDO abort codes (CiA 301) ------------------------------------------------------------
ABORT_UNSUPPORTED = 0x06010000
ABORT_WRITE_ONLY = 0x06010001
ABORT_READ_ONLY = 0x06010002
ABORT_NO_OBJECT = 0x06020000
ABORT_NOT_MAPPABLE = 0x06040041
ABORT_PDO_LENGTH = 0x06040042
ABORT_INCOMPATIBLE = 0x06040043
ABORT_LENGTH = 0x06070010
ABORT_NO_SUBINDEX = 0x06090011
ABORT_RANGE = 0x06090030
ABORT_TOO_HIGH = 0x06090031
ABORT_TOO_LOW = 0x06090032
ABORT_STATE = 0x08000022

# ---- objects ------------------------------------------------------------------------------
MOTOR = 0x2200  #: REAL32 J, R_s, R_r, L_s, L_r, M (sub-indices 1..6)
DRIVE = 0x2201  #: u_dc, i_trip, current_loop_bw, i_offset_a/b, i_gain_error, i_noise_rms, f_pwm,
#: w_max
MODEL = 0x2202  #: 0 ideal current source, 1 PI current loop
RPDO_APPLY = 0x2203  #: 0 at the next SYNC (delay 1), 1 on receipt (delay 0)
SEED = 0x2204
TIME_BASE = 0x2205  #: dbc.timing.TimeBase: 0 wall clock, 1 SYNC (lockstep)
ACCOUNT = 0x2300
ACCOUNT_CLEAR = 0x2301
MOTOR_SUBS = ("J", "R_s", "R_r", "L_s", "L_r", "M")
DRIVE_SUBS = ("u_dc", "i_trip", "current_loop_bw", "i_offset_a", "i_offset_b", "i_gain_error",
              "i_noise_rms", "f_pwm", "w_max")
#: Ranges of the REAL32 parameters. EDS readers take integer LowLimit/HighLimit only
#: (objdictgen refuses "1e-05", python-canopen skips it), so ``tools/gen_eds.py`` writes the
#: integral bounds from here into the EDS and lists every range in its [Comments].
REAL32_LIMITS: dict[Key, tuple[float, float]] = {
    (MOTOR, 1): (1e-05, 10.0), (MOTOR, 2): (0.001, 100.0), (MOTOR, 3): (0.001, 100.0),
    (MOTOR, 4): (0.0001, 10.0), (MOTOR, 5): (0.0001, 10.0), (MOTOR, 6): (0.0001, 10.0),
    (DRIVE, 1): (10.0, 1300.0), (DRIVE, 2): (0.1, 1000.0), (DRIVE, 3): (10.0, 1e6),
    (DRIVE, 4): (-5.0, 5.0), (DRIVE, 5): (-5.0, 5.0), (DRIVE, 6): (-0.5, 0.5),
    (DRIVE, 7): (0.0, 5.0), (DRIVE, 9): (1.0, 10000.0),
}
#: Written only in PRE-OPERATIONAL: the communication setup and the mode (and, in the
#: emulator's own dictionary, its parameters); the PDO records too (:attr:`ObjectStore.pdos`).
PREOP_ONLY = frozenset({0x1005, 0x1006, 0x1014, 0x1019, 0x6060})
EMULATOR_PREOP_ONLY = frozenset({MOTOR, DRIVE, MODEL, RPDO_APPLY, SEED, TIME_BASE})
#: Whose change requires rebuilding the drive model (and its control) on entering
#: OPERATIONAL: the mode and the period; the emulator's parameters; a twin's units and
#: torque limit (:mod:`plant.units`).
PARAMETER_OBJECTS = frozenset({0x6060, 0x1006})
EMULATOR_PARAMETERS = frozenset({MOTOR, DRIVE, MODEL, SEED})
TWIN_PARAMETERS = frozenset({0x6072, 0x6075, 0x6076, 0x608F, 0x6091, 0x6092, 0x60A8, 0x60A9})
#: The PDO records a dictionary may hold (CiA 301): communication, mapping = + 0x200.
RPDO_RANGE = range(0x1400, 0x1600)
TPDO_RANGE = range(0x1800, 0x1A00)
COB_INVALID = 0x80000000
#: The simulated time per SYNC of a twin whose 0x1006 is 0 (not set) or missing, s.
UNSET_PERIOD = 1e-3
#: CiA 301 restricted COB-IDs (inclusive ranges): NMT and reserved 0x000..0x07F, 0x101..0x180,
#: the default SDO 0x581..0x5FF and 0x601..0x67F, reserved 0x6E0..0x6FF, NMT error control
#: 0x701..0x77F and reserved (LSS) 0x780..0x7FF. They hold the node's own NMT, SDO and
#: heartbeat identifiers; the defaults of SYNC (0x080) and EMCY (0x080 + n) lie outside.
RESTRICTED_COB_IDS = ((0x000, 0x07F), (0x101, 0x180), (0x581, 0x5FF), (0x601, 0x67F),
                      (0x6E0, 0x6FF), (0x701, 0x77F), (0x780, 0x7FF))


def restricted_cob_id(cob_id: int) -> bool:
    """The 11-bit ``cob_id`` is one CiA 301 restricts (see :data:`RESTRICTED_COB_IDS`)."""
    return any(lo <= cob_id <= hi for lo, hi in RESTRICTED_COB_IDS)


def load_od(node_id: int) -> canopen.ObjectDictionary:
    """``dbc/drive.eds`` for ``node_id``."""
    return canopen.import_od(str(EDS_PATH), node_id)


@dataclass(frozen=True)
class Dictionary:
    """The dictionary a device presents. ``own``: the emulator's ``dbc/drive.eds`` (its
    manufacturer objects are its parameters and vector signals), else a twin's file.
    ``modes``: the modes 0x6060 accepts. ``runtime``: values the device's runtime needs of
    objects the dictionary lacks (a twin's file without 0x1017, …): kept, but no SDO
    reaches them (0x06020000)."""

    od: canopen.ObjectDictionary
    own: bool
    modes: frozenset[OperationMode]
    runtime: Mapping[Key, Any] = field(default_factory=dict)

    @classmethod
    def emulator(cls, node_id: int) -> Dictionary:
        """The emulator's own dictionary for ``node_id``: every :class:`OperationMode`."""
        return cls(load_od(node_id), True, frozenset(OperationMode))


def _default(var: ODVariable) -> Any:
    """A sub-object's value as the file configures it, or the zero of its type."""
    value = configured(var)
    if value is not None:
        return value
    if var.data_type in (datatypes.VISIBLE_STRING, datatypes.UNICODE_STRING):
        return ""
    if var.data_type in (datatypes.OCTET_STRING, datatypes.DOMAIN):
        return b""
    return 0.0 if var.data_type in datatypes.FLOAT_TYPES else 0


def iter_vars(od: canopen.ObjectDictionary) -> Iterator[tuple[Key, ODVariable]]:
    """Every sub-object as ((index, subindex), variable)."""
    for obj in od.values():
        if isinstance(obj, ODVariable):
            yield (obj.index, 0), obj
        elif isinstance(obj, ODRecord | ODArray):
            for sub in obj.values():
                yield (obj.index, sub.subindex), sub


@dataclass(frozen=True)
class PdoConfig:
    """One PDO as configured in the dictionary (CiA 301 0x14xx/0x16xx, 0x18xx/0x1Axx)."""

    number: int  #: 1..512
    cob_id: int  #: 11-bit identifier
    valid: bool  #: COB-ID bit 31 clear
    trans_type: int  #: sub 2
    event_timer_ms: int  #: sub 5 (RPDO: deadline monitoring; 0 = off)
    entries: tuple[Key, ...]  #: mapped objects in order
    names: tuple[str, ...]  #: their ParameterNames (= DBC signal names)


class ObjectStore:
    """Values of the dictionary with the SDO write rules (see the module docstring).

    ``dictionary``: the emulator's own for ``node_id`` unless given. ``signals``: the
    emulator's PDO signal objects by DBC signal name (none in a twin). ``pdos``: the PDO
    communication records present (0x1400.., 0x1800..), each with its mapping (+ 0x200).
    ``f_pwm``: the drive's nominal internal rate, Hz (a twin's period 0x1006 raises it to a
    whole number of steps, :func:`dbc.timing.internal_rate`)."""

    def __init__(self, node_id: int, overrides: Mapping[Key, Any] | None = None,
                 dictionary: Dictionary | None = None, f_pwm: float = 10e3) -> None:
        self.node_id = node_id
        self.dictionary = dictionary if dictionary is not None else Dictionary.emulator(node_id)
        self.own = self.dictionary.own
        self.modes = frozenset(int(m) for m in self.dictionary.modes)
        self.f_pwm = f_pwm
        self.od = self.dictionary.od
        self.vars: dict[Key, ODVariable] = dict(iter_vars(self.od))
        self.limits: dict[Key, tuple[float | None, float | None]] = {
            k: (v.min, v.max) for k, v in self.vars.items()
            if v.min is not None or v.max is not None}
        if self.own:
            self.limits.update(REAL32_LIMITS)
        self.defaults: dict[Key, Any] = dict(self.dictionary.runtime)
        self.defaults.update({key: _default(var) for key, var in self.vars.items()})
        self.defaults.update(overrides or {})
        self.values: dict[Key, Any] = dict(self.defaults)
        names = {v.name: k for k, v in self.vars.items() if v.pdo_mappable}
        self.signals: dict[str, Key] = ({n: k for n, k in names.items() if n in signal_specs()}
                                        if self.own else {})
        self.rpdos = tuple(i for i in RPDO_RANGE if i in self.od and i + 0x200 in self.od)
        self.tpdos = tuple(i for i in TPDO_RANGE if i in self.od and i + 0x200 in self.od)
        pdo_records = {i + d for i in (*self.rpdos, *self.tpdos) for d in (0, 0x200)}
        self.preop_only = PREOP_ONLY | pdo_records | (EMULATOR_PREOP_ONLY if self.own
                                                      else frozenset())
        self.parameters = PARAMETER_OBJECTS | (EMULATOR_PARAMETERS if self.own
                                               else TWIN_PARAMETERS)
        #: the COB-ID objects (index, subindex): SYNC, EMCY, RPDOs, TPDOs
        self.cob_id_objects = tuple(k for k in ((0x1005, 0), (0x1014, 0),
                                                *((i, 1) for i in (*self.rpdos, *self.tpdos)))
                                    if k in self.vars)

    @property
    def period(self) -> float:
        """The simulated time one SYNC advances, s: 0x1006 (a twin's 0, or none: 1 ms)."""
        us = self.values.get((0x1006, 0), 0)
        return us / 1e6 if us or self.own else UNSET_PERIOD

    @property
    def internal_rate(self) -> float:
        """A twin's internal rate, Hz: the nominal ``f_pwm`` raised to a whole number of
        steps per :attr:`period` (:func:`dbc.timing.internal_rate`)."""
        return internal_rate(self.f_pwm, self.period)

    # ---- plain access -----------------------------------------------------------------------
    def reset(self, communication_only: bool = False) -> None:
        """Restore the defaults (all, or the communication area 0x1000..0x1FFF)."""
        for key, value in self.defaults.items():
            if not communication_only or 0x1000 <= key[0] < 0x2000:
                self.values[key] = value

    def lookup(self, index: int, subindex: int) -> Any:
        """The present value of a sub-object the dictionary has; None if it has none (a
        value the runtime keeps for an object a twin's file lacks included)."""
        return self.values.get((index, subindex)) if (index, subindex) in self.vars else None

    def var(self, index: int, subindex: int) -> ODVariable:
        """The sub-object, or SdoAbortedError 0x06020000 / 0x06090011."""
        if index not in self.od:
            raise SdoAbortedError(ABORT_NO_OBJECT)
        obj = self.od[index]
        if isinstance(obj, ODVariable):
            if subindex != 0:
                raise SdoAbortedError(ABORT_NO_SUBINDEX)
            return obj
        # an ARRAY makes up any sub-index it is asked for (python-canopen): only those the
        # dictionary holds exist (0x1003 beyond its entries, 0x1016 beyond sub 1 …)
        declared = getattr(obj, "subindices", None)
        if subindex not in (declared if declared is not None else obj) or \
                (index, subindex) not in self.values:
            raise SdoAbortedError(ABORT_NO_SUBINDEX)
        return obj[subindex]

    def read(self, index: int, subindex: int) -> bytes:
        """SDO upload: the encoded value (0x06010001 for write-only objects)."""
        var = self.var(index, subindex)
        if not var.readable:
            raise SdoAbortedError(ABORT_WRITE_ONLY)
        return var.encode_raw(self.values[(index, subindex)])

    # ---- SDO download rules -----------------------------------------------------------------
    def check_write(self, index: int, subindex: int, data: bytes, nmt: str) -> Any:
        """Decode and validate an SDO download; returns the value (does not store it)."""
        var = self.var(index, subindex)
        if not var.writable:
            raise SdoAbortedError(ABORT_READ_ONLY)
        if var.data_type in datatypes.NUMBER_TYPES and 8 * len(data) != len(var):
            raise SdoAbortedError(ABORT_LENGTH)
        try:
            value = var.decode_raw(bytes(data))
        except Exception:
            raise SdoAbortedError(ABORT_RANGE) from None
        if index in self.preop_only and nmt != "PRE-OPERATIONAL":
            raise SdoAbortedError(ABORT_STATE)
        if isinstance(value, float) and not math.isfinite(value):
            raise SdoAbortedError(ABORT_RANGE)
        lo, hi = self.limits.get((index, subindex), (None, None))
        if hi is not None and value > hi:
            raise SdoAbortedError(ABORT_TOO_HIGH)
        if lo is not None and value < lo:
            raise SdoAbortedError(ABORT_TOO_LOW)
        self._check_specific(index, subindex, value)
        return value

    def _check_specific(self, index: int, subindex: int, value: Any) -> None:
        if index == 0x6060 and value not in self.modes:
            raise SdoAbortedError(ABORT_RANGE)  # a mode this drive does not have (0x6502)
        if (index in (0x1005, 0x1014) and value & 0x7FFFF800) or (index == 0x1019
                                                                    and value == 1):
            raise SdoAbortedError(ABORT_RANGE)  # 29-bit ids, SYNC production, counter 1
        if (index, subindex) in self.cob_id_objects:
            self._check_cob_id(index, subindex, value)
        if index == 0x1016 and subindex == 1:
            node = (value >> 16) & 0xFF
            if value >> 24 or (value & 0xFFFF and not 1 <= node <= 127):
                raise SdoAbortedError(ABORT_RANGE)
        elif index == 0x1006:
            self.check_period(value)
        elif index == 0x1003 and subindex == 0 and value != 0:
            raise SdoAbortedError(ABORT_RANGE)
        elif index in self.rpdos or index in self.tpdos:
            self._check_pdo_comm(index, subindex, value)
        elif index - 0x200 in self.rpdos or index - 0x200 in self.tpdos:
            self._check_pdo_map(index, subindex, value)
        elif self.own:
            self._check_emulator(index, subindex, value)

    def check_period(self, us: int) -> None:
        """0x1006: the emulator's whole number of steps of its internal rate 0x2201 sub 8; a
        twin's period of 100 µs … 100 ms (or 0: not set, 1 ms per SYNC) at an internal
        rate it can raise to a whole number of steps."""
        if self.own:
            steps = us * self.values[(DRIVE, 8)] / 1e6
            if abs(steps - round(steps)) > 1e-9 or round(steps) < 1:
                raise SdoAbortedError(ABORT_RANGE)
        elif us and not (PERIOD_MIN <= us / 1e6 <= PERIOD_MAX
                         and internal_rate(self.f_pwm, us / 1e6) <= INTERNAL_RATE_MAX):
            raise SdoAbortedError(ABORT_RANGE)

    def _check_emulator(self, index: int, subindex: int, value: Any) -> None:
        """The rules of the emulator's own parameters (0x2201, 0x2200)."""
        v = self.values
        if index == DRIVE and subindex == 8:
            steps = v[(0x1006, 0)] * value / 1e6
            if abs(steps - round(steps)) > 1e-9 or v[(DRIVE, 3)] >= math.pi * value:
                raise SdoAbortedError(ABORT_RANGE)
        elif index == DRIVE and subindex == 3 and value >= math.pi * v[(DRIVE, 8)]:
            raise SdoAbortedError(ABORT_TOO_HIGH)
        elif index == MOTOR:
            m = {name: v[(MOTOR, k)] for k, name in enumerate(MOTOR_SUBS, 1)}
            m[MOTOR_SUBS[subindex - 1]] = value
            if m["M"] ** 2 >= m["L_s"] * m["L_r"]:
                raise SdoAbortedError(ABORT_RANGE)  # not a physical motor (σ ≤ 0)

    def _valid_cob_id(self, key: Key, value: int) -> int | None:
        """The 11-bit id a COB-ID object with ``value`` uses, None if it is not valid
        (bit 31; SYNC 0x1005 has no such bit: its consumer always listens)."""
        if key[0] != 0x1005 and value & COB_INVALID:
            return None
        return value & 0x7FF

    def _check_cob_id(self, index: int, subindex: int, value: int) -> None:
        """CiA 301 restricted COB-IDs (0x06090030), whether valid or not, and, for a valid
        one, a collision with another of the node's own valid COB-IDs (SYNC, EMCY, PDOs)."""
        cob = value & 0x7FF
        if restricted_cob_id(cob):
            raise SdoAbortedError(ABORT_RANGE)
        key = (index, subindex)
        if self._valid_cob_id(key, value) is None:
            return
        for other in self.cob_id_objects:
            if other != key and self._valid_cob_id(other, self.values[other]) == cob:
                raise SdoAbortedError(ABORT_RANGE)

    def _check_pdo_comm(self, index: int, subindex: int, value: int) -> None:
        if subindex == 1:
            if value & 0x1FFFF800 or value & 0x7FF == 0:
                raise SdoAbortedError(ABORT_RANGE)  # 29-bit / reserved id
            old = self.values[(index, 1)]
            if not old & COB_INVALID and not value & COB_INVALID and (old ^ value) & 0x7FF:
                raise SdoAbortedError(ABORT_RANGE)  # CiA 301: invalidate before changing
            if old & COB_INVALID and not value & COB_INVALID and self.mapping_problem(index):
                raise SdoAbortedError(ABORT_INCOMPATIBLE)  # a twin's default we cannot serve
        elif subindex == 2 and index in self.rpdos and 240 < value < 254:
            raise SdoAbortedError(ABORT_RANGE)

    def _check_pdo_map(self, index: int, subindex: int, value: int) -> None:
        comm = index - 0x200
        if not self.values[(comm, 1)] & COB_INVALID:
            raise SdoAbortedError(ABORT_STATE)  # CiA 301: the PDO must be invalid
        rx = index - 0x200 in self.rpdos
        if subindex == 0:
            if value > 8:
                raise SdoAbortedError(ABORT_TOO_HIGH)
            bits = 0
            for k in range(1, value + 1):
                entry = self.values.get((index, k), 0)
                self._mappable(entry, rx)
                bits += entry & 0xFF
            if bits > 64:
                raise SdoAbortedError(ABORT_PDO_LENGTH)
            return
        if self.values[(index, 0)] != 0:
            raise SdoAbortedError(ABORT_STATE)  # CiA 301: disable the mapping first
        if value:
            self._mappable(value, rx)

    def _mappable(self, entry: int, rx: bool) -> None:
        """A mapping entry names an object a PDO can carry, else 0x06040041."""
        if self.unmappable(entry, rx) is not None:
            raise SdoAbortedError(ABORT_NOT_MAPPABLE)

    def unmappable(self, entry: int, rx: bool) -> str | None:
        """Why a PDO (``rx``: an RPDO) cannot carry the object a mapping entry names, None if
        it can: it must exist, be PDO-mappable, writable for an RPDO, of the entry's length,
        and of 8, 16 or 32 bits (the PDO codec's)."""
        index, sub, bits = entry >> 16, (entry >> 8) & 0xFF, entry & 0xFF
        name = f"0x{index:04X} sub {sub}"
        try:
            var = self.var(index, sub)
        except SdoAbortedError:
            return f"{name} is not in the dictionary"
        if not var.pdo_mappable:
            return f"{name} is not PDO-mappable"
        if rx and not var.writable:
            return f"{name} is {var.access_type}: an RPDO writes it"
        if bits != len(var):
            return f"{name} has {len(var)} bits, the entry {bits}"
        if bits not in (8, 16, 32):
            return f"{name} has {bits} bits: the emulator's PDOs carry 8, 16 or 32"
        return None

    def mapping_problem(self, comm: int) -> str | None:
        """Why the present mapping of the PDO ``comm`` cannot be served, None if it can: an
        entry (sub-index and value) naming no mappable object of its size, or over 64 bits."""
        mapping, rx = comm + 0x200, comm in self.rpdos
        count, bits = self.values.get((mapping, 0), 0), 0
        if count > 8:
            return f"sub-index 0 = {count} mapped objects (at most 8)"
        for k in range(1, count + 1):
            entry = self.values.get((mapping, k), 0)
            why = self.unmappable(entry, rx)
            if why is not None:
                return f"sub-index {k} = 0x{entry:08X}: {why}"
            bits += entry & 0xFF
        return f"{bits} bits (at most 64)" if bits > 64 else None

    # ---- PDO configuration ------------------------------------------------------------------
    def pdo(self, comm: int) -> PdoConfig:
        """The PDO whose communication record is ``comm`` (0x1400.. or 0x1800..)."""
        v = self.values
        mapping = comm + 0x200
        entries = []
        for k in range(1, v.get((mapping, 0), 0) + 1):
            e = v.get((mapping, k), 0)
            entries.append((e >> 16, (e >> 8) & 0xFF))
        cob = v.get((comm, 1), COB_INVALID)
        return PdoConfig(
            number=(comm & 0x1FF) + 1,
            cob_id=cob & 0x7FF,
            valid=not cob & COB_INVALID,
            trans_type=v.get((comm, 2), 1),
            event_timer_ms=v.get((comm, 5), 0),
            entries=tuple(entries),
            names=tuple(self.vars[e].name for e in entries),
        )
