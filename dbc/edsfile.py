"""Reading a drive's EDS or DCF (CiA 306) as tools write them, into python-canopen's object
dictionary: the one reader of user files for the gateway and the emulator.

python-canopen reads the standard's form; editors write more. Here, before it reads:

* the text is UTF-8, or Windows-1252 as many vendors' files are; a binary file is refused;
* a key with an empty value (``VendorNumber=``, ``LowLimit=``, as CANopenEditor writes
  them) is left out, as if absent;
* a key that must be a number and is not is named with its line, section and key.

Errors are :class:`EdsError` (a :class:`ValueError`) with a message for the user.
"""

from __future__ import annotations

import io
import re
from pathlib import Path

import canopen

__all__ = ["EdsError", "load_od"]

#: Keys whose values python-canopen reads as numbers (hex or decimal; $NODEID allowed in
#: the value keys).
_NUMBER_KEYS = frozenset({
    "vendornumber", "productnumber", "revisionnumber", "nrofrxpdo", "nroftxpdo",
    "granularity", "simplebootupmaster", "simplebootupslave", "dynamicchannelssupported",
    "groupmessaging", "lss_supported", "objecttype", "datatype", "pdomapping", "subnumber",
    "compactsubobj", "nrofentries", "lowlimit", "highlimit", "lines", "nodeid", "baudrate",
})
_VALUE_KEYS = frozenset({"defaultvalue", "parametervalue", "lowlimit", "highlimit"})
_NUMBER = re.compile(r"^\s*(\$NODEID\s*\+?\s*)?([+-]?(0x[0-9a-f]+|\d+))?(\s*\+?\s*\$NODEID)?\s*$",
                     re.IGNORECASE)


class EdsError(ValueError):
    """An EDS or DCF that cannot be read, with where and why."""


def _text(path: Path) -> str:
    try:
        raw = path.read_bytes()
    except OSError as exc:
        raise EdsError(f"cannot read the EDS {str(path)!r}: {exc.strerror or exc}") from None
    if b"\0" in raw:
        raise EdsError(f"the EDS {str(path)!r} is a binary file, not a CiA 306 text")
    try:
        return raw.decode("utf-8")
    except UnicodeDecodeError:  # vendors' EDS files are often Latin-1/Windows-1252
        return raw.decode("cp1252", errors="replace")


def clean(text: str, source: str) -> str:
    """The text without empty-valued keys; an :class:`EdsError` naming the line of a number
    key that holds something else."""
    out = []
    section = ""
    for n, line in enumerate(text.splitlines(), 1):
        stripped = line.strip()
        if stripped.startswith("[") and stripped.endswith("]"):
            section = stripped[1:-1]
        elif "=" in stripped and not stripped.startswith(";"):
            key, value = (s.strip() for s in stripped.split("=", 1))
            if not value:
                continue  # an empty value: as if the key were absent
            k = key.lower()
            if k in _NUMBER_KEYS and k not in _VALUE_KEYS and not _is_number(value):
                raise EdsError(f"{source}, line {n}: [{section}] {key}={value!r} is not a "
                               "number (decimal or 0x hexadecimal)")
            if k in ("lowlimit", "highlimit") and not _is_number(value) \
                    and not _is_real(value):
                raise EdsError(f"{source}, line {n}: [{section}] {key}={value!r} is not a "
                               "number")
        out.append(line)
    return "\n".join(out) + "\n"


def _is_number(value: str) -> bool:
    m = _NUMBER.match(value)
    return m is not None and (m.group(2) is not None or m.group(1) or m.group(4)) is not None


def _is_real(value: str) -> bool:
    try:
        float(value)
    except ValueError:
        return False
    return True


def load_od(path: str | Path, node_id: int | None = None) -> canopen.ObjectDictionary:
    """The object dictionary of the EDS or DCF at ``path`` for ``node_id`` ($NODEID
    resolved), read as the module docstring says."""
    p = Path(path)
    if not p.is_file():
        raise EdsError(f"the EDS {str(p)!r} does not exist or is not a file")
    text = clean(_text(p), str(p))
    src = io.StringIO(text)
    src.name = str(p)  # python-canopen picks the format by the name's suffix
    try:
        return canopen.import_od(src, node_id)
    except Exception as exc:  # configparser, ValueError, KeyError... from python-canopen
        msg = " ".join(str(exc).split())[:200]
        raise EdsError(f"the EDS {str(p)!r} cannot be read as CiA 306 "
                       f"({type(exc).__name__}: {msg})") from None
