"""A twin: the emulated drive presenting the drive another EDS or DCF describes.

``hil-plant run --eds FILE --node N`` serves the file's object dictionary (read by
:func:`dbc.edsfile.read_eds`: python-canopen's import, ``$NODEID`` resolved for N, a DCF's
ParameterValue before its DefaultValue) on the emulated motor:

* identity: 0x1000, 0x1018, 0x1008.. as the file gives them (constants);
* the CANopen runtime of the emulator (NMT, heartbeat 0x1017/0x1016, SYNC 0x1005/0x1006,
  EMCY 0x1014/0x1001/0x1003, SDO, the PDO records 0x1400..0x1BFF with the file's default
  COB-IDs, transmission types and mappings);
* the standard CiA 402 objects of :data:`BACKED`, backed by the motor model and the drive's
  own control in the units the file states (:mod:`plant.units`);
* the modes its 0x6502 lists that the emulator has (PV, PT, CSP, CSV, CST, each with its
  target object in the file); 0x6502 reads those, 0x6060 refuses any other (0x06090030);
* every other object as plain storage: read and written as its access type says, from the
  file's value, with its limits; listed at start-up (:meth:`Twin.describe`).

The emulator's own manufacturer objects (0x2xxx of ``drive.eds``) are not there unless the
file has objects at those indices, which are then the file's. A file the twin cannot serve
(no 0x6040/0x6041/0x6060, a default PDO mapping of objects it cannot carry, a period out of
range) is refused with what to change.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

from canopen.objectdictionary import ODArray, ODRecord
from canopen.sdo import SdoAbortedError

from dbc.cia402 import SUPPORTED_MODES, OperationMode
from dbc.edsfile import EdsFile, configured, read_eds
from dbc.errors import UserError
from plant import od as odm
from plant.units import TARGETS, units_from

#: Identity objects (CiA 301): served from the file.
IDENTITY = frozenset({0x1000, 0x1008, 0x1009, 0x100A, 0x1018})
#: Communication objects the emulator's CANopen runtime serves (the PDO records too).
RUNTIME = frozenset({0x1001, 0x1003, 0x1005, 0x1006, 0x1014, 0x1016, 0x1017, 0x1019})
#: The standard CiA 402 objects the motor model and the drive's control back: the state
#: machine, the modes, targets, actual values, demands, limits, profile parameters, units.
BACKED = frozenset({0x603F, 0x6040, 0x6041, 0x6060, 0x6061, 0x6064, 0x606B, 0x606C, 0x606D,
                    0x606E, 0x606F, 0x6070, 0x6071, 0x6072, 0x6074, 0x6075, 0x6076, 0x6077,
                    0x6078, 0x6079, 0x607A, 0x6083, 0x6084, 0x6087, 0x6088, 0x608F, 0x6091,
                    0x6092, 0x60A8, 0x60A9, 0x60FF, SUPPORTED_MODES})
#: A twin needs these to be a CiA 402 drive at all (CiA 301: 0x1000, 0x1018).
REQUIRED = {0x1000: "device type", 0x1018: "identity", 0x6040: "controlword",
            0x6041: "statusword", 0x6060: "modes of operation"}
#: Other modes CiA 402 names by their 0x6502 bit.
OTHER_MODES = {0: "1 profile position", 1: "2 velocity", 5: "6 homing",
               6: "7 interpolated position", 10: "11 cyclic synchronous torque with "
               "commutation angle"}


def mode_name(mode: OperationMode) -> str:
    """'3 profile velocity'."""
    return f"{int(mode)} {mode.name.lower().replace('_', ' ').replace('sync', 'synchronous')}"


@dataclass(frozen=True)
class Twin:
    """What the emulator makes of a drive's EDS/DCF (see the module docstring)."""

    file: EdsFile
    dictionary: odm.Dictionary
    storage: tuple[str, ...]  #: the plain-storage objects, one line each
    notes: tuple[str, ...]  #: modes and units: what the twin offers and assumes

    @property
    def node_id(self) -> int:
        return self.file.node_id

    def describe(self) -> list[str]:
        """The start-up report: identity, modes, units, plain storage."""
        od = self.file.od
        info = od.device_information
        variables = dict(odm.iter_vars(od))

        def value(index: int, sub: int = 0) -> str:
            var = variables.get((index, sub))
            v = None if var is None else configured(var)
            return "-" if v is None else f"0x{v:08X}" if isinstance(v, int) else str(v)

        product = info.product_name or value(0x1008)
        lines = [f"twin of {product!r} by {info.vendor_name or '?'} from {self.file.path}"
                 + (" (node id from its [DeviceComissioning])" if self.file.node_from_file
                    else ""),
                 f"identity: device type {value(0x1000)}, vendor {value(0x1018, 1)}, product "
                 f"{value(0x1018, 2)}, revision {value(0x1018, 3)}, serial {value(0x1018, 4)}",
                 *self.notes]
        if self.storage:
            lines.append(f"plain storage, not backed by the motor model ({len(self.storage)}):")
            lines += [f"  {s}" for s in self.storage]
        return lines


def _runtime(node_id: int) -> dict[odm.Key, int]:
    """Values the runtime needs of objects a file may lack (CiA 301's pre-defined
    connection set: SYNC 0x80, EMCY 0x80 + n; no heartbeat, no history)."""
    return {(0x1001, 0): 0, (0x1003, 0): 0, (0x1005, 0): 0x80, (0x1006, 0): 0,
            (0x1014, 0): 0x80 + node_id, (0x1016, 1): 0, (0x1017, 0): 0, (0x1019, 0): 0,
            (0x603F, 0): 0, (0x6040, 0): 0, (0x6041, 0): 0, (0x6060, 0): 0, (0x6061, 0): 0}


def _modes(f: EdsFile) -> tuple[frozenset[OperationMode], list[str]]:
    """The modes a twin offers (its 0x6502 ∩ the emulator's standard modes whose target
    object the file has) and what it says about the others."""
    od = f.od
    supported = configured(od[SUPPORTED_MODES]) if SUPPORTED_MODES in od else None
    if not isinstance(supported, int):
        return frozenset(), ["modes: none (the file gives no 0x6502 supported drive modes); "
                             "0x6060 refuses every mode"]
    offered, missing = [], []
    for mode in sorted(OperationMode.offered(supported)):
        if not mode.standard:
            continue  # its manufacturer modes are the vendor's, not the emulator's vectors
        if TARGETS[mode][0] in od:
            offered.append(mode)
        else:
            missing.append(f"{mode_name(mode)} (no 0x{TARGETS[mode][0]:04X} in the file)")
    ours = sum(m.supported_bit for m in OperationMode if m.standard)
    others = [OTHER_MODES.get(b, f"manufacturer-specific bit {b}" if b >= 16 else f"bit {b}")
              for b in range(32) if supported & ~ours & (1 << b)]
    notes = [f"modes: {', '.join(mode_name(m) for m in offered) or 'none'} "
             f"(0x6502 reads 0x{sum(m.supported_bit for m in offered):08X}; the file's "
             f"0x{supported:08X})"]
    if others or missing:
        notes.append("not emulated, refused by 0x6060: " + ", ".join([*others, *missing]))
    default = configured(od[0x6060]) if 0x6060 in od else None
    if default not in {int(m) for m in offered}:
        notes.append(f"0x6060's value {default} is no mode the twin offers: the drive's "
                     "control waits for the master to set one")
    return frozenset(offered), notes


def _storage(f: EdsFile, store: odm.ObjectStore) -> tuple[str, ...]:
    """One line per object not backed by the model, the runtime or the identity."""
    lines = []
    for obj in f.od.values():
        index = obj.index
        if (index < 0x1000 or index in IDENTITY or index in RUNTIME or index in BACKED
                or index in store.rpdos or index in store.tpdos
                or index - 0x200 in store.rpdos or index - 0x200 in store.tpdos):
            continue
        if isinstance(obj, ODRecord | ODArray):
            subs = [v for v in obj.values() if v.subindex]
            access = "/".join(sorted({v.access_type for v in subs})) or "-"
            lines.append(f"0x{index:04X} {obj.name} ({len(subs)} sub-indices, {access})")
        else:
            lines.append(f"0x{index:04X} {obj.name} ({obj.access_type})")
    return tuple(lines)


def _check(f: EdsFile, store: odm.ObjectStore) -> None:
    """Refuse what the twin cannot serve (see the module docstring)."""
    missing = [f"0x{i:04X} {what}" for i, what in REQUIRED.items() if i not in f.od]
    if missing:
        raise UserError(f"{f.path}: a twin needs the CiA 301/402 objects {', '.join(missing)}, "
                        "which the file does not define; give the EDS of a CiA 402 drive")
    for comm in (*store.rpdos, *store.tpdos):
        problem = store.mapping_problem(comm)
        if problem is not None:
            kind = "RPDO" if comm in store.rpdos else "TPDO"
            raise UserError(
                f"{f.path}: {kind}{store.pdo(comm).number}'s mapping 0x{comm + 0x200:04X} "
                f"cannot be served: {problem}; fix the file's default mapping (or leave "
                f"sub-index 0 at 0 for a PDO the master maps itself)")
    period = store.values.get((0x1006, 0), 0)
    try:
        store.check_period(period)
    except SdoAbortedError:
        raise UserError(f"{f.path}: 0x1006 communication cycle period {period} µs is not one "
                        "the twin can run (100 µs … 100 ms, or 0: 1 ms per SYNC); change its "
                        "value in the file") from None


def load_twin(path: str | Path, node_id: int | None = None, f_pwm: float = 10e3) -> Twin:
    """The twin of the drive ``path`` describes at ``node_id`` (None: a DCF's NodeID, else 1);
    :class:`UserError` when the file cannot be read or served."""
    f = read_eds(path, node_id)
    modes, mode_notes = _modes(f)
    dictionary = odm.Dictionary(f.od, own=False, modes=modes, runtime=_runtime(f.node_id))
    store = odm.ObjectStore(f.node_id, dictionary=dictionary, f_pwm=f_pwm)
    _check(f, store)
    _, unit_notes = units_from(store.lookup)
    notes = (*mode_notes, "units: " + "; ".join(unit_notes))
    return Twin(f, dictionary, _storage(f, store), notes)
