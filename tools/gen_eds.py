"""Generate ``dbc/drive.eds`` (CiA 306) from the table below and the PDO frames of ``drive.dbc``.

Run ``python tools/gen_eds.py`` after changing either; ``tests/test_contract.py`` checks that
the committed EDS and the DBC agree. The PDO signal objects take their data type from
the DBC signal (bits, signedness) and their ParameterName from the signal name; the
default PDO mappings are the DBC messages (``RPDO2_AB``, from the (a, b) companion
``drive_ab.dbc``, is the alternative of RPDO2 and is not a default). Parameter defaults are
those of :mod:`dbc.motor` and :mod:`plant.params`. This is a development tool, not part of
the installed packages.

The text keeps to CiA 306 so that other EDS readers load it (``tests/test_eds.py``: python-
canopen, objdictgen, eds-utils, and a lint): nothing before [FileInfo], only CiA 306 keys
(descriptions and units go to [Comments]), no '=' inside a value, limits as integers (the
REAL32 ranges live in :data:`plant.od.REAL32_LIMITS`; only their integral bounds are written).
"""

from __future__ import annotations

import sys
from dataclasses import dataclass, field
from pathlib import Path

from dbc.codec import _parse_dbc

BOOLEAN, INTEGER8, INTEGER16, INTEGER32 = 0x1, 0x2, 0x3, 0x4
UNSIGNED8, UNSIGNED16, UNSIGNED32, REAL32, VISIBLE_STRING = 0x5, 0x6, 0x7, 0x8, 0x9
VAR, ARRAY, RECORD = 0x7, 0x8, 0x9

#: Object index of each PDO signal (ParameterName = DBC signal name).
SIGNAL_INDEX: dict[str, int] = {
    "controlword": 0x6040, "statusword": 0x6041,
    "eps_0": 0x2001, "w_0": 0x2002,
    "i_sd_ref": 0x2010, "i_sq_ref": 0x2011, "u_sd_ref": 0x2012, "u_sq_ref": 0x2013,
    "i_sa_ref": 0x2014, "i_sb_ref": 0x2015, "u_sa_ref": 0x2016, "u_sb_ref": 0x2017,
    "T_L": 0x2020,
    "i_sa": 0x2100, "i_sb": 0x2101, "sync_counter": 0x2102,
    "u_sa": 0x2110, "u_sb": 0x2111, "u_dc": 0x2112,
    "w_m": 0x2120, "psi_ra": 0x2121, "psi_rb": 0x2122, "T_e": 0x2123,
}
#: PDO number (1..3) of each default message.
RPDOS = {"RPDO1": 1, "RPDO2": 2, "RPDO3": 3}
TPDOS = {"TPDO1": 1, "TPDO2": 2, "TPDO3": 3}


@dataclass
class Var:
    """One EDS variable (a VAR object or a sub-index)."""

    name: str
    dtype: int
    access: str
    default: str | None = None
    pdo: bool = False
    low: str | None = None
    high: str | None = None
    desc: str | None = None


@dataclass
class Obj:
    """One object: a VAR, or an ARRAY/RECORD with sub-indices."""

    index: int
    name: str
    otype: int = VAR
    var: Var | None = None
    subs: dict[int, Var] = field(default_factory=dict)


def _f(x: float) -> str:
    return repr(float(x))


def _real32_limits(objs: list[Obj]) -> None:
    """LowLimit/HighLimit of the REAL32 parameters from :data:`plant.od.REAL32_LIMITS`.

    Only integral bounds go into the EDS, written as integers: objdictgen refuses a
    non-integer limit and python-canopen parses limits with ``int(x, 0)``. Every range is
    listed in [Comments] (see :func:`_comments`)."""
    from plant.od import REAL32_LIMITS

    for o in objs:
        for sub, v in o.subs.items():
            rng = REAL32_LIMITS.get((o.index, sub))
            if v.dtype != REAL32 or rng is None:
                continue
            v.low, v.high = (str(int(x)) if float(x).is_integer() else None for x in rng)


def _objects() -> list[Obj]:
    from dbc.cia402 import SUPPORTED_DRIVE_MODES
    from dbc.motor import MotorParams
    from plant.params import DriveParams
    from plant.profile import DEFAULTS
    from plant.servo import T_RATED, ServoParams
    from plant.units import EMULATOR

    messages, specs = _parse_dbc()
    m, d, sv = MotorParams(), DriveParams(), ServoParams()
    objs: list[Obj] = []

    def var(index: int, name: str, dtype: int, access: str, default: str | None = None,
            **kw) -> None:
        objs.append(Obj(index, name, VAR, Var(name, dtype, access, default, **kw)))

    def rec(index: int, name: str, otype: int, subs: dict[int, Var]) -> None:
        objs.append(Obj(index, name, otype, subs=subs))

    # ---- communication profile (CiA 301) ----
    var(0x1000, "Device type", UNSIGNED32, "ro", "0x00010192",
        desc="CiA 402 drive, frequency converter")
    var(0x1001, "Error register", UNSIGNED8, "ro", "0x00")
    rec(0x1003, "Pre-defined error field", ARRAY, {
        0: Var("Number of errors", UNSIGNED8, "rw", "0", high="0",
               desc="write 0 to clear the history"),
        **{k: Var(f"Standard error field {k}", UNSIGNED32, "ro", "0") for k in range(1, 9)},
    })
    var(0x1005, "COB-ID SYNC", UNSIGNED32, "rw", "0x00000080")
    var(0x1006, "Communication cycle period", UNSIGNED32, "rw", "1000", low="100",
        high="1000000", desc="us; the simulation advances this much per SYNC")
    var(0x1007, "Synchronous window length", UNSIGNED32, "rw", "0", desc="us (not enforced)")
    var(0x1008, "Manufacturer device name", VISIBLE_STRING, "const", "can-drive-hil emulator")
    var(0x1014, "COB-ID EMCY", UNSIGNED32, "rw", "$NODEID+0x80")
    rec(0x1016, "Consumer heartbeat time", ARRAY, {
        0: Var("Highest sub-index supported", UNSIGNED8, "ro", "1"),
        1: Var("Consumer heartbeat time 1", UNSIGNED32, "rw", "0",
               desc="bits 16-23 node id, bits 0-15 time in ms (0: off)"),
    })
    var(0x1017, "Producer heartbeat time", UNSIGNED16, "rw", "100", desc="ms (0: off)")
    rec(0x1018, "Identity object", RECORD, {
        0: Var("Highest sub-index supported", UNSIGNED8, "ro", "4"),
        1: Var("Vendor-ID", UNSIGNED32, "ro", "0x00000000"),
        2: Var("Product code", UNSIGNED32, "ro", "0x00000402"),
        3: Var("Revision number", UNSIGNED32, "ro", "0x00010000"),
        4: Var("Serial number", UNSIGNED32, "ro", "0x00000001"),
    })
    var(0x1019, "Synchronous counter overflow value", UNSIGNED8, "rw", "0", high="240",
        desc="0: SYNC without counter, else 2..240")

    for msg, n in RPDOS.items():
        cob = messages[msg].frame_id - 1
        rec(0x1400 + n - 1, f"RPDO{n} communication parameter", RECORD, {
            0: Var("Highest sub-index supported", UNSIGNED8, "ro", "5"),
            1: Var("COB-ID used by RPDO", UNSIGNED32, "rw", f"$NODEID+0x{cob:X}"),
            2: Var("Transmission type", UNSIGNED8, "rw", "1",
                   desc="0..240 synchronous; applied per 0x2203"),
            5: Var("Event timer", UNSIGNED16, "rw", "0",
                   desc="ms; RPDO deadline monitoring (0: off), EMCY 0x8250"),
        })
    for msg, n in TPDOS.items():
        cob = messages[msg].frame_id - 1
        rec(0x1800 + n - 1, f"TPDO{n} communication parameter", RECORD, {
            0: Var("Highest sub-index supported", UNSIGNED8, "ro", "6"),
            1: Var("COB-ID used by TPDO", UNSIGNED32, "rw", f"$NODEID+0x{0x40000000 | cob:X}"),
            2: Var("Transmission type", UNSIGNED8, "rw", "1", low="1", high="240",
                   desc="n: every n-th SYNC"),
            3: Var("Inhibit time", UNSIGNED16, "rw", "0", desc="100 us (unused)"),
            5: Var("Event timer", UNSIGNED16, "rw", "0", desc="ms (unused, synchronous only)"),
            6: Var("SYNC start value", UNSIGNED8, "rw", "0"),
        })
    for msgs, base in ((RPDOS, 0x1600), (TPDOS, 0x1A00)):
        for msg, n in msgs.items():
            sigs = messages[msg].signals
            subs = {0: Var("Number of mapped objects", UNSIGNED8, "rw", str(len(sigs)),
                           high="8")}
            for k in range(1, 9):
                entry = 0
                if k <= len(sigs):
                    s = sigs[k - 1]
                    entry = SIGNAL_INDEX[s.name] << 16 | s.bits
                subs[k] = Var(f"Mapped object {k}", UNSIGNED32, "rw", f"0x{entry:08X}")
            kind = "RPDO" if base == 0x1600 else "TPDO"
            rec(base + n - 1, f"{kind}{n} mapping parameter", RECORD, subs)

    # ---- PDO signals (raw integers in the units of drive.dbc) ----
    tx_signals = {s.name for msg in TPDOS for s in messages[msg].signals}
    dtypes = {(8, False): UNSIGNED8, (16, False): UNSIGNED16, (16, True): INTEGER16}
    for name, index in sorted(SIGNAL_INDEX.items(), key=lambda kv: kv[1]):
        if index >= 0x6000:
            continue
        s = specs[name]
        ro = name in tx_signals
        var(index, name, dtypes[(s.bits, s.signed)], "ro" if ro else "rw", "0", pdo=True,
            desc=f"{'TPDO' if ro else 'RPDO'} signal, raw; scaling in drive.dbc")

    # ---- emulator parameters (writable in PRE-OPERATIONAL only) ----
    rec(0x2200, "Motor parameters", RECORD, {
        0: Var("Highest sub-index supported", UNSIGNED8, "ro", "6"),
        1: Var("J", REAL32, "rw", _f(m.J), desc="kg.m^2"),
        2: Var("R_s", REAL32, "rw", _f(m.R_s), desc="Ohm"),
        3: Var("R_r", REAL32, "rw", _f(m.R_r), desc="Ohm"),
        4: Var("L_s", REAL32, "rw", _f(m.L_s), desc="H"),
        5: Var("L_r", REAL32, "rw", _f(m.L_r), desc="H"),
        6: Var("M", REAL32, "rw", _f(m.M), desc="H, M^2 < L_s*L_r"),
    })
    rec(0x2201, "Drive parameters", RECORD, {
        0: Var("Highest sub-index supported", UNSIGNED8, "ro", "9"),
        1: Var("u_dc", REAL32, "rw", _f(d.u_dc), desc="V"),
        2: Var("i_trip", REAL32, "rw", _f(d.i_trip),
               desc="A, over-current trip of |i_s|, EMCY 0x2310"),
        3: Var("current_loop_bw", REAL32, "rw", _f(d.current_loop_bw),
               desc="rad/s, below pi*f_pwm"),
        4: Var("i_offset_a", REAL32, "rw", _f(d.i_offset_ab.real),
               desc="A, current-sensor offset"),
        5: Var("i_offset_b", REAL32, "rw", _f(d.i_offset_ab.imag),
               desc="A, current-sensor offset"),
        6: Var("i_gain_error", REAL32, "rw", _f(d.i_gain_error),
               desc="relative current-sensor gain error"),
        7: Var("i_noise_rms", REAL32, "rw", _f(d.i_noise_rms),
               desc="A rms per axis"),
        8: Var("f_pwm", UNSIGNED32, "rw", str(round(d.f_pwm)), low="1000", high="100000",
               desc="Hz, internal (PWM/current-loop) rate; 0x1006 must be a multiple of 1/f_pwm"),
        9: Var("w_max", REAL32, "rw", _f(d.w_max),
               desc="rad/s, over-speed limit of |w_m|, EMCY 0x8400"),
    })
    var(0x2202, "Emulator model", UNSIGNED8, "rw", "1", high="1",
        desc="current vector mode: 0 ideal current source, 1 PI current loop")
    var(0x2203, "RPDO apply", UNSIGNED8, "rw", "0", high="1",
        desc="0 at the next SYNC (delay 1), 1 on receipt (delay 0)")
    var(0x2204, "Noise seed", UNSIGNED32, "rw", str(d.seed))
    var(0x2205, "Time base", UNSIGNED8, "rw", "0", high="1",
        desc="supervision time: 0 wall clock, 1 SYNC (lockstep: simulated time)")
    rec(0x2300, "Account", RECORD, {
        0: Var("Highest sub-index supported", UNSIGNED8, "ro", "3"),
        1: Var("cycles", UNSIGNED32, "ro", "0", desc="SYNC cycles simulated"),
        2: Var("sync_gaps", UNSIGNED32, "ro", "0", desc="SYNC counter discontinuities"),
        3: Var("fault_count", UNSIGNED32, "ro", "0", desc="EMCY faults raised"),
    })
    var(0x2301, "Account clear", UNSIGNED8, "wo", "0", desc="write any value to clear 0x2300")

    # ---- device profile (CiA 402) ----
    var(0x603F, "Error code", UNSIGNED16, "ro", "0", desc="last EMCY error code")
    var(0x6040, "controlword", UNSIGNED16, "rw", "0", pdo=True, desc="CiA 402 controlword")
    var(0x6041, "statusword", UNSIGNED16, "ro", "0", pdo=True, desc="CiA 402 statusword")
    var(0x6060, "Modes of operation", INTEGER8, "rw", "-1", low="-2", high="10",
        desc="-1 current vector, -2 voltage vector (manufacturer-specific), 3 profile "
             "velocity, 4 profile torque, 8 cyclic synchronous position, 9 cyclic synchronous "
             "velocity, 10 cyclic synchronous torque")
    var(0x6061, "Modes of operation display", INTEGER8, "ro", "-1")
    var(0x6064, "Position actual value", INTEGER32, "ro", "0", pdo=True,
        desc="1/65536 revolution (the encoder, counted in the standard modes)")
    var(0x606B, "Velocity demand value", INTEGER32, "ro", "0", pdo=True,
        desc="0.001 rev/min (profile velocity: the ramp's output)")
    var(0x606C, "Velocity actual value", INTEGER32, "ro", "0", pdo=True,
        desc="0.001 rev/min (the encoder)")
    var(0x606D, "Velocity window", UNSIGNED16, "rw", str(round(DEFAULTS.window
                                                                / EMULATOR.velocity)),
        desc="0.001 rev/min; profile velocity: target reached (statusword bit 10)")
    var(0x606E, "Velocity window time", UNSIGNED16, "rw",
        str(round(DEFAULTS.window_time * 1000)), desc="ms")
    var(0x606F, "Velocity threshold", UNSIGNED16, "rw", str(round(DEFAULTS.threshold
                                                                   / EMULATOR.velocity)),
        desc="0.001 rev/min; profile velocity: speed zero (statusword bit 12)")
    var(0x6070, "Velocity threshold time", UNSIGNED16, "rw",
        str(round(DEFAULTS.threshold_time * 1000)), desc="ms")
    var(0x6071, "Target torque", INTEGER16, "rw", "0", pdo=True,
        desc="per mille of the motor rated torque 0x6076 (CST, profile torque)")
    var(0x6072, "Max torque", UNSIGNED16, "rw", str(round(1000 * sv.T_max / T_RATED)),
        low="1", high="32767", desc="per mille of the motor rated torque 0x6076")
    var(0x6074, "Torque demand", INTEGER16, "ro", "0", pdo=True,
        desc="per mille of the motor rated torque 0x6076 (profile torque: the ramp's output)")
    var(0x6076, "Motor rated torque", UNSIGNED32, "ro", str(round(1000 * T_RATED)),
        desc="mN.m")
    var(0x6077, "Torque actual value", INTEGER16, "ro", "0", pdo=True,
        desc="per mille of the motor rated torque 0x6076")
    var(0x6079, "DC link circuit voltage", UNSIGNED32, "ro", str(round(d.u_dc * 1000)),
        desc="mV")
    var(0x607A, "Target position", INTEGER32, "rw", "0", pdo=True,
        desc="1/65536 revolution (CSP)")
    for index, name in ((0x6083, "Profile acceleration"), (0x6084, "Profile deceleration")):
        si = DEFAULTS.acceleration if index == 0x6083 else DEFAULTS.deceleration
        var(index, name, UNSIGNED32, "rw", str(round(si / EMULATOR.acceleration)), low="1",
            pdo=True, desc="0.001 rev/min per second (profile velocity)")
    var(0x6087, "Torque slope", UNSIGNED32, "rw",
        str(round(DEFAULTS.torque_slope / EMULATOR.torque)), low="1", pdo=True,
        desc="per mille of the motor rated torque 0x6076 per second (profile torque)")
    var(0x6088, "Torque profile type", INTEGER16, "rw", "0", low="0", high="0",
        desc="0: linear ramp (the only one)")
    var(0x60A9, "SI unit velocity", UNSIGNED32, "ro", "0xFDB44700",
        desc="0.001 rev/min (CiA 402 coding: power of ten -3, revolution 0xB4, minute 0x47)")
    var(0x60FF, "Target velocity", INTEGER32, "rw", "0", pdo=True,
        desc="0.001 rev/min (CSV, profile velocity)")
    var(0x6502, "Supported drive modes", UNSIGNED32, "ro", f"0x{SUPPORTED_DRIVE_MODES:08X}",
        desc="bit 2: 3 profile velocity, bit 3: 4 profile torque, bit 7: 8 CSP, bit 8: 9 CSV, "
             "bit 9: 10 CST, bit 16: -1 current vector, bit 17: -2 voltage vector")
    _real32_limits(objs)
    return sorted(objs, key=lambda o: o.index)


def _var_lines(v: Var, otype: int = VAR) -> list[str]:
    lines = [f"ParameterName={v.name}", f"ObjectType=0x{otype:X}", f"DataType=0x{v.dtype:04X}",
             f"AccessType={v.access}"]
    if v.default is not None:
        lines.append(f"DefaultValue={v.default}")
    if v.low is not None:
        lines.append(f"LowLimit={v.low}")
    if v.high is not None:
        lines.append(f"HighLimit={v.high}")
    lines.append(f"PDOMapping={int(v.pdo)}")
    return lines


def _comments(objs: list[Obj]) -> list[str]:
    """The [Comments] lines: provenance, then the unit or meaning of objects and the ranges of
    the REAL32 parameters (CiA 306 has no per-object description key)."""
    from plant.od import REAL32_LIMITS

    lines = ["Generated by python tools/gen_eds.py from tools/gen_eds.py and dbc/drive.dbc;"
             " do not edit by hand.",
             "PDO signal objects 2001h..2123h hold raw integers; scalings in dbc/drive.dbc."]
    for o in objs:
        items = [(0, o.var)] if o.var is not None else list(o.subs.items())
        for sub, v in items:
            assert v is not None
            notes = [v.desc] if v.desc else []
            rng = REAL32_LIMITS.get((o.index, sub))
            if rng is not None:
                notes.append(f"range {rng[0]:g}..{rng[1]:g}")
            if notes:
                # not "0x..." first: objdictgen reads such a value as a number
                where = f"{o.index:04X}h" + (f" sub {sub}" if o.var is None else "")
                lines.append(f"{where} {v.name}: {'; '.join(notes)}")
    return lines


#: [FileInfo] dates (CiA 306: hh:mm(AM|PM), mm-dd-yyyy). Bump FileRevision and the
#: modification date when the generated dictionary changes.
FILE_VERSION, FILE_REVISION = 1, 2
CREATED = ("10:00AM", "11-01-2026")
MODIFIED = ("10:00AM", "11-24-2026")


def render() -> str:
    """The EDS text (CiA 306: no text before [FileInfo], only CiA 306 keys, no '=' in values,
    sections separated by one empty line)."""
    objs = _objects()
    groups = {
        "MandatoryObjects": [o for o in objs if o.index in (0x1000, 0x1001, 0x1018)],
        "OptionalObjects": [o for o in objs if o.index < 0x2000 or o.index >= 0x6000
                            if o.index not in (0x1000, 0x1001, 0x1018)],
        "ManufacturerObjects": [o for o in objs if 0x2000 <= o.index < 0x6000],
    }
    nr_rx = sum(1 for o in objs if 0x1400 <= o.index < 0x1600)
    nr_tx = sum(1 for o in objs if 0x1800 <= o.index < 0x1A00)
    sections: list[tuple[str, list[str]]] = [
        ("FileInfo", [
            "FileName=drive.eds", f"FileVersion={FILE_VERSION}", f"FileRevision={FILE_REVISION}",
            "EDSVersion=4.0",
            "Description=can-drive-hil CiA 402 drive emulator (induction motor)",
            f"CreationTime={CREATED[0]}", f"CreationDate={CREATED[1]}",
            "CreatedBy=can-drive-hil tools/gen_eds.py",
            f"ModificationTime={MODIFIED[0]}", f"ModificationDate={MODIFIED[1]}",
            "ModifiedBy=can-drive-hil tools/gen_eds.py"]),
        ("DeviceInfo", [
            "VendorName=can-drive-hil", "VendorNumber=0x00000000",
            "ProductName=can-drive-hil emulator", "ProductNumber=0x00000402",
            "RevisionNumber=0x00010000", "OrderCode=can-drive-hil-emulator",
            *(f"BaudRate_{k}=1" for k in (10, 20, 50, 125, 250, 500, 800, 1000)),
            "SimpleBootUpMaster=0", "SimpleBootUpSlave=1", "Granularity=8",
            "DynamicChannelsSupported=0", "GroupMessaging=0", f"NrOfRXPDO={nr_rx}",
            f"NrOfTXPDO={nr_tx}", "LSS_Supported=0"]),
        ("DummyUsage", [f"Dummy000{k}=0" for k in range(1, 8)]),
    ]
    comments = _comments(objs)
    sections.append(("Comments", [f"Lines={len(comments)}",
                                  *(f"Line{k}={c}" for k, c in enumerate(comments, 1))]))
    for group, members in groups.items():
        sections.append((group, [f"SupportedObjects={len(members)}",
                                 *(f"{k}=0x{o.index:04X}" for k, o in enumerate(members, 1))]))
    for o in objs:
        if o.otype == VAR:
            assert o.var is not None
            sections.append((f"{o.index:04X}", _var_lines(o.var)))
            continue
        sections.append((f"{o.index:04X}", [
            f"ParameterName={o.name}", f"ObjectType=0x{o.otype:X}",
            f"SubNumber={len(o.subs)}"]))
        for sub, v in o.subs.items():
            sections.append((f"{o.index:04X}sub{sub:X}", _var_lines(v)))
    out: list[str] = []
    for name, lines in sections:
        for line in lines:  # eds-utils splits each line at every '='
            if line.count("=") != 1:
                raise ValueError(f"[{name}] {line!r}: a value must not contain '='")
        out += [f"[{name}]", *lines, ""]
    return "\n".join(out)


def main(argv: list[str] | None = None) -> int:
    """Write dbc/drive.eds (or the path given)."""
    args = sys.argv[1:] if argv is None else argv
    from dbc import EDS_PATH

    path = Path(args[0]) if args else EDS_PATH
    path.write_text(render(), encoding="ascii")
    print(f"wrote {path}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
