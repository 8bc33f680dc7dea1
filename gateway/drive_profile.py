"""Drive profiles: what the gateway must know about a CANopen drive, in a TOML file.

A real CiA 402 inverter is described without code: its EDS, node id, which DBC messages
carry which signals, the modes of operation, and timing. The emulator's profile is built in
(``gateway/drives/emulator.toml``). Example::

    [drive]
    name = "can-drive-hil emulated drive"
    eds = "builtin:drive.eds"        # or a path, relative to this file
    dbc = "builtin:drive.dbc"
    node = 1
    device_type = 0x00010192         # 0x1000 expected (CiA 402, frequency converter)
    bitrate = 1000000                # the bus's bit rate, bit/s: the bus time of a cycle
    modulator_dc_link_v = 560.0      # optional: a drive WITHOUT DC-link compensation, whose
                                     # modulator assumes this DC link: it applies the voltage
                                     # it reports × u_dc/this (u_dc from [pdo].voltages);
                                     # leave out for a drive that compensates (most do)

    [modes]                          # 0x6060 values
    current = -1                     # current vector (current-fed law)
    voltage = -2                     # voltage vector (full-order law)
    torque = 10                      # cyclic synchronous torque (CST; a standard drive;
                                     # 4: profile torque)
    velocity = 9                     # cyclic synchronous velocity (CSV; 3: profile velocity)
    position = 8                     # cyclic synchronous position (CSP)
    default = "velocity"             # optional: the drive mode of a run without --drive-mode
                                     # (a standard one: also --controller stream)

    [pdo]                            # DBC messages (ids for node 1; offset by node id)
    control = "RPDO1"                # controlword, eps_0, w_0
    setpoints = "RPDO2"              # dq setpoints; "RPDO2_AB" for drives that hold (a, b);
                                     # none for a standard drive (targets in control)
    load = "RPDO3"                   # emulated dynamometer (emulator only)
    currents = "TPDO1"               # statusword, i_sa, i_sb, sync_counter
    voltages = "TPDO2"               # u_sa, u_sb, u_dc (optional)
    truth = "TPDO3"                  # w_m, psi_ra, psi_rb, T_e (emulator only)
    remap = true                     # write the PDO mappings by SDO from the DBC layout
                                     # (and disable the drive's PDOs the profile does not use)
    mapping = "default"              # or "lean": what `--mapping` names (emulator-lean.toml)
    transmission_type = 1            # synchronous, every n-th SYNC (CiA 301 1..240); the
                                     # loop takes a cycle's TPDOs every SYNC: 1 to run

    [limits]                         # what the drive can report: beyond is a fault
    current_peak_a = 25.0            # largest |i_s| (default: 1.5 × the controller's limit)
    dc_link_v = [400.0, 700.0]       # DC-link range (default: only > 0)

    [timing]                         # ms: 1..65535; s: finite, > 0
    heartbeat_ms = 50                # the drive's heartbeat (0x1017)
    heartbeat_timeout_ms = 300       # the gateway's heartbeat as seen by the drive (0x1016)
    drive_heartbeat_timeout_ms = 500 # the drive's heartbeat as watched by the gateway
    rpdo_timeout_ms = 300            # RPDO deadline monitoring (0x1400.5)
    boot_timeout_s = 2.0
    sdo_timeout_s = 0.5

    [[sdo]]                          # start-up SDO writes, in order, in PRE-OPERATIONAL
    index = 0x6083                   # (after the identity check, before the PDO mappings);
    sub = 0                          # each is read back and must equal the value
    value = 10000
    note = "profile acceleration"    # optional, for messages
"""

from __future__ import annotations

import re
import tomllib
from dataclasses import dataclass, field
from enum import StrEnum
from importlib import resources
from pathlib import Path
from typing import Any

from dbc import diskcache
from dbc.codec import ab_companion
from dbc.filecache import FileMemo, resolved
from dbc.modes import DriveMode
from gateway.errors import UserError

_SECTIONS: dict[str, dict[str, type | tuple[type, ...]]] = {
    "drive": {"name": str, "eds": str, "dbc": str, "node": int, "device_type": int,
              "emulator": bool, "gateway_node": int, "dbc_node": int, "bitrate": int,
              "modulator_dc_link_v": (int, float)},
    "modes": {"current": int, "voltage": int, "torque": int, "velocity": int, "position": int,
              "default": str},
    "pdo": {"control": str, "setpoints": str, "load": str, "currents": str, "voltages": str,
            "truth": str, "remap": bool, "transmission_type": int, "mapping": str},
    "timing": {"heartbeat_ms": int, "heartbeat_timeout_ms": int, "rpdo_timeout_ms": int,
               "drive_heartbeat_timeout_ms": int,
               "boot_timeout_s": (int, float), "sdo_timeout_s": (int, float)},
    "limits": {"current_peak_a": (int, float), "dc_link_v": list},
    "signals": {},  # role = "MESSAGE.signal": any role of dbc/signals.py
    "objects": {},  # "MESSAGE.signal" = "0xIIII.S": the EDS object a DBC signal maps
    "sdo": {},  # [[sdo]]: a list of start-up writes (:class:`SdoWrite`), checked apart
}
#: The keys of an [[sdo]] entry and their types (``note`` optional).
_SDO_KEYS: dict[str, type | tuple[type, ...]] = {"index": int, "sub": int,
                                                  "value": (int, float), "note": str}
#: Ranges of the timing keys: (low, high, unit, what it is).
_TIMING_RANGES: dict[str, tuple[float, float, str, str]] = {
    "heartbeat_ms": (1, 65535, "ms", "0x1017 is UNSIGNED16 ms; 0 would switch the drive's "
                     "heartbeat off and with it the gateway's watch"),
    "heartbeat_timeout_ms": (1, 65535, "ms", "0x1016 holds UNSIGNED16 ms; 0 would switch the "
                             "drive's supervision of the gateway off"),
    "drive_heartbeat_timeout_ms": (1, 65535, "ms", "the gateway's watch of the drive"),
    "rpdo_timeout_ms": (1, 65535, "ms", "0x1400.5 is UNSIGNED16 ms; 0 would switch the RPDO "
                        "deadline off"),
    "boot_timeout_s": (0.01, 600.0, "s", "a finite wait for the boot-up"),
    "sdo_timeout_s": (0.001, 60.0, "s", "a finite wait for an SDO answer"),
}
#: Objects a CiA 402 drive's EDS must have for the gateway to run it.
REQUIRED_OBJECTS: dict[int, str] = {
    0x1000: "device type", 0x1017: "producer heartbeat time", 0x6040: "controlword",
    0x6041: "statusword", 0x6060: "modes of operation",
}
_REQUIRED = (("drive", "eds"), ("drive", "dbc"), ("pdo", "control"), ("pdo", "currents"))


class Mapping(StrEnum):
    """Which process data a profile's PDOs are ([pdo].mapping, `--mapping`): DEFAULT every
    signal of the emulator every cycle; LEAN a cycle that fits 500 us on 1 Mbit/s
    (``gateway/drives/emulator-lean.toml``)."""

    DEFAULT = "default"
    LEAN = "lean"


@dataclass(frozen=True)
class SdoWrite:
    """A start-up SDO write of the drive profile's [[sdo]] list: object, value, and what it
    is for (messages)."""

    index: int
    sub: int
    value: int | float
    note: str = ""

    def describe(self) -> str:
        """"0xIIII.S = value (note)"."""
        return (f"0x{self.index:04X}.{self.sub} = {self.value!r}"
                + (f" ({self.note})" if self.note else ""))


@dataclass(frozen=True)
class DriveProfile:
    """A drive as the gateway sees it (see the module docstring for the TOML form)."""

    name: str
    source: str
    eds: Path
    dbc: Path
    node: int = 1
    device_type: int | None = 0x00010192
    emulator: bool = False
    mode_current: int = -1
    mode_voltage: int = -2
    mode_torque: int = 10
    mode_velocity: int = 9
    mode_position: int = 8
    default_mode: DriveMode | None = None
    control: str = "RPDO1"
    setpoints: str | None = "RPDO2"
    load: str | None = None
    currents: str = "TPDO1"
    voltages: str | None = "TPDO2"
    truth: str | None = None
    remap: bool = True
    heartbeat_ms: int = 50
    heartbeat_timeout_ms: int = 300
    drive_heartbeat_timeout_ms: int = 500
    rpdo_timeout_ms: int = 300
    boot_timeout_s: float = 2.0
    sdo_timeout_s: float = 0.5
    current_peak_a: float | None = None
    dc_link_v: tuple[float, float] | None = None
    #: V: the DC link an uncompensated modulator assumes (None: the drive compensates its
    #: DC link, the voltage it reports is the one it applies)
    modulator_dc_link_v: float | None = None
    signals: dict[str, tuple[str, str]] = field(default_factory=dict)
    objects: dict[str, tuple[int, int]] = field(default_factory=dict)
    gateway_node: int = 0x7F
    dbc_node: int | None = None
    sdo: tuple[SdoWrite, ...] = ()
    bitrate: int = 1_000_000
    transmission_type: int = 1
    mapping: Mapping = Mapping.DEFAULT

    def mode_of(self, drive_mode: DriveMode) -> int:
        """The 0x6060 value of a drive mode on this drive ([modes])."""
        return {DriveMode.VOLTAGE: self.mode_voltage, DriveMode.TORQUE: self.mode_torque,
                DriveMode.VELOCITY: self.mode_velocity,
                DriveMode.POSITION: self.mode_position}.get(drive_mode, self.mode_current)

    @property
    def check_mode(self) -> DriveMode:
        """The drive mode `check` configures: [modes].default, else the current loop."""
        return self.default_mode or DriveMode.CURRENT_LOOP

    @property
    def messages(self) -> tuple[str, ...]:
        """The DBC messages the profile names in [pdo], RPDOs then TPDOs."""
        return tuple(n for n in (self.control, self.setpoints, self.load, self.currents,
                                 self.voltages, self.truth) if n)



def _builtin(name: str) -> Path:
    return Path(str(resources.files("dbc").joinpath(name)))


def _resolve(value: str, base: Path) -> Path:
    if value.startswith("builtin:"):
        return _builtin(value.removeprefix("builtin:"))
    p = Path(value)
    return p if p.is_absolute() else base / p


#: The built-in emulator profiles: its vector modes, its CiA 402 standard modes, and its
#: vector modes with lean process data (a cycle that fits 500 us on 1 Mbit/s).
EMULATOR = "emulator"
EMULATOR_STANDARD = "emulator-standard"
EMULATOR_LEAN = "emulator-lean"


def emulator_profile(mode: DriveMode, mapping: Mapping | None = None) -> str:
    """The built-in emulator profile for a drive mode and ``--mapping``: its CiA 402
    standard modes (CST, CSV, CSP, …), or its vector modes with the default or the lean
    process data (:class:`Mapping`; the lean one has no standard-mode variant)."""
    if mapping is Mapping.LEAN:
        if mode.standard:
            raise UserError(f"--mapping lean is the emulator's lean process data for its "
                            f"vector modes; --drive-mode {mode.value} runs the drive's own "
                            "control with the standard CiA 402 mapping: drop --mapping lean")
        if mode is DriveMode.VOLTAGE:
            raise UserError("--mapping lean carries current setpoints only (one 8-byte RPDO: "
                            "eps_0, w_0, i_sd*, i_sq*); --drive-mode voltage needs the voltage "
                            "setpoints of the default mapping: drop --mapping lean, or use "
                            "--drive-mode ideal or current-loop")
        return EMULATOR_LEAN
    return EMULATOR_STANDARD if mode.standard else EMULATOR


def load_drive_profile(path: str | Path | None = None, builtin: str = EMULATOR
                       ) -> DriveProfile:
    """Read a drive profile; None gives a built-in emulator profile (``builtin``:
    :data:`EMULATOR`, or :data:`EMULATOR_STANDARD` for CST/CSV)."""
    if path is None:
        src = resources.files("gateway").joinpath(f"drives/{builtin}.toml")
        text, source, base = src.read_text(), f"<{builtin}>", Path(".")
    else:
        p = Path(path)
        try:
            text = p.read_text()
        except OSError as exc:
            raise UserError(f"cannot read the drive profile {str(p)!r}: {exc.strerror or exc}; "
                            "give an existing TOML file with --drive") from exc
        source, base = str(p), p.parent
    return _CHECKED.get((text, source, resolved(base)),
                        lambda: _checked(text, source, base))


#: Drive profiles read and checked, kept while the profile's text and its EDS and DBC are
#: unchanged (a campaign's points load the same profile again and again; checking its EDS
#: and DBC takes about 30 ms). :class:`DriveProfile` is frozen: shared, read-only.
_CHECKED: FileMemo[DriveProfile] = FileMemo()


def _checked(text: str, source: str, base: Path) -> tuple[DriveProfile, tuple[Path, ...]]:
    """The profile of ``text`` checked, and the files it depends on."""
    try:
        data = tomllib.loads(text)
    except tomllib.TOMLDecodeError as exc:
        raise UserError(f"{source}: not valid TOML: {exc}; fix the syntax") from exc
    prof = _from_mapping(data, source, base)
    return prof, (prof.eds, prof.dbc, ab_companion(prof.dbc))


def _from_mapping(data: dict[str, Any], source: str, base: Path) -> DriveProfile:
    """The profile from the parsed TOML ``data`` (read from ``source``; relative paths from
    ``base``): every section and value checked, then the EDS and DBC it names."""
    _check_sections(data, source)
    t, lim, d = (data.get(s, {}) for s in ("timing", "limits", "drive"))
    _check_timing(t, source)
    _check_limits(lim, source)
    _check_nodes(d, source)
    _check_modulator(d, source)
    _check_bus(d, data.get("pdo", {}), source)
    prof = _build_profile(data, source, base)
    for what, path in (("eds", prof.eds), ("dbc", prof.dbc)):
        if not path.is_file():
            raise UserError(f"{source}: [drive].{what} = {str(path)!r} does not exist; give the "
                            f"path of the drive's {what.upper()} file, relative to the profile")
    _check_files(prof)
    return prof


def _check_files(prof: DriveProfile) -> None:
    """The EDS and the DBC checks (:func:`_check_eds`, :func:`_check_dbc`), their verdict
    kept on disk between processes (:mod:`dbc.diskcache`; reading the EDS imports
    python-canopen: 0.17 s of a `simulate`), keyed by both files, the profile's [[sdo]]
    writes and messages, and the checking code."""
    here = Path(diskcache.__file__).parent  # dbc/ (its modules not imported for this)
    companion = ab_companion(prof.dbc)
    entry = diskcache.key(
        "drive-check", [prof.eds, prof.dbc, companion if companion.is_file() else None],
        [__file__, here / "edsfile.py", here / "codec.py", here / "frame.py"],
        packages=("canopen", "cantools"),
        extra=repr((sorted(prof.messages), prof.sdo)))

    def check() -> bool:
        _check_eds(prof)
        _check_dbc(prof, list(prof.messages))
        return True

    diskcache.cached(entry, check)


def _check_sections(data: dict[str, Any], source: str) -> None:
    """Only the known sections (:data:`_SECTIONS`) and keys, each of its type; the
    :data:`_REQUIRED` keys present."""
    for section, value in data.items():
        if section not in _SECTIONS:
            raise UserError(f"{source}: unknown section [{section}]; the sections are "
                            f"{', '.join('[' + s + ']' for s in _SECTIONS)}")
        if section == "sdo":
            _check_sdo_list(source, value)
            continue
        if not isinstance(value, dict):
            raise UserError(f"{source}: [{section}] must be a table")
        for key, v in value.items():
            if section == "signals":
                _check_signal(source, key, v)
                continue
            if section == "objects":
                _object_key(source, key, v)
                continue
            types = _SECTIONS[section].get(key)
            if types is None:
                raise UserError(f"{source}: unknown key [{section}].{key}; the keys of "
                                f"[{section}] are {', '.join(_SECTIONS[section])}")
            if not isinstance(v, types) or (isinstance(v, bool) and types is not bool):
                raise UserError(f"{source}: [{section}].{key} = {v!r} has the wrong type")
    for section, key in _REQUIRED:
        if key not in data.get(section, {}):
            raise UserError(f"{source}: [{section}].{key} is missing; add it (see "
                            "gateway/drives/emulator.toml for an example)")


def _default_mode(source: str, modes: dict[str, Any]) -> DriveMode | None:
    """[modes].default: a drive mode (``velocity``, ``torque``, ``position``, ...)."""
    value = modes.get("default")
    if value is None:
        return None
    try:
        return DriveMode(value)
    except ValueError:
        raise UserError(f"{source}: [modes].default = {value!r} is not a drive mode; the "
                        f"drive modes are {', '.join(m.value for m in DriveMode)}") from None


def _check_sdo_list(source: str, entries: object) -> None:
    """[[sdo]]: a list of tables with ``index`` (0x1000..0xFFFF), ``sub`` (0..255), a
    numeric ``value`` and an optional ``note``."""
    if not isinstance(entries, list):
        raise UserError(f"{source}: sdo must be a list of [[sdo]] tables (index, sub, value)")
    for k, e in enumerate(entries, 1):
        where = f"{source}: [[sdo]] entry {k}"
        if not isinstance(e, dict):
            raise UserError(f"{where} must be a table with index, sub and value")
        for key, v in e.items():
            types = _SDO_KEYS.get(key)
            if types is None:
                raise UserError(f"{where}: unknown key {key!r}; the keys are "
                                f"{', '.join(_SDO_KEYS)}")
            if not isinstance(v, types) or isinstance(v, bool):
                raise UserError(f"{where}: {key} = {v!r} has the wrong type")
        missing = [key for key in ("index", "sub", "value") if key not in e]
        if missing:
            raise UserError(f"{where} has no {', '.join(missing)}; write index = 0xIIII, "
                            "sub = S, value = V")
        if not 0x1000 <= e["index"] <= 0xFFFF or not 0 <= e["sub"] <= 255:
            raise UserError(f"{where}: 0x{e['index']:X}.{e['sub']} is not an object of the "
                            "object dictionary (index 0x1000..0xFFFF, sub-index 0..255)")


def _check_timing(t: dict[str, Any], source: str) -> None:
    """Each [timing] key within its range (:data:`_TIMING_RANGES`: ms 1..65535, s finite)."""
    for key, value in t.items():
        lo, hi, unit, what = _TIMING_RANGES[key]
        if not lo <= value <= hi:  # NaN and inf too
            raise UserError(f"{source}: [timing].{key} = {value!r} is outside {lo:g}..{hi:g} "
                            f"{unit} ({what}); give a value in that range")


def _check_limits(lim: dict[str, Any], source: str) -> None:
    """[limits]: ``current_peak_a`` a current in A (0 < I < 10000), ``dc_link_v`` a range
    [low, high] in V (0 <= low < high < 100000)."""
    peak = lim.get("current_peak_a")
    if peak is not None and not 0.0 < peak < 1e4:
        raise UserError(f"{source}: [limits].current_peak_a = {peak!r} must be a current in A, "
                        "0 < I < 10000")
    dc = lim.get("dc_link_v")
    if dc is not None and (len(dc) != 2 or not all(isinstance(x, int | float)
                                                    and not isinstance(x, bool) for x in dc)
                           or not 0.0 <= dc[0] < dc[1] < 1e5):
        raise UserError(f"{source}: [limits].dc_link_v = {dc!r} must be [low, high] in V with "
                        "0 <= low < high")


def _check_bus(d: dict[str, Any], p: dict[str, Any], source: str) -> None:
    """[drive].bitrate: a CAN bit rate (10 kbit/s .. 1 Mbit/s); [pdo].transmission_type:
    synchronous, every n-th SYNC (CiA 301 types 1..240)."""
    rate = d.get("bitrate", 1_000_000)
    if not 10_000 <= rate <= 1_000_000:
        raise UserError(f"{source}: [drive].bitrate = {rate}: a CAN bit rate is 10000 .. "
                        "1000000 bit/s")
    mapping = p.get("mapping", "default")
    if mapping not in set(Mapping):
        raise UserError(f"{source}: [pdo].mapping = {mapping!r}: the mappings are "
                        f"{', '.join(m.value for m in Mapping)}")
    tt = p.get("transmission_type", 1)
    if not 1 <= tt <= 240:
        raise UserError(f"{source}: [pdo].transmission_type = {tt}: the gateway's PDOs are "
                        "synchronous, every n-th SYNC (CiA 301 types 1..240)")


def _check_modulator(d: dict[str, Any], source: str) -> None:
    """[drive].modulator_dc_link_v: a DC-link voltage in V (0 < U < 100000)."""
    u = d.get("modulator_dc_link_v")
    if u is not None and not 0.0 < u < 1e5:
        raise UserError(f"{source}: [drive].modulator_dc_link_v = {u!r} must be the DC link "
                        "the drive's modulator assumes, in V (0 < U < 100000); leave it out "
                        "for a drive that compensates its DC link")


def _check_nodes(d: dict[str, Any], source: str) -> None:
    """[drive] ``node``, ``gateway_node``, ``dbc_node``: CANopen node ids (1..127); the
    gateway's differs from the drive's."""
    node = d.get("node", 1)
    for key, value in (("node", node), ("gateway_node", d.get("gateway_node", 0x7F)),
                       ("dbc_node", d.get("dbc_node", node))):
        if not 1 <= value <= 127:
            raise UserError(f"{source}: [drive].{key} = {value}: a CANopen node id is 1..127")
    if d.get("gateway_node", 0x7F) == node:
        raise UserError(f"{source}: [drive].gateway_node = {node} is the drive's node id: the "
                        "gateway's heartbeat would look like the drive's; choose another")


def _build_profile(data: dict[str, Any], source: str, base: Path) -> DriveProfile:
    """The :class:`DriveProfile` of checked ``data``, with the defaults for keys left out;
    ``eds`` and ``dbc`` resolved against ``base`` (not yet checked to exist)."""
    d, m, p, t, lim, sg = (data.get(s, {}) for s in ("drive", "modes", "pdo", "timing",
                                                     "limits", "signals"))
    ob = data.get("objects", {})
    peak, dc = lim.get("current_peak_a"), lim.get("dc_link_v")
    return DriveProfile(
        name=d.get("name", Path(source).stem), source=source,
        eds=_resolve(d["eds"], base), dbc=_resolve(d["dbc"], base), node=d.get("node", 1),
        device_type=d.get("device_type"), emulator=d.get("emulator", False),
        mode_current=m.get("current", -1), mode_voltage=m.get("voltage", -2),
        mode_torque=m.get("torque", 10), mode_velocity=m.get("velocity", 9),
        mode_position=m.get("position", 8), default_mode=_default_mode(source, m),
        control=p["control"], setpoints=p.get("setpoints"), load=p.get("load"),
        currents=p["currents"], voltages=p.get("voltages"), truth=p.get("truth"),
        remap=p.get("remap", True),
        heartbeat_ms=t.get("heartbeat_ms", 50),
        heartbeat_timeout_ms=t.get("heartbeat_timeout_ms", 300),
        drive_heartbeat_timeout_ms=t.get("drive_heartbeat_timeout_ms", 500),
        rpdo_timeout_ms=t.get("rpdo_timeout_ms", 300),
        boot_timeout_s=float(t.get("boot_timeout_s", 2.0)),
        sdo_timeout_s=float(t.get("sdo_timeout_s", 0.5)),
        current_peak_a=None if peak is None else float(peak),
        dc_link_v=None if dc is None else (float(dc[0]), float(dc[1])),
        modulator_dc_link_v=(None if d.get("modulator_dc_link_v") is None
                             else float(d["modulator_dc_link_v"])),
        signals={role: _message_signal(v) for role, v in sg.items()},
        objects={key: _object_key(source, key, v) for key, v in ob.items()},
        gateway_node=d.get("gateway_node", 0x7F), dbc_node=d.get("dbc_node"),
        sdo=tuple(SdoWrite(e["index"], e["sub"], e["value"], e.get("note", ""))
                  for e in data.get("sdo", [])),
        bitrate=d.get("bitrate", 1_000_000), transmission_type=p.get("transmission_type", 1),
        mapping=Mapping(p.get("mapping", "default")),
    )


_OBJECT = re.compile(r"^0x([0-9A-Fa-f]{4})(?:[.:](?:0x)?([0-9A-Fa-f]{1,2}))?$")


def _object_key(source: str, key: str, value: object) -> tuple[int, int]:
    """[objects] ``"MESSAGE.signal" = "0xIIII.S"``: (index, sub-index; sub 0 if left out,
    hexadecimal as in an EDS)."""
    m = _OBJECT.match(value) if isinstance(value, str) else None
    if m is None or key.count(".") != 1:
        raise UserError(f"{source}: [objects].{key} = {value!r}: write \"MESSAGE.signal\" = "
                        "\"0xIIII.S\" (the EDS object the DBC signal maps, e.g. "
                        "\"TPDO1.i_sa\" = \"0x3010.0\")")
    return int(m.group(1), 16), int(m.group(2) or "0", 16)


def _message_signal(value: str) -> tuple[str, str]:
    message, signal = value.split(".", 1)
    return message, signal


def _check_signal(source: str, role: str, value: object) -> None:
    from dbc.signals import ROLES

    if role not in ROLES:
        raise UserError(f"{source}: [signals].{role} is not a role of the gateway; the roles "
                        f"are {', '.join(sorted(ROLES))}")
    if not isinstance(value, str) or value.count(".") != 1 or value.startswith(".") or \
            value.endswith("."):
        raise UserError(f"{source}: [signals].{role} = {value!r}: write \"MESSAGE.signal\" of "
                        "the profile's DBC, e.g. \"TPDO1.Ia\"")


def _check_eds(prof: DriveProfile) -> None:
    """The EDS loads and has the objects the gateway needs (:data:`REQUIRED_OBJECTS`)."""
    from dbc.edsfile import read_eds

    try:
        od = read_eds(prof.eds).od
    except UserError as exc:
        raise UserError(f"{prof.source}: {exc}; give the drive's CiA 306 EDS") from None
    missing = [f"0x{i:04X} {what}" for i, what in REQUIRED_OBJECTS.items() if i not in od]
    if missing:
        raise UserError(f"{prof.source}: the EDS {str(prof.eds)!r} has no {', '.join(missing)}: "
                        "the gateway needs them to run a CiA 402 drive (is it the drive's EDS?)")
    for w in prof.sdo:
        _check_sdo_object(prof, od, w)


def _check_sdo_object(prof: DriveProfile, od: Any, w: SdoWrite) -> None:
    """An [[sdo]] write names a writable variable of the EDS, and its value fits it."""
    from canopen.objectdictionary import ODArray, ODRecord, ODVariable

    obj = od.get(w.index)
    var = obj.get(w.sub) if isinstance(obj, ODRecord | ODArray) else (
        obj if isinstance(obj, ODVariable) and w.sub == 0 else None)
    where = f"{prof.source}: [[sdo]] {w.describe()}"
    if var is None:
        raise UserError(f"{where}: the EDS {str(prof.eds)!r} has no such object; check index "
                        "and sub-index against the drive's EDS")
    if not var.writable:
        raise UserError(f"{where}: the EDS says 0x{w.index:04X}.{w.sub} ({var.name}) is "
                        f"{var.access_type}, not writable")
    if var.data_type in _FLOAT_TYPES:
        return
    if isinstance(w.value, float):
        raise UserError(f"{where}: {var.name} is an integer object; give an integer value")
    lo, hi = _int_range(var)
    if not lo <= w.value <= hi:
        raise UserError(f"{where}: {w.value} is outside {var.name}'s range {lo}..{hi}")


_FLOAT_TYPES = (0x8, 0x11)  #: REAL32, REAL64


def _int_range(var: Any) -> tuple[int, int]:
    """The raw range of an integer object of the EDS (its data type's, or its own limits)."""
    from canopen.objectdictionary import SIGNED_TYPES

    bits = {0x1: 1, 0x2: 8, 0x3: 16, 0x4: 32, 0x5: 8, 0x6: 16, 0x7: 32, 0x10: 24, 0x12: 40,
            0x13: 48, 0x14: 56, 0x15: 64, 0x16: 24, 0x18: 40, 0x19: 48, 0x1A: 56,
            0x1B: 64}.get(var.data_type, 64)
    if var.data_type in SIGNED_TYPES:
        lo, hi = -(1 << (bits - 1)), (1 << (bits - 1)) - 1
    else:
        lo, hi = 0, (1 << bits) - 1
    if var.min is not None:
        lo = max(lo, var.min)
    if var.max is not None:
        hi = min(hi, var.max)
    return lo, hi


def _check_dbc(prof: DriveProfile, names: list[str]) -> None:
    """The DBC loads and has the messages the profile names."""
    from dbc import load_database, parse_dbc

    try:  # the codec's parse, kept on disk (dbc.diskcache): no cantools to import
        known = set(parse_dbc(prof.dbc)[0])
    except Exception:  # what the fast codec cannot take, cantools may: ask it
        known = set()
    if not set(names) <= known:
        try:
            db = load_database(prof.dbc)
        except Exception as exc:
            raise UserError(f"{prof.source}: the DBC {str(prof.dbc)!r} cannot be read "
                            f"({type(exc).__name__}: {str(exc)[:200]}); give a DBC file"
                            ) from None
        known = {m.name for m in db.messages}
    unknown = [n for n in names if n not in known]
    if unknown:
        raise UserError(f"{prof.source}: [pdo] names {', '.join(unknown)}, which the DBC "
                        f"{str(prof.dbc)!r} does not define; its messages are "
                        f"{', '.join(sorted(known))}")
