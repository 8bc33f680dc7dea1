"""`hil-gateway profile new-drive` for a standard CiA 402 drive: a drive profile and DBC that
run it in its standard modes, from its EDS or DCF alone.

A drive whose file has no vector current or voltage process data cannot run the paper's
laws, but it can follow a reference profile streamed as its target. The mode is the best
its 0x6502 (supported drive modes) offers among those the gateway streams, in this order:
cyclic synchronous velocity (CSV, 9), torque (CST, 10), position (CSP, 8: the speed
profile integrated to position), profile velocity (3), profile torque (4). Without a 0x6502
default the modes are taken from the targets the file has, and the header says so. The
choice is written as ``[modes].default``; the other modes the drive offers are listed.

The PDOs are CiA 301's default ones of the drive's node: RPDO1 the controlword and the
targets of torque (0x6071) and velocity (0x60FF), RPDO2 the target position (0x607A),
TPDO1 the statusword, the torque (0x6077) and velocity (0x606C) actual values — each with
the size the file states. Scalings come from the file (:mod:`dbc.units402`), or from a
vendor DBC (``--dbc``): a signal of it named like the object (or like our signal) gives
its factor; what neither gives is assumed and marked TODO in both files.

Pure: :func:`plan` (file → :class:`StandardPlan` or None), :func:`render_toml`,
:func:`render_dbc`.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import TYPE_CHECKING, Any

from dbc.cia402 import (
    CONTROLWORD,
    STATUSWORD,
    SUPPORTED_DRIVE_MODES_OBJECT,
    TARGET_POSITION,
    TARGET_TORQUE,
    TARGET_VELOCITY,
    TORQUE_ACTUAL,
    VELOCITY_ACTUAL,
    describe_mode,
    modes_in,
)
from dbc.modes import DriveMode
from dbc.units402 import StandardUnits, standard_units

if TYPE_CHECKING:
    from gateway.newdrive import DriveEds

#: The modes the gateway streams, best first: (0x6060 value, drive mode, its target object).
MODE_ORDER: tuple[tuple[int, DriveMode, int], ...] = (
    (9, DriveMode.VELOCITY, TARGET_VELOCITY), (10, DriveMode.TORQUE, TARGET_TORQUE),
    (8, DriveMode.POSITION, TARGET_POSITION), (3, DriveMode.VELOCITY, TARGET_VELOCITY),
    (4, DriveMode.TORQUE, TARGET_TORQUE),
)
#: DBC signal → (object, message, quantity of its unit, role in [signals] or None).
_SIGNALS: dict[str, tuple[int, str, str, str | None]] = {
    "controlword": (CONTROLWORD, "RPDO1", "", None),
    "target_torque": (TARGET_TORQUE, "RPDO1", "torque", None),
    "target_velocity": (TARGET_VELOCITY, "RPDO1", "velocity", None),
    "target_position": (TARGET_POSITION, "RPDO2", "position", None),
    "statusword": (STATUSWORD, "TPDO1", "", None),
    "velocity_actual": (VELOCITY_ACTUAL, "TPDO1", "velocity", "w_m"),
    "torque_actual": (TORQUE_ACTUAL, "TPDO1", "torque", "T_e"),
}
_UNIT_NAMES = {"torque": "N.m", "velocity": "rad/s", "position": "rad", "": ""}
#: COB-ID bases of CiA 301's default PDOs (plus the node id).
_COB_BASE = {"RPDO1": 0x200, "RPDO2": 0x300, "RPDO3": 0x400, "TPDO1": 0x180,
             "TPDO2": 0x280}
#: The drive profile's [pdo] keys a standard drive's messages go in, by direction (rx: the
#: drive receives); ``truth`` stays unused (it names the emulator's true flux).
MESSAGE_SLOTS: dict[bool, tuple[str, ...]] = {True: ("control", "setpoints", "load"),
                                               False: ("currents", "voltages")}
#: CiA 301 integer data types: bits, signed.
_INT = {0x2: (8, True), 0x3: (16, True), 0x4: (32, True), 0x5: (8, False),
        0x6: (16, False), 0x7: (32, False)}


@dataclass(frozen=True)
class Signal:
    """One signal of the DBC: its object, size, scaling and where the scaling came from."""

    name: str
    index: int
    message: str
    bits: int
    signed: bool
    factor: float
    unit: str
    source: str
    todo: bool  #: the scaling is assumed: confirm it


@dataclass(frozen=True)
class StandardPlan:
    """What the skeleton writes for a standard drive."""

    modes: dict[DriveMode, int]  #: drive mode → 0x6060 value, for the modes it streams
    default: DriveMode
    offered: tuple[int, ...]  #: the standard modes its 0x6502 offers (all, for the header)
    from_6502: bool  #: the modes come from a 0x6502 default (else from the objects)
    signals: tuple[Signal, ...]
    units: StandardUnits
    skipped: tuple[str, ...]  #: why an object of the drive's targets was left out

    def messages(self) -> dict[str, list[Signal]]:
        out: dict[str, list[Signal]] = {}
        for s in self.signals:
            out.setdefault(s.message, []).append(s)
        return out


def plan(eds: DriveEds, vendor_dbc: Any = None) -> StandardPlan | None:
    """The standard profile of the drive the file describes; None if it offers no mode the
    gateway streams (or lacks the controlword or statusword)."""
    usable, skipped = _usable(eds)
    if CONTROLWORD not in usable or STATUSWORD not in usable:
        return None
    supported = eds.default(SUPPORTED_DRIVE_MODES_OBJECT)
    from_6502 = isinstance(supported, int)
    offered = tuple(modes_in(supported)) if from_6502 else ()
    modes: dict[DriveMode, int] = {}
    for value, mode, target in MODE_ORDER:
        ok = (value in offered) if from_6502 else value in (9, 10, 8)
        if ok and target in usable and mode not in modes:
            modes[mode] = value
    if not modes:
        return None
    default = next(iter(modes))
    units = standard_units(lambda i, s: _int_or_none(eds.default(i, s)))
    wanted = {TARGET_TORQUE: DriveMode.TORQUE in modes,
              TARGET_VELOCITY: DriveMode.VELOCITY in modes,
              TARGET_POSITION: DriveMode.POSITION in modes}
    default_target = next(t for _, m, t in MODE_ORDER if m is default)
    order = sorted((n for n, (i, _, _, _) in _SIGNALS.items()
                    if i in usable and wanted.get(i, True)),
                   key=lambda n: (_SIGNALS[n][0] != default_target, list(_SIGNALS).index(n)))
    signals = []
    for name, message in _layout(eds, order, usable, skipped).items():
        index, _, quantity, _ = _SIGNALS[name]
        bits, signed = usable[index]
        factor, unit, source, todo = _scaling(name, quantity, eds, units, vendor_dbc)
        signals.append(Signal(name, index, message, bits, signed, factor, unit, source, todo))
    signals.sort(key=lambda s: (s.message, list(_SIGNALS).index(s.name)))
    return StandardPlan(modes, default, offered, from_6502, tuple(signals), units,
                        tuple(skipped))


def _capacity(eds: DriveEds, rx: bool) -> list[int]:
    """Entries each of the drive's RPDOs (``rx``) or TPDOs can map, in order: its mapping
    record's sub-indices (CiA 301's defaults, 4 PDOs of 8 entries, where the file
    describes none). At most the :data:`MESSAGE_SLOTS` the profile names."""
    base = 0x1600 if rx else 0x1A00
    out = []
    for n in range(len(MESSAGE_SLOTS[rx])):
        entries = sum(1 for (i, s) in eds.objects if i == base + n and s > 0)
        if not eds.has(base + n):
            break
        out.append(entries)
    return out or [8] * len(MESSAGE_SLOTS[rx])


def _layout(eds: DriveEds, order: list[str], usable: dict[int, tuple[int, bool]],
            skipped: list[str]) -> dict[str, str]:
    """Signal → message: in ``order`` (the controlword or statusword, the default mode's
    target first), each into the first PDO of its direction with a free entry and room
    in its 64 bits; what fits nowhere is named in ``skipped``."""
    out: dict[str, str] = {}
    for rx in (True, False):
        caps = _capacity(eds, rx)
        used = [[0, 0] for _ in caps]  # entries, bits
        for name in order:
            if _SIGNALS[name][1].startswith("RPDO") != rx:
                continue
            bits = usable[_SIGNALS[name][0]][0]
            for n, cap in enumerate(caps):
                if used[n][0] < cap and used[n][1] + bits <= 64:
                    used[n][0] += 1
                    used[n][1] += bits
                    out[name] = f"{'R' if rx else 'T'}PDO{n + 1}"
                    break
            else:
                skipped.append(f"{name} (0x{_SIGNALS[name][0]:04X}): no room in the drive's "
                               f"{'R' if rx else 'T'}PDOs ({caps} entries)")
    return out


def _int_or_none(value: Any) -> int | None:
    return value if isinstance(value, int) and not isinstance(value, bool) else None


def _usable(eds: DriveEds) -> tuple[dict[int, tuple[int, bool]], list[str]]:
    """The standard objects the file has as PDO-mappable integers: index → (bits, signed);
    and why the others of them cannot be used."""
    usable: dict[int, tuple[int, bool]] = {}
    skipped = []
    for index, _, _, _ in _SIGNALS.values():
        o = eds.objects.get((index, 0))
        if o is None:
            continue
        if not o.pdo:
            skipped.append(f"0x{index:04X} {o.name}: not PDO-mappable in the file")
        elif o.dtype not in _INT:
            skipped.append(f"0x{index:04X} {o.name}: {o.type_name}, not an integer")
        else:
            usable[index] = _INT[o.dtype]
    return usable, skipped


def _scaling(name: str, quantity: str, eds: DriveEds, units: StandardUnits,
             vendor_dbc: Any) -> tuple[float, str, str, bool]:
    """(factor, unit, source, assumed) of one signal: the vendor DBC's, else the file's."""
    if not quantity:
        return 1.0, "", "bit field", False
    if vendor_dbc is not None:
        found = vendor_signal(vendor_dbc, name, eds.objects[(_SIGNALS[name][0], 0)].name)
        if found is not None:
            return found
    factor = {"torque": units.torque, "velocity": units.velocity,
              "position": units.position}[quantity]
    return (factor, _UNIT_NAMES[quantity], units.sources[quantity],
            quantity in units.assumed)


def vendor_signal(db: Any, *names: str) -> tuple[float, str, str, bool] | None:
    """The factor and unit of the vendor DBC's signal named like one of ``names``
    (compared without case and punctuation), as (factor, unit, source, False); None if
    it has none."""
    from gateway.newdrive import normalize

    want = {normalize(n) for n in names}
    for m in db.messages:
        for s in m.signals:
            if normalize(s.name) in want:
                return (float(s.scale), s.unit or "", f"vendor DBC {m.name}.{s.name}", False)
    return None


# ---- the files ----------------------------------------------------------------------------


def render_toml(eds: DriveEds, p: StandardPlan, *, node: int, eds_ref: str, dbc_ref: str,
                common: tuple[list[str], list[str]]) -> str:
    """The drive profile: header, [drive], [modes], [pdo], then ``common`` ([timing],
    [limits] of the vector skeleton), [signals] and [objects]."""
    from gateway.newdrive import _toml_str

    name = eds.product or eds.path.stem
    lines = [*_header(eds, p, name), "", "[drive]", f"name = {_toml_str(name)}",
             f"eds = {_toml_str(eds_ref)}", f"dbc = {_toml_str(dbc_ref)}"
             "              # written next to this file", f"node = {node}"]
    dt = eds.default(0x1000)
    lines.append(f"device_type = 0x{dt:08X}       # 0x1000 default of the file"
                 if isinstance(dt, int) else
                 "# device_type = 0x00020192     # the file gives no 0x1000 default")
    lines += ["", "[modes]                           # 0x6060 values"]
    lines += [f"{mode.value} = {value}".ljust(34) + f"# {describe_mode(value)}"
              for mode, value in p.modes.items()]
    lines.append(f'default = "{p.default.value}"'.ljust(34)
                 + "# the drive mode of a run without --drive-mode")
    msgs = p.messages()
    lines += ["", "[pdo]                             # CiA 301 default PDOs of the node"]
    for rx in (True, False):
        names = sorted(m for m in msgs if m.startswith("RPDO" if rx else "TPDO"))
        for key, message in zip(MESSAGE_SLOTS[rx], names, strict=False):
            what = ", ".join(s.name for s in msgs[message])
            lines.append(f'{key} = "{message}"'.ljust(34) + f"# {what}")
    lines.append("remap = true                      # write the PDO mappings by SDO")
    timing, limits = common
    lines += [*timing, *limits, "", "[signals]                         # role = "
              "\"MESSAGE.signal\""]
    lines += [f'{role} = "{s.message}.{s.name}"' for s in p.signals
              if (role := _SIGNALS[s.name][3]) is not None]
    lines += ["", "[objects]                         # the object each DBC signal maps"]
    lines += [f'"{s.message}.{s.name}" = "0x{s.index:04X}.0"' for s in p.signals]
    return "\n".join([*lines, ""])


def _header(eds: DriveEds, p: StandardPlan, name: str) -> list[str]:
    vendor = f" ({eds.vendor})" if eds.vendor else ""
    chosen = p.modes[p.default]
    others = [f"--drive-mode {m.value} ({describe_mode(v)})" for m, v in p.modes.items()
              if m is not p.default]
    lines = [f"# Drive profile for {name}{vendor}, a standard CiA 402 drive,",
             f"# written by `hil-gateway profile new-drive` from {eds.path.name}.",
             "# Its file has no vector current or voltage process data, so the paper's laws",
             "# cannot run on it; it follows a reference profile streamed as its target",
             "# (--controller stream, the default with this profile) or a speed PI over its",
             "# torque (--controller speed-pi --drive-mode torque).",
             f"# Mode: {describe_mode(chosen)}, the best the drive offers"
             + ("" if p.from_6502 else " (the file has no 0x6502 default: modes taken from "
                "its targets; confirm them)") + "."]
    if others:
        lines.append("# Also: " + "; ".join(others) + ".")
    if p.offered:
        lines.append("# Its 0x6502 offers: " + ", ".join(describe_mode(m) for m in p.offered)
                     + ".")
    lines.append("# Units (the DBC's factors):")
    lines += [f"#   {s.name}: {s.factor:.9g} {s.unit} per unit ({s.source})"
              + ("  TODO: confirm" if s.todo else "") for s in p.signals if s.unit]
    todo = sorted({q for s in p.signals if s.todo for q in [_SIGNALS[s.name][2]]})
    if todo:
        lines.append(f"# TODO: the file does not state the {', '.join(todo)} unit: find it in "
                     "the manual and correct the factors in the DBC next to this file.")
    lines += [f"# Left out: {why}." for why in p.skipped]
    return lines


def render_dbc(eds: DriveEds, p: StandardPlan, node: int) -> str:
    """The DBC: the profile's PDOs with the COB-IDs of ``node``, factors and units."""
    out = ['VERSION ""', "", "", "NS_ :", "\tCM_", "\tBA_DEF_", "\tBA_", "\tVAL_", "",
           "BS_:", "", "BU_: GATEWAY DRIVE", "", ""]
    comments = [f'CM_ "Standard CiA 402 drive profile from {eds.path.name} (hil-gateway '
                f'profile new-drive); COB-IDs of the CiA 301 default PDOs for node {node}.";']
    for message, sigs in p.messages().items():
        fid = _COB_BASE[message] + node
        rx = message.startswith("RPDO")
        sender, receiver = ("GATEWAY", "DRIVE") if rx else ("DRIVE", "GATEWAY")
        out.append(f"BO_ {fid} {message}: {sum(s.bits for s in sigs) // 8} {sender}")
        bit = 0
        for s in sigs:
            lo = -(1 << (s.bits - 1)) if s.signed else 0
            hi = (1 << (s.bits - 1)) - 1 if s.signed else (1 << s.bits) - 1
            out.append(f" SG_ {s.name} : {bit}|{s.bits}@1{'-' if s.signed else '+'} "
                       f"({s.factor!r},0) [{lo * s.factor:.12g}|{hi * s.factor:.12g}] "
                       f'"{s.unit}" {receiver}')
            o = eds.objects[(s.index, 0)]
            note = (f"0x{s.index:04X} {o.name} ({o.type_name}); {s.source}"
                    + ("; TODO: confirm the unit" if s.todo else "")).replace(
                '"', "'").replace("·", ".")  # DBC files are ASCII
            comments.append(f'CM_ SG_ {fid} {s.name} "{note}";')
            bit += s.bits
        out.append("")
    return "\n".join([*out, "", *comments, ""])


__all__ = ["MODE_ORDER", "Signal", "StandardPlan", "plan", "render_dbc", "render_toml",
           "vendor_signal"]
