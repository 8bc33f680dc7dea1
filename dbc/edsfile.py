"""A drive's CiA 306 EDS or DCF as python-canopen's object dictionary, or an error naming the
file, line and key to fix.

python-canopen's ``import_od`` reads the file; this module first makes sure it can, so
that a bad file is told as what is wrong and where instead of a traceback:

* the file exists, is text (UTF-8, or Windows-1252 as many vendors write it) and ends in
  .eds or .dcf (python-canopen picks the format by the suffix);
* a key without a value (``VendorNumber=``, as CANopenEditor writes unset keys) counts as
  absent, as CiA 306 means it;
* every value python-canopen converts is checked first (object type, data type, access
  type, PDO mapping, limits, default and parameter values, [DeviceInfo] numbers,
  [DeviceComissioning] NodeID, [Comments]), and every sub-index section has its object.

A DCF's ParameterValue is the object's configured value (python-canopen keeps it beside the
DefaultValue: :func:`configured` gives it first). The node id that resolves ``$NODEID`` is
the one asked for, else the DCF's [DeviceComissioning] NodeID, else 1.
"""

from __future__ import annotations

import configparser
import io
import re
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import canopen
from canopen.objectdictionary import ODVariable, datatypes

from dbc.errors import UserError

HINT = "give the drive's CiA 306 EDS or DCF (from the vendor's website or configuration tool)"
ACCESS_TYPES = frozenset({"ro", "wo", "rw", "rwr", "rww", "const"})
_OBJECT = re.compile(r"^[0-9A-Fa-f]{4}$")
_SUB = re.compile(r"^([0-9A-Fa-f]{4})[Ss]ub([0-9A-Fa-f]+)$")
_NAMES = re.compile(r"^([0-9A-Fa-f]{4})Name$")
_VAR, _DOMAIN, _ARRAY, _RECORD = 0x7, 0x2, 0x8, 0x9
_DEVICE_INFO_NUMBERS = ("VendorNumber", "ProductNumber", "RevisionNumber", "NrOfRXPDO",
                        "NrOfTXPDO", "SimpleBootUpMaster", "SimpleBootUpSlave", "Granularity",
                        "DynamicChannelsSupported", "GroupMessaging", "LSS_Supported",
                        *(f"BaudRate_{k}" for k in (10, 20, 50, 125, 250, 500, 800, 1000)))


@dataclass(frozen=True)
class EdsFile:
    """A read EDS/DCF: python-canopen's dictionary (``$NODEID`` resolved for ``node_id``)."""

    path: Path
    od: canopen.ObjectDictionary
    node_id: int
    node_from_file: bool  #: the node id is the DCF's [DeviceComissioning] NodeID
    dcf: bool


def configured(var: ODVariable) -> Any:
    """An object's value as the file configures it: a DCF's ParameterValue, else its
    DefaultValue (None when the file gives neither)."""
    return var.value if var.value is not None else var.default


class _Text:
    """The file's lines, with where each section and key is."""

    def __init__(self, path: Path, text: str) -> None:
        self.path = path
        self.lines = text.splitlines()
        self.where: dict[tuple[str, str], int] = {}
        section = ""
        for n, line in enumerate(self.lines, 1):
            stripped = line.strip()
            if stripped.startswith("[") and stripped.endswith("]"):
                section = stripped[1:-1].strip()
                self.where.setdefault((section.lower(), ""), n)
            elif "=" in stripped and not stripped.startswith(";"):
                key, value = stripped.split("=", 1)
                if not value.split(";", 1)[0].strip():
                    self.lines[n - 1] = ""  # an empty value: the key is absent
                else:
                    self.where.setdefault((section.lower(), key.strip().lower()), n)

    def error(self, section: str, key: str, value: str | None, what: str) -> UserError:
        """What is wrong with ``key`` of ``[section]`` (None ``value``: the key is absent),
        with the line of the key, else of the section."""
        line = self.where.get((section.lower(), key.lower()),
                              self.where.get((section.lower(), "")))
        item = f"[{section}]" + (f" {key}={value}" if key and value is not None else
                                 f" {key}" if key else "")
        return UserError(f"the EDS {str(self.path)!r} cannot be read: "
                         + (f"line {line}, " if line else "") + f"{item}: {what}; correct it in "
                         "the file")


def _int(text: str) -> int:
    return int(text.replace(" ", ""), 0)


def _check_number(t: _Text, cp: configparser.RawConfigParser, section: str, key: str,
                  what: str, lo: int | None = None, hi: int | None = None) -> int | None:
    if not cp.has_option(section, key):
        return None
    raw = cp.get(section, key)
    try:
        value = _int(raw)
    except ValueError:
        raise t.error(section, key, raw, f"{what} must be a number") from None
    if (lo is not None and value < lo) or (hi is not None and value > hi):
        raise t.error(section, key, raw, f"{what} must lie in {lo}..{hi}")
    return value


def _check_value(t: _Text, section: str, key: str, raw: str, dtype: int) -> None:
    """A DefaultValue/ParameterValue/limit python-canopen would convert for ``dtype``."""
    if dtype in (datatypes.VISIBLE_STRING, datatypes.UNICODE_STRING):
        return
    if dtype in (datatypes.OCTET_STRING, datatypes.DOMAIN):
        try:
            bytes.fromhex(raw)
        except ValueError:
            raise t.error(section, key, raw, "not hexadecimal bytes") from None
        return
    try:
        if dtype in datatypes.FLOAT_TYPES:
            float(raw)
        else:
            _int(re.sub(r"\+?\$NODEID\+?", "", raw.upper()) or "0")
    except ValueError:
        kind = "a number" if dtype in datatypes.FLOAT_TYPES else "an integer (or $NODEID+n)"
        raise t.error(section, key, raw, f"not {kind}") from None


def _check_variable(t: _Text, cp: configparser.RawConfigParser, section: str) -> None:
    """The keys python-canopen's build_variable reads of a VAR (or sub-index) section."""
    if not cp.has_option(section, "ParameterName"):
        raise t.error(section, "ParameterName", None, "missing")
    dtype = _check_number(t, cp, section, "DataType", "the data type", 0, 0xFFFF)
    if dtype is None:
        raise t.error(section, "DataType", None, "missing")
    if not cp.has_option(section, "AccessType"):
        raise t.error(section, "AccessType", None, "missing")
    access = cp.get(section, "AccessType")
    if access.strip().lower() not in ACCESS_TYPES:
        raise t.error(section, "AccessType", access,
                      f"not an access type ({', '.join(sorted(ACCESS_TYPES))})")
    _check_number(t, cp, section, "PDOMapping", "PDOMapping", 0, 1)
    for key in ("DefaultValue", "ParameterValue"):
        if cp.has_option(section, key):
            _check_value(t, section, key, cp.get(section, key), dtype)
    if dtype in datatypes.INTEGER_TYPES:
        for key in ("LowLimit", "HighLimit"):
            if cp.has_option(section, key):
                _check_value(t, section, key, cp.get(section, key), dtype)


def _check(t: _Text, cp: configparser.RawConfigParser) -> None:
    for key in _DEVICE_INFO_NUMBERS:
        if cp.has_section("DeviceInfo"):
            _check_number(t, cp, "DeviceInfo", key, key)
    if cp.has_section("DeviceComissioning"):
        _check_number(t, cp, "DeviceComissioning", "NodeID", "the node id", 1, 127)
        _check_number(t, cp, "DeviceComissioning", "Baudrate", "the bit rate (kbit/s)", 1)
    if cp.has_section("Comments"):
        lines = _check_number(t, cp, "Comments", "Lines", "the number of comment lines", 0)
        for k in range(1, (lines or 0) + 1):
            if not cp.has_option("Comments", f"Line{k}"):
                raise t.error("Comments", f"Line{k}", None, f"missing (Lines={lines})")
    objects = {s.upper() for s in cp.sections() if _OBJECT.match(s)}
    for section in cp.sections():
        if re.fullmatch(r"[Dd]ummy[Uu]sage", section):
            for k in range(1, 8):
                _check_number(t, cp, section, f"Dummy{k:04d}", "a dummy usage", 0, 1)
        elif _OBJECT.match(section):
            if not cp.has_option(section, "ParameterName"):
                raise t.error(section, "ParameterName", None, "missing")
            otype = _check_number(t, cp, section, "ObjectType", "the object type", 0, 0xFF)
            if otype in (None, _VAR, _DOMAIN) or (otype == _ARRAY
                                                  and cp.has_option(section, "CompactSubObj")):
                _check_variable(t, cp, section)
        elif m := _SUB.match(section):
            if m.group(1).upper() not in objects:
                raise t.error(section, "", None, f"a sub-index of object {m.group(1)}, which "
                              f"the file does not define (no [{m.group(1)}] section)")
            _check_variable(t, cp, section)
        elif (m := _NAMES.match(section)) and not cp.has_option(section, "NrOfEntries"):
            raise t.error(section, "NrOfEntries", None, "missing")


def read_eds(path: str | Path, node_id: int | None = None) -> EdsFile:
    """Load an EDS or DCF (see the module docstring); :class:`UserError` naming the file,
    line and key when it cannot be read."""
    p = Path(path)
    if not p.is_file():
        raise UserError(f"the EDS {str(p)!r} does not exist or is not a file; {HINT}")
    if p.suffix.lower() not in (".eds", ".dcf"):
        raise UserError(f"the EDS {str(p)!r} does not end in .eds or .dcf; {HINT}")
    try:
        raw = p.read_bytes()
    except OSError as exc:
        raise UserError(f"cannot read the EDS {str(p)!r}: {exc.strerror or exc}") from None
    if b"\0" in raw:
        raise UserError(f"the EDS {str(p)!r} is a binary file, not a CiA 306 text; {HINT}")
    try:
        text = raw.decode("utf-8")
    except UnicodeDecodeError:  # vendors' EDS files are often Latin-1/Windows-1252
        text = raw.decode("cp1252", errors="replace")
    t = _Text(p, text)
    cp = configparser.RawConfigParser(inline_comment_prefixes=(";",), strict=True)
    cp.optionxform = str  # type: ignore[assignment,method-assign]
    clean = "\n".join(t.lines) + "\n"
    try:
        cp.read_string(clean, source=str(p))
    except configparser.Error as exc:
        msg = " ".join(str(exc).split())
        raise UserError(f"the EDS {str(p)!r} cannot be read as CiA 306 ({msg}); {HINT}") from None
    if not any(_OBJECT.match(s) for s in cp.sections()):
        raise UserError(f"the EDS {str(p)!r} has no object sections ([1000], [6040], ...); "
                        f"{HINT}")
    _check(t, cp)
    from_file = None
    if cp.has_option("DeviceComissioning", "NodeID"):
        from_file = _int(cp.get("DeviceComissioning", "NodeID"))
    node = node_id if node_id is not None else from_file if from_file is not None else 1
    src = io.StringIO(clean)
    src.name = str(p)  # python-canopen picks the format by the name's suffix
    try:
        od = canopen.import_od(src, node)
    except Exception as exc:  # what the checks above did not foresee
        msg = " ".join(str(exc).split())[:200]
        raise UserError(f"the EDS {str(p)!r} cannot be read as CiA 306 "
                        f"({type(exc).__name__}: {msg}); {HINT}") from None
    return EdsFile(p, od, node, node_id is None and from_file is not None,
                   p.suffix.lower() == ".dcf")
