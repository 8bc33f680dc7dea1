"""`hil-gateway profile new-drive`: a drive-profile skeleton from a drive's EDS/DCF.

The first step on a new inverter. For each process-data role the gateway uses (the signal
names of ``dbc/drive.dbc``) the drive's objects are ranked by

1. exact CiA 402 index (0x6040 controlword, 0x6041 statusword, 0x6079 DC link voltage),
2. presence in a default PDO mapping of the right direction (0x16xx for gateway→drive,
   0x1Axx for drive→gateway),
3. ParameterName tokens ("phase current a", "i_alpha", "dc link", "voltage alpha", ...),
4. access right (rw/rww/wo for gateway→drive, ro/rwr/rw for drive→gateway), integer type,
   manufacturer range where the role is manufacturer-specific;

only PDO-mappable objects of an integer type of 8, 16 or 32 bits can carry a role (the
gateway's codec takes byte-aligned integers). The skeleton lists up to 3 candidates per role
as comments, takes the best for the ``[signals]`` table and writes a DBC skeleton whose
messages carry the chosen objects with their sizes (scalings 1: confirm the drive's units).

A drive with only standard CiA 402 process data (0x6071 target torque, 0x6077 torque actual,
0x6078 current actual, 0x6079 DC link, mode 10 cyclic synchronous torque) cannot run these
laws; the skeleton's header says so and what to look for.

Pure functions: :func:`read_eds` (file → :class:`DriveEds`), :func:`choose` (→ candidates
and choices), :func:`render_toml`, :func:`render_dbc`; :func:`add_action` registers the CLI
action on the `reference`/`profile` subcommand.
"""

from __future__ import annotations

import argparse
import os
import re
import textwrap
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from dbc.cia402 import describe_mode
from gateway.errors import UserError

RX, TX = "rx", "tx"  # gateway→drive (RPDO of the drive), drive→gateway (TPDO)

#: CiA 301 data types usable by the gateway's codec: (name, bits, signed).
INT_TYPES: dict[int, tuple[str, int, bool]] = {
    0x2: ("INTEGER8", 8, True), 0x3: ("INTEGER16", 16, True), 0x4: ("INTEGER32", 32, True),
    0x5: ("UNSIGNED8", 8, False), 0x6: ("UNSIGNED16", 16, False),
    0x7: ("UNSIGNED32", 32, False),
}
TYPE_NAMES: dict[int, str] = {
    0x1: "BOOLEAN", **{k: v[0] for k, v in INT_TYPES.items()}, 0x8: "REAL32",
    0x9: "VISIBLE_STRING", 0xA: "OCTET_STRING", 0xB: "UNICODE_STRING", 0xF: "DOMAIN",
    0x10: "INTEGER24", 0x11: "REAL64", 0x15: "INTEGER64", 0x16: "UNSIGNED24",
    0x1B: "UNSIGNED64",
}
_REF_WORDS = r"\b(ref|reference|setpoint|set point|target|demand|command|cmd|set)\b"


@dataclass(frozen=True)
class Role:
    """One process-data signal of ``dbc/drive.dbc`` the gateway exchanges with the drive."""

    name: str
    direction: str  #: RX or TX
    message: str  #: proposed DBC message
    what: str  #: what the object carries (for "none found")
    std: tuple[int, ...] = ()  #: exact CiA 402 indices
    patterns: tuple[tuple[str, int], ...] = ()  #: (regex on the normalized name, weight)
    required: bool = True
    manufacturer: bool = True  #: normally a manufacturer-specific object (0x2000..0x5FFF)
    note: dict[str, str] = field(default_factory=dict)  #: pattern → remark on a match


def _vector(sym: str, word: str, axes: tuple[str, ...], phase: str | None = None,
            phase_weight: int = 25) -> tuple[tuple[str, int], ...]:
    """Name patterns of one vector component (i/u, current/voltage, axis spellings)."""
    out: list[tuple[str, int]] = []
    syms = "(i)" if sym == "i" else "(u|v)"
    for ax in axes:
        out += [(rf"\b{syms} ?s? ?{ax}\b", 40), (rf"\b{word} {ax}\b", 35),
                (rf"\b{ax} {word}\b", 35), (rf"\b{ax} axis {word}\b", 35),
                (rf"\bstator {word} {ax}\b", 35)]
    if phase:
        out += [(rf"\bphase {word} {phase}\b", phase_weight),
                (rf"\b{word} phase {phase}\b", phase_weight),
                (rf"\bphase {phase} {word}\b", phase_weight),
                (rf"\boutput {word} {phase}\b", phase_weight)]
    return tuple(out)


_BETA_NOTE = ("phase b, not beta: the gateway needs the beta component, "
              "x_beta = (x_a + 2 x_b)/sqrt(3) for a star without neutral")
_ALPHA_NOTE = "phase a equals alpha (amplitude-invariant Clarke): confirm"


def _roles() -> tuple[Role, ...]:
    r: list[Role] = [
        Role("controlword", RX, "RPDO1", "the CiA 402 controlword", std=(0x6040,),
             patterns=((r"\bcontrol ?word\b", 40),), manufacturer=False),
        Role("eps_0", RX, "RPDO1", "the angle of the (d, q) setpoint frame (rad)",
             patterns=((r"\beps ?0\b", 50), (r"\bframe angle\b", 40), (r"\bfield angle\b", 35),
                       (r"\bflux angle\b", 35), (r"\btheta\b", 20), (r"\bangle\b", 10))),
        Role("w_0", RX, "RPDO1", "the speed of the (d, q) setpoint frame (rad/s)",
             patterns=((r"\bw ?0\b", 50), (r"\bomega ?0\b", 45), (r"\bframe speed\b", 40),
                       (r"\bfield speed\b", 35), (r"\bflux speed\b", 35),
                       (r"\bsynchronous speed\b", 30), (r"\bomega\b", 15))),
    ]
    for name, sym, word, axes in (
            ("i_sd_ref", "i", "current", ("d", "sd")), ("i_sq_ref", "i", "current", ("q", "sq")),
            ("u_sd_ref", "u", "voltage", ("d", "sd")), ("u_sq_ref", "u", "voltage", ("q", "sq"))):
        r.append(Role(name, RX, "RPDO2", f"the {word} setpoint on the {axes[0]} axis of the "
                      "frame turned by eps_0/w_0", patterns=_vector(sym, word, axes)))
    for name, sym, word, axes, phase in (
            ("i_sa_ref", "i", "current", ("alpha", "sa"), "a"),
            ("i_sb_ref", "i", "current", ("beta", "sb"), None),
            ("u_sa_ref", "u", "voltage", ("alpha", "sa"), "a"),
            ("u_sb_ref", "u", "voltage", ("beta", "sb"), None)):
        r.append(Role(name, RX, "RPDO2_AB", f"the {word} setpoint in the fixed frame "
                      f"({axes[0]})", patterns=_vector(sym, word, axes, phase)))
    r += [
        Role("T_L", RX, "RPDO3", "the load torque of a dynamometer (emulator only)",
             patterns=((r"\bt ?l\b", 40), (r"\bload torque\b", 40)), required=False),
        Role("statusword", TX, "TPDO1", "the CiA 402 statusword", std=(0x6041,),
             patterns=((r"\bstatus ?word\b", 40),), manufacturer=False),
        Role("i_sa", TX, "TPDO1", "the stator current, alpha component (fixed frame, A)",
             patterns=(*_vector("i", "current", ("alpha", "sa", "a"), "a", 30),
                       (r"\bcurrent a\b", 20)),
             note={r"\bphase\b": _ALPHA_NOTE}),
        Role("i_sb", TX, "TPDO1", "the stator current, beta component (fixed frame, A)",
             patterns=(*_vector("i", "current", ("beta", "sb"), "b", 12),
                       (r"\bi ?b\b", 12), (r"\bcurrent b\b", 10)),
             note={r"\bphase\b|\bi ?b\b|\bcurrent b\b": _BETA_NOTE}),
        Role("sync_counter", TX, "TPDO1", "the counter of the SYNC that triggered the TPDO",
             patterns=((r"\bsync ?counter\b", 40), (r"\bsync count\b", 35)), required=False),
        Role("u_sa", TX, "TPDO2", "the applied stator voltage, alpha component, averaged over "
             "the period (V)", patterns=_vector("u", "voltage", ("alpha", "sa", "a"), "a", 25),
             note={r"\bphase\b|\boutput\b": _ALPHA_NOTE}),
        Role("u_sb", TX, "TPDO2", "the applied stator voltage, beta component, averaged over "
             "the period (V)", patterns=_vector("u", "voltage", ("beta", "sb"), "b", 10),
             note={r"\bphase\b|\boutput\b": _BETA_NOTE}),
        Role("u_dc", TX, "TPDO2", "the DC-link voltage (0x6079 is UNSIGNED32 mV per CiA 402)",
             std=(0x6079,), manufacturer=False, note={"std": "CiA 402 unit mV: scale 0.001 V"},
             patterns=((r"\bu ?dc\b", 40), (r"\bv ?dc\b", 40), (r"\bdc ?link\b", 40),
                       (r"\bdc bus\b", 35), (r"\bbus voltage\b", 30),
                       (r"\bintermediate circuit\b", 30))),
    ]
    for name, pats, what in (
            ("w_m", ((r"\bw ?m\b", 40), (r"\bmechanical speed\b", 35)),
             "the measured mechanical speed (rad/s)"),
            ("psi_ra", ((r"\bpsi ?ra\b", 40), (r"\brotor flux (a|alpha)\b", 35)),
             "the rotor flux, alpha component (Wb)"),
            ("psi_rb", ((r"\bpsi ?rb\b", 40), (r"\brotor flux (b|beta)\b", 35)),
             "the rotor flux, beta component (Wb)"),
            ("T_e", ((r"\bt ?e\b", 40), (r"\belectromagnetic torque\b", 35)),
             "the electromagnetic torque (N.m)")):
        r.append(Role(name, TX, "TPDO3", what + " (truth for reporting; emulator only)",
                      patterns=pats, required=False))
    return tuple(r)


ROLES: tuple[Role, ...] = _roles()


@dataclass(frozen=True)
class EdsObject:
    """One sub-object of the drive's dictionary."""

    index: int
    sub: int
    name: str  #: ParameterName ("record name: sub name" for sub-indices)
    dtype: int
    access: str
    pdo: bool
    default: Any

    @property
    def key(self) -> str:
        return f"0x{self.index:04X}:{self.sub:02X}"

    @property
    def type_name(self) -> str:
        return TYPE_NAMES.get(self.dtype, f"0x{self.dtype:04X}")


@dataclass(frozen=True)
class DriveEds:
    """What the skeleton needs from an EDS/DCF."""

    path: Path
    product: str
    vendor: str
    objects: dict[tuple[int, int], EdsObject]
    mapped_rx: frozenset[tuple[int, int]]  #: in a default RPDO mapping (0x16xx)
    mapped_tx: frozenset[tuple[int, int]]  #: in a default TPDO mapping (0x1Axx)

    def default(self, index: int, sub: int = 0) -> Any:
        o = self.objects.get((index, sub))
        return None if o is None else o.default

    def has(self, index: int) -> bool:
        return any(i == index for i, _ in self.objects)


def read_eds(path: str | Path, node: int = 1) -> DriveEds:
    """Load an EDS or DCF (:func:`dbc.edsfile.read_eds`: python-canopen, after naming what
    it would choke on); :class:`UserError` when it cannot be read."""
    from canopen.objectdictionary import ODArray, ODRecord, ODVariable

    from dbc.edsfile import HINT, configured
    from dbc.edsfile import read_eds as load

    p = Path(path)
    od = load(p, node).od
    objects: dict[tuple[int, int], EdsObject] = {}
    for obj in od.values():
        if isinstance(obj, ODVariable):
            items = [(obj, obj.name)]
        elif isinstance(obj, ODRecord | ODArray):
            items = [(v, f"{obj.name}: {v.name}") for v in obj.values()]
        else:  # pragma: no cover
            continue
        for v, name in items:
            objects[(v.index, v.subindex)] = EdsObject(  # a DCF's ParameterValue first
                v.index, v.subindex, name, int(v.data_type or 0), str(v.access_type or ""),
                bool(v.pdo_mappable), configured(v))
    if not objects:
        raise UserError(f"the EDS {str(p)!r} has no object sections ([1000], [6040], ...); "
                        f"{HINT}")
    mapped: dict[str, set[tuple[int, int]]] = {RX: set(), TX: set()}
    for (index, sub), o in objects.items():
        direction = RX if 0x1600 <= index < 0x1800 else TX if 0x1A00 <= index < 0x1C00 else None
        if direction is None or sub == 0 or not isinstance(o.default, int):
            continue
        count = objects.get((index, 0))
        if count is not None and isinstance(count.default, int) and sub > count.default:
            continue
        if o.default >> 16:
            mapped[direction].add((o.default >> 16, (o.default >> 8) & 0xFF))
    info = od.device_information
    return DriveEds(p, str(getattr(info, "product_name", None) or ""),
                    str(getattr(info, "vendor_name", None) or ""), objects,
                    frozenset(mapped[RX]), frozenset(mapped[TX]))


def normalize(name: str) -> str:
    """Lower case, words separated by one space ("I_alpha (A)" → "i alpha a")."""
    return " ".join(re.sub(r"[^0-9a-z]+", " ", name.lower()).split())


@dataclass(frozen=True)
class Candidate:
    obj: EdsObject
    score: int
    reasons: tuple[str, ...]
    usable: bool  #: PDO-mappable integer of 8/16/32 bits with the right access
    note: str = ""


def _score(role: Role, o: EdsObject, eds: DriveEds) -> Candidate | None:
    if o.index < 0x2000:  # the communication profile carries no process data
        return None
    name = normalize(o.name.split(": ")[-1]) if o.sub else normalize(o.name)
    reasons: list[str] = []
    score = 0
    if o.index in role.std:
        score += 100
        reasons.append("CiA 402 index")
    best = 0
    hit = ""
    for pattern, weight in role.patterns:
        if weight > best and re.search(pattern, name):
            best, hit = weight, pattern
    if not score and not best:
        return None
    if best:
        score += best
        reasons.append("name")
    has_ref = bool(re.search(_REF_WORDS, name))
    if role.direction == RX and role.name.endswith("_ref"):
        score += 15 if has_ref else -25  # a setpoint without a setpoint word is doubtful
    if role.direction == TX and has_ref:
        score -= 30
    access = o.access.lower()
    if role.direction == RX:
        right = access in ("rw", "rww", "wo")
        score += 10 if access in ("rww", "wo") else 5 if right else 0
    else:
        right = access in ("ro", "rwr", "rw")
        score += 10 if access in ("ro", "rwr") else 0
    mapped = (o.index, o.sub) in (eds.mapped_rx if role.direction == RX else eds.mapped_tx)
    if mapped:
        score += 50
        reasons.append(f"default {'RPDO' if role.direction == RX else 'TPDO'} mapping")
    if role.manufacturer and 0x2000 <= o.index < 0x6000:
        score += 5
    integer = o.dtype in INT_TYPES
    score += 5 if integer else -20
    usable = bool(o.pdo and integer and right)
    if not usable:
        score -= 60
    note = role.note.get("std", "") if o.index in role.std else ""
    for pattern, text in role.note.items():  # phase remarks, not for alpha/beta names
        if (hit and pattern != "std" and re.search(pattern, name)
                and not re.search(r"\b(alpha|beta)\b", name)):
            note = text
    return Candidate(o, score, tuple(reasons), usable, note)


@dataclass(frozen=True)
class Choice:
    role: Role
    candidates: tuple[Candidate, ...]  #: best first, up to 3
    chosen: Candidate | None


def choose(eds: DriveEds, roles: tuple[Role, ...] = ROLES) -> dict[str, Choice]:
    """Candidates and the chosen object for every role: the usable (role, object) pairs are
    taken best score first, an object carrying one role only."""
    ranked: dict[str, list[Candidate]] = {}
    for role in roles:
        cands = [c for o in eds.objects.values() if (c := _score(role, o, eds)) is not None]
        ranked[role.name] = sorted(cands, key=lambda c: (-c.score, c.obj.index, c.obj.sub))
    pairs = sorted(((c.score, k, role.name, c) for k, role in enumerate(roles)
                    for c in ranked[role.name] if c.usable),
                   key=lambda t: (-t[0], t[1], t[3].obj.index, t[3].obj.sub))
    picked: dict[str, Candidate] = {}
    taken: set[tuple[int, int]] = set()
    for _, _, name, c in pairs:
        key = (c.obj.index, c.obj.sub)
        if name not in picked and key not in taken:
            picked[name] = c
            taken.add(key)
    out: dict[str, Choice] = {}
    for role in roles:
        cands, pick = ranked[role.name], picked.get(role.name)
        top = cands[:3]
        if pick is not None and pick not in top:
            top = [*cands[:2], pick]
        out[role.name] = Choice(role, tuple(top), pick)
    return out


# ---- the skeleton -------------------------------------------------------------------------

_MESSAGES = {  # message → (direction, PDO number, roles in order)
    "RPDO1": (RX, 1, ("controlword", "eps_0", "w_0")),
    "RPDO2": (RX, 2, ("i_sd_ref", "i_sq_ref", "u_sd_ref", "u_sq_ref")),
    "RPDO2_AB": (RX, 2, ("i_sa_ref", "i_sb_ref", "u_sa_ref", "u_sb_ref")),
    "RPDO3": (RX, 3, ("T_L",)),
    "TPDO1": (TX, 1, ("statusword", "i_sa", "i_sb", "sync_counter")),
    "TPDO2": (TX, 2, ("u_sa", "u_sb", "u_dc")),
    "TPDO3": (TX, 3, ("w_m", "psi_ra", "psi_rb", "T_e")),
}
_LOOK_FOR = """\
#   - the stator (phase) currents in the fixed frame, sampled at the SYNC: i_a and i_b, or
#     i_alpha and i_beta (often "phase current U/V", "I_alpha", "current alpha"),
#   - the applied output voltage, averaged over the period: u_alpha and u_beta, or the phase
#     voltages or modulation indices times the DC-link voltage ("output voltage U/V",
#     "voltage reference alpha"),
#   - a current- or voltage-vector setpoint mode (a manufacturer-specific 0x6060 mode, bit
#     16.. of 0x6502) taking (d, q) setpoints in a frame the drive turns from an angle and a
#     speed (eps_0, w_0), or (alpha, beta) setpoints in the fixed frame."""


def _modes(eds: DriveEds) -> tuple[list[int], bool]:
    """Manufacturer-specific modes of 0x6502 (bit 16 + k → mode -1 - k) and whether mode 10
    (cyclic synchronous torque, bit 9) is supported."""
    sup = eds.default(0x6502)
    if not isinstance(sup, int):
        return [], False
    return [-1 - k for k in range(16) if sup >> (16 + k) & 1], bool(sup >> 9 & 1)


def _layout(choices: dict[str, Choice], setpoints: str) -> dict[str, list[Choice]]:
    """The messages of the DBC skeleton: chosen objects in role order, up to 8 bytes."""
    out: dict[str, list[Choice]] = {}
    for msg, (_, _, roles) in _MESSAGES.items():
        if msg.startswith("RPDO2") and msg != setpoints:
            continue
        sigs: list[Choice] = []
        bits = 0
        for r in roles:
            c = choices[r]
            if c.chosen is None:
                continue
            n = INT_TYPES[c.chosen.obj.dtype][1]
            if bits + n > 64:
                continue  # dropped; the TOML says so
            sigs.append(c)
            bits += n
        if sigs:
            out[msg] = sigs
    return out


def _setpoint_family(choices: dict[str, Choice]) -> tuple[str, bool]:
    """"RPDO2" (dq) or "RPDO2_AB" and whether it is complete (current or voltage pair)."""
    def pair(*names: str) -> bool:
        return all(choices[n].chosen is not None for n in names)

    dq = pair("eps_0", "w_0") and (pair("i_sd_ref", "i_sq_ref") or pair("u_sd_ref", "u_sq_ref"))
    ab = pair("i_sa_ref", "i_sb_ref") or pair("u_sa_ref", "u_sb_ref")
    if dq or not ab:
        return "RPDO2", dq
    return "RPDO2_AB", True


def _cand_line(k: int, c: Candidate, chosen: Candidate | None) -> str:
    o = c.obj
    flags = [o.type_name, o.access or "?", "PDO" if o.pdo else "no PDO mapping"]
    why = ", ".join(c.reasons)
    tail = "  <- chosen" if c is chosen else ("" if c.usable else "  (not usable: "
                                            + _why_not(c) + ")")
    line = f"#   {k}. {o.key} {o.name!r}  {' '.join(flags)}" + (f"  [{why}]" if why else "")
    out = line + tail
    if c.note:
        out += f"\n#      note: {c.note}"
    return out


def _why_not(c: Candidate) -> str:
    o = c.obj
    why = []
    if not o.pdo:
        why.append("not PDO-mappable")
    if o.dtype not in INT_TYPES:
        why.append(f"{o.type_name}: the codec takes 8/16/32-bit integers")
    if c.usable is False and o.pdo and o.dtype in INT_TYPES:
        why.append(f"access {o.access} for this direction")
    return "; ".join(why)


def _wrap(text: str, prefix: str, width: int = 92) -> list[str]:
    return [prefix + line for line in textwrap.wrap(text, width - len(prefix))]


def _toml_str(s: str) -> str:
    return '"' + s.replace("\\", "\\\\").replace('"', '\\"') + '"'


def render_toml(eds: DriveEds, choices: dict[str, Choice], *, node: int = 1,
                eds_ref: str | None = None, dbc_ref: str = "drive.dbc") -> str:
    """The drive-profile skeleton (TOML): header comments, then one section after another."""
    setpoints, setpoints_ok = _setpoint_family(choices)
    layout = _layout(choices, setpoints)
    in_layout = {c.role.name for sigs in layout.values() for c in sigs}
    name = eds.product or eds.path.stem
    return "\n".join([
        *_toml_header(eds, name),
        *_toml_missing(eds),
        *_toml_refusal(eds, choices, setpoints_ok),
        *_toml_drive(eds, name, node, eds_ref, dbc_ref),
        *_toml_modes(eds),
        *_toml_pdo(layout, in_layout, setpoints),
        *_toml_timing(eds),
        *_toml_limits(eds),
        *_toml_roles(choices, in_layout, setpoints),
        *_toml_signals(choices, in_layout, setpoints),
    ])


def _toml_header(eds: DriveEds, name: str) -> list[str]:
    """The opening comment: the drive (product, vendor), the EDS it comes from, and that every
    object and scaling is to be confirmed in the manual."""
    return [
        f"# Drive profile skeleton for {name}"
        + (f" ({eds.vendor})" if eds.vendor else "") + ",",
        f"# written by `hil-gateway profile new-drive` from {eds.path.name}.",
        "# Every object below was chosen by index, name, type and access: CONFIRM EACH ONE in",
        "# the drive's manual (unit, scaling, sampling instant, frame) before a run, and the",
        "# scalings in the DBC next to this file (all 1 here).",
    ]


def _toml_missing(eds: DriveEds) -> list[str]:
    """A warning naming the objects of :data:`gateway.drive_profile.REQUIRED_OBJECTS` (0x6040
    controlword, ...) the EDS lacks; nothing when it has them all."""
    from gateway.drive_profile import REQUIRED_OBJECTS

    missing = [f"0x{i:04X} {what}" for i, what in REQUIRED_OBJECTS.items() if not eds.has(i)]
    if not missing:
        return []
    return ["#", *_wrap(f"The EDS has no {', '.join(missing)}: the gateway needs them "
                        "to run a CiA 402 drive (is it a CiA 402 drive's EDS?).", "# !! ")]


def _toml_refusal(eds: DriveEds, choices: dict[str, Choice], setpoints_ok: bool) -> list[str]:
    """The "cannot run these control laws" warning when the currents (i_sa, i_sb) or a
    complete setpoint family are missing: the standard CiA 402 process data the drive has
    instead (0x6071, 0x6077, 0x6078, 0x6079, mode 10), what is missing and what to look for;
    nothing when the drive can run the laws."""
    currents_ok = choices["i_sa"].chosen is not None and choices["i_sb"].chosen is not None
    voltages_ok = choices["u_sa"].chosen is not None and choices["u_sb"].chosen is not None
    if currents_ok and setpoints_ok:
        return []
    _, cst = _modes(eds)
    std = {0x6071: "0x6071 target torque", 0x6077: "0x6077 torque actual value",
           0x6078: "0x6078 current actual value", 0x6079: "0x6079 DC link circuit voltage"}
    has_std = [t for i, t in std.items() if eds.has(i)] + (
        ["mode 10 cyclic synchronous torque"] if cst else [])
    lines = ["#", "# !! THIS DRIVE CANNOT RUN THESE CONTROL LAWS as its EDS describes it."]
    if has_std:
        lines += _wrap(f"Its process data are the standard CiA 402 ones ("
                       f"{', '.join(has_std)}): a torque demand to the drive's own "
                       "current loop" + (" and a current magnitude" if eds.has(0x6078)
                                         else "") + ".", "# !! ")
    return [
        *lines,
        "# !! The laws need the stator current vector in a fixed frame (i_sa, i_sb) and the",
        "# !! applied voltage (u_sa, u_sb) every period, and a drive that takes current or",
        "# !! voltage setpoints in a (d, q) frame it turns from eps_0/w_0 (or in the fixed",
        "# !! frame). Missing here: " + ", ".join(
            x for x, ok in (("phase/alpha-beta currents", currents_ok),
                            ("vector setpoints", setpoints_ok),
                            ("applied voltages", voltages_ok)) if not ok) + ".",
        "# !! Look in the manual for manufacturer-specific objects (0x2000..0x5FFF) carrying:",
        _LOOK_FOR,
    ]


def _toml_drive(eds: DriveEds, name: str, node: int, eds_ref: str | None,
                dbc_ref: str) -> list[str]:
    """[drive]: name, eds (``eds_ref``, else the EDS's path), dbc, node and device_type (the
    EDS's 0x1000 default; commented out when it gives none); modulator_dc_link_v commented
    out (a drive without DC-link compensation: the manual says)."""
    lines = ["", "[drive]", f"name = {_toml_str(name)}",
             f"eds = {_toml_str(eds_ref or str(eds.path))}",
             f"dbc = {_toml_str(dbc_ref)}              # written next to this file",
             f"node = {node}"]
    dt = eds.default(0x1000)
    if isinstance(dt, int):
        lines.append(f"device_type = 0x{dt:08X}       # 0x1000 default of the EDS")
    else:
        lines.append("# device_type = 0x00010192     # the EDS gives no 0x1000 default")
    lines += ["# modulator_dc_link_v = 560.0     # V: ONLY for a drive without DC-link "
              "compensation",
              "                                  # (manual): its applied voltage is the "
              "reported × u_dc/this"]
    return lines


def _toml_modes(eds: DriveEds) -> list[str]:
    """[modes] (0x6060 values): current and voltage from the manufacturer-specific modes
    0x6502 lists, in that order; commented out (-1, -2) when it lists none."""
    manuf_modes, cst = _modes(eds)
    lines = ["", "[modes]                           # 0x6060 values"]
    if not manuf_modes:
        return [*lines, *_wrap("0x6502 lists no manufacturer-specific mode" + (
            " (it has mode 10, cyclic synchronous torque, which these laws cannot use)"
            if cst else "") + ": find the drive's vector mode in the manual", "# "),
            "# current = -1", "# voltage = -2"]
    lines.append(f"# 0x6502 lists manufacturer-specific modes {manuf_modes}: which one is "
                 "current-vector\n# and which voltage-vector control is in the manual")
    lines.append(f"current = {manuf_modes[0]}")
    if len(manuf_modes) > 1:
        lines.append(f"voltage = {manuf_modes[1]}")
    else:
        lines.append("# voltage = ?                  # only one manufacturer mode listed")
    return lines


def _pdo_line(key: str, msg: str, layout: dict[str, list[Choice]], remark: str = "") -> str:
    """One key of [pdo] (``key = "msg"``) with ``remark`` as a comment; the remark says so when
    ``msg`` is not in the DBC skeleton (no candidate for any of its signals)."""
    line = f'{key} = "{msg}"'
    if msg not in layout:
        remark = "no candidate for any of its signals: not in the DBC skeleton"
    return (line.ljust(34) + f"# {remark}") if remark else line


def _toml_pdo(layout: dict[str, list[Choice]], in_layout: set[str],
              setpoints: str) -> list[str]:
    """[pdo]: the messages of the DBC skeleton: control, setpoints (RPDO2 or RPDO2_AB), load
    (when T_L is in it), currents, voltages, truth (when w_m, psi_ra, psi_rb or T_e is in
    it), and remap = true."""
    lines = ["", "[pdo]                             # messages of the DBC skeleton",
             _pdo_line("control", "RPDO1", layout),
             _pdo_line("setpoints", setpoints, layout,
                       "" if setpoints == "RPDO2" else "(alpha, beta)")]
    if "T_L" in in_layout:
        lines.append('load = "RPDO3"')
    lines += [_pdo_line("currents", "TPDO1", layout), _pdo_line("voltages", "TPDO2", layout)]
    if any(r in in_layout for r in ("w_m", "psi_ra", "psi_rb", "T_e")):
        lines.append('truth = "TPDO3"')
    lines.append("remap = true                      # write the PDO mappings by SDO")
    return lines


def _toml_timing(eds: DriveEds) -> list[str]:
    """[timing]: heartbeat_ms (0x1017, with the EDS default), heartbeat_timeout_ms (0x1016,
    noted when the EDS has none), drive_heartbeat_timeout_ms, rpdo_timeout_ms (0x1400.5),
    boot_timeout_s and sdo_timeout_s."""
    hb = eds.default(0x1017)
    return ["", "[timing]",
            "heartbeat_ms = 50                 # 0x1017"
            + (f" (EDS default {hb})" if isinstance(hb, int) else " (not in the EDS!)"),
            "heartbeat_timeout_ms = 300        # 0x1016"
            + ("" if eds.has(0x1016) else "; the EDS has none: the drive cannot\n"
               "                                  # watch the gateway's heartbeat"),
            "drive_heartbeat_timeout_ms = 500",
            "rpdo_timeout_ms = 300             # 0x1400.5 (RPDO deadline)",
            "boot_timeout_s = 2.0", "sdo_timeout_s = 0.5"]


def _toml_limits(eds: DriveEds) -> list[str]:
    """[limits]: current_peak_a (A) = 0x6075 rated current (mA) × 0x6073 max current (per
    mille) when the EDS gives both, else commented out; dc_link_v (V) commented out."""
    lines = ["", "[limits]"]
    rated, peak = eds.default(0x6075), eds.default(0x6073)
    if isinstance(rated, int) and isinstance(peak, int) and rated > 0 and peak > 0:
        lines.append(f"current_peak_a = {rated * peak / 1e6:g}"
                     "      # 0x6075 rated current (mA) x 0x6073 max current (per mille)")
    else:
        lines.append("# current_peak_a = 25.0         # A: the drive's peak/trip current "
                     "(manual)")
    lines.append("# dc_link_v = [400.0, 700.0]      # V: the drive's DC-link range (manual)")
    return lines


def _unused_setpoints(setpoints: str) -> str:
    """The setpoint message the skeleton does not use: RPDO2_AB when ``setpoints`` is RPDO2."""
    return "RPDO2_AB" if setpoints == "RPDO2" else "RPDO2"


def _toml_roles(choices: dict[str, Choice], in_layout: set[str], setpoints: str) -> list[str]:
    """The process-data roles as comments, one block per role (:func:`_role_comment`); the
    roles of the unused setpoint message are left out when they have no candidate."""
    unused = _unused_setpoints(setpoints)
    lines = ["", "# ---- process-data roles ---------------------------------------------",
             "# role = \"MESSAGE.signal\" of the DBC skeleton; candidates best first",
             "# (index:sub, name, type, access, PDO mapping)."]
    for c in choices.values():
        if c.role.message == unused and not c.candidates:
            continue
        lines += _role_comment(c, in_layout, unused)
    return lines


def _role_comment(c: Choice, in_layout: set[str], unused: str) -> list[str]:
    """One role's comment block: direction and meaning, candidates best first (or "none
    found"), and why a chosen object is not in the DBC skeleton."""
    role = c.role
    arrow = "gateway -> drive" if role.direction == RX else "drive -> gateway"
    opt = "" if role.required else ", optional"
    lines = [f"# {role.name} ({arrow}{opt}): {role.what}"]
    if not c.candidates and role.required:
        lines += _wrap(f"none found: look in the manual for a manufacturer object "
                       f"carrying {role.what}", "#   ")
    elif not c.candidates:
        lines.append("#   none found (optional: leave it out)")
    lines += [_cand_line(k, cand, c.chosen) for k, cand in enumerate(c.candidates, 1)]
    if c.chosen is not None and role.name not in in_layout:
        lines.append("#   (not in the DBC skeleton: " + (
            "the other setpoint frame is used)" if role.message == unused
            else f"{role.message} would exceed 8 bytes)"))
    return lines


def _toml_signals(choices: dict[str, Choice], in_layout: set[str], setpoints: str
                  ) -> list[str]:
    """[signals]: ``role = "MESSAGE.signal"`` for every chosen object in the DBC skeleton,
    with its index:sub and name as a comment; [objects]: the EDS object each of those
    signals maps, ``"MESSAGE.signal" = "0xIIII.S"`` (the master maps by it)."""
    unused = _unused_setpoints(setpoints)
    table = [f'{c.role.name} = "{c.role.message}.{c.role.name}"'.ljust(34)
             + f" # {c.chosen.obj.key} {c.chosen.obj.name}"
             for c in choices.values()
             if not (c.role.message == unused and not c.candidates)
             and c.chosen is not None and c.role.name in in_layout]
    objects = [f'"{c.role.message}.{c.role.name}" = "0x{c.chosen.obj.index:04X}.'
               f'{c.chosen.obj.sub}"' for c in choices.values()
               if not (c.role.message == unused and not c.candidates)
               and c.chosen is not None and c.role.name in in_layout]
    return ["", "[signals]                         # role = \"MESSAGE.signal\"", *table, "",
            "[objects]                         # the EDS object each DBC signal maps",
            *objects, ""]


def render_dbc(eds: DriveEds, choices: dict[str, Choice], node: int = 1,
               vendor: Any = None) -> str:
    """The DBC skeleton: one message per PDO with the chosen objects, with the COB-IDs of
    the CiA 301 default PDOs of ``node`` (as a third-party tool sees the drive's frames);
    the scalings 1, or the ``vendor`` DBC's where it has a signal named like the object or
    the role."""
    from gateway.newdrive_standard import vendor_signal

    setpoints, _ = _setpoint_family(choices)
    layout = _layout(choices, setpoints)
    out = ['VERSION ""', "", "", "NS_ :", "\tCM_", "\tBA_DEF_", "\tBA_", "\tVAL_", "",
           "BS_:", "", "BU_: GATEWAY DRIVE", "", ""]
    comments = [f'CM_ "Drive profile skeleton from {eds.path.name} (hil-gateway profile '
                f'new-drive); COB-IDs of the CiA 301 default PDOs for node {node}. '
                f'Scalings are 1: confirm the drive\'s units.";']
    for msg, sigs in layout.items():
        direction, n, _ = _MESSAGES[msg]
        fid = (0x200 if direction == RX else 0x180) + 0x100 * (n - 1) + node
        sender, receiver = ("GATEWAY", "DRIVE") if direction == RX else ("DRIVE", "GATEWAY")
        objs = [c.chosen.obj for c in sigs if c.chosen is not None]
        length = sum(INT_TYPES[o.dtype][1] for o in objs) // 8
        out.append(f"BO_ {fid} {msg}: {length} {sender}")
        bit = 0
        for c, o in zip(sigs, objs, strict=True):
            _, bits, signed = INT_TYPES[o.dtype]
            lo, hi = (-(1 << bits - 1), (1 << bits - 1) - 1) if signed else (0, (1 << bits) - 1)
            found = None if vendor is None else vendor_signal(vendor, c.role.name, o.name)
            factor, unit, why = ((found[0], found[1], found[2]) if found is not None
                                 else (1.0, "", "scaling 1: confirm the drive's unit"))
            out.append(f" SG_ {c.role.name} : {bit}|{bits}@1{'-' if signed else '+'} "
                       f"({factor!r},0) [{lo * factor:.12g}|{hi * factor:.12g}] "
                       f'"{unit}" {receiver}')
            body = f"{o.key} {o.name} ({o.type_name}, {o.access}); {why}".replace('"', "'")
            comments.append(f'CM_ SG_ {fid} {c.role.name} "{body}";')
            bit += bits
        out.append("")
    return "\n".join([*out, "", *comments, ""])


# ---- the command line ---------------------------------------------------------------------


def _vendor_dbc(path: str | None) -> Any:
    """``--dbc``: the vendor's DBC (cantools), or None."""
    if path is None:
        return None
    from dbc import load_database

    try:
        return load_database(Path(path))
    except Exception as exc:  # cantools raises many kinds on a bad file
        raise UserError(f"--dbc {path}: cannot be read as a DBC ({type(exc).__name__}: "
                        f"{str(exc)[:200]}); give the vendor's DBC file") from None


def _laws_can_run(choices: dict[str, Choice]) -> bool:
    """The file has the phase currents and a complete setpoint family."""
    return (choices["i_sa"].chosen is not None and choices["i_sb"].chosen is not None
            and _setpoint_family(choices)[1])


def cmd_new_drive(args: argparse.Namespace) -> int:
    """`hil-gateway profile new-drive --eds FILE [--node N] [--dbc VENDOR.dbc]
    [-o PROFILE.toml]`: a vector drive's skeleton, or a standard drive's profile."""
    from gateway import newdrive_standard

    if not 1 <= args.node <= 127:
        raise UserError(f"--node {args.node}: a CANopen node id is 1..127")
    eds = read_eds(args.eds, args.node)
    vendor = _vendor_dbc(args.dbc)
    choices = choose(eds)
    std = None if _laws_can_run(choices) else newdrive_standard.plan(eds, vendor)
    out = None if args.output is None else Path(args.output)
    if out is not None and out.suffix.lower() != ".toml":
        raise UserError(f"-o {str(out)!r}: give the profile's name ending in .toml (the DBC "
                        "skeleton is written next to it with the suffix .dbc)")
    dbc_path = Path(args.eds).with_suffix(".dbc") if out is None else out.with_suffix(".dbc")
    eds_ref = args.eds
    if out is not None:
        try:
            eds_ref = os.path.relpath(eds.path.resolve(), out.resolve().parent).replace(
                os.sep, "/")
        except ValueError:  # another drive (Windows)
            eds_ref = str(eds.path.resolve())
    if std is not None:
        toml_text = newdrive_standard.render_toml(
            eds, std, node=args.node, eds_ref=eds_ref, dbc_ref=dbc_path.name,
            common=(_toml_timing(eds), _toml_limits(eds)))
        dbc_text = newdrive_standard.render_dbc(eds, std, args.node)
    else:
        toml_text = render_toml(eds, choices, node=args.node, eds_ref=eds_ref,
                                dbc_ref=dbc_path.name)
        dbc_text = render_dbc(eds, choices, args.node, vendor)
    if out is None:
        print(toml_text, end="")
        return 0
    try:
        out.parent.mkdir(parents=True, exist_ok=True)
        out.write_text(toml_text, encoding="utf-8")
        dbc_path.write_text(dbc_text, encoding="utf-8")
    except OSError as exc:
        raise UserError(f"cannot write {str(out)!r}: {exc.strerror or exc}; choose a "
                        "writable place with -o") from None
    if std is not None:
        todo = sorted({s.name for s in std.signals if s.todo})
        print(f"wrote {out} and {dbc_path}: a standard CiA 402 drive, "
              f"{std.default.value} mode ({std.modes[std.default]} = "
              f"{describe_mode(std.modes[std.default])}); "
              + (f"TODO: confirm the units of {', '.join(todo)} (see the header)" if todo
                 else "units from the file") + f"; check it offline: hil-gateway profile "
              f"check {out}")
        return 0
    found = sum(1 for c in choices.values() if c.chosen is not None)
    print(f"wrote {out} and {dbc_path}: {found} of {len(choices)} roles have a candidate; "
          "confirm each against the drive's manual")
    return 0


def add_action(psub: Any) -> None:
    """Register `new-drive` on the actions of the `reference`/`profile` subcommand."""
    p = psub.add_parser(
        "new-drive", help="write a drive-profile skeleton from a drive's EDS/DCF",
        description="Write a drive-profile skeleton (TOML) from the drive's EDS or DCF: for "
                    "each process-data role the gateway uses, up to 3 candidate objects "
                    "chosen by index, name, type and access, as comments to confirm, the best "
                    "in [signals]; with -o X.toml also a DBC skeleton X.dbc. Exit 2 if the "
                    "EDS cannot be read.")
    p.add_argument("--eds", required=True, metavar="FILE", help="the drive's EDS or DCF")
    p.add_argument("--node", type=int, default=1, metavar="N",
                   help="node id (default 1): every COB-ID of the DBC is this node's")
    p.add_argument("--dbc", metavar="VENDOR.dbc",
                   help="take the scalings from the vendor's DBC: a signal named like the EDS "
                        "object (or like our signal) gives its factor and unit")
    p.add_argument("-o", "--output", metavar="PROFILE.toml",
                   help="write the profile here and the DBC skeleton next to it "
                        "(default: the profile on standard output)")
    p.set_defaults(func=cmd_new_drive)
