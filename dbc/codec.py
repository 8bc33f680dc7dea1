"""The PDO frames: ``drive.eds`` (object dictionary), ``drive.dbc`` (frames and scalings)
and a fast codec built once from a DBC.

Scalings live only in ``drive.dbc``. Every manufacturer object a PDO maps has an EDS
ParameterName equal to its DBC signal name, so the device derives each object's factor
from the name (:func:`scaling`). Encoding rounds to nearest and saturates at the raw range,
except ``eps_0``, which wraps modulo 2π (modulo 65536 counts).

:func:`parse_dbc` takes what a DBC allows for a PDO: Intel or Motorola byte order, any start
bit, integers of 1..64 bits, REAL32/REAL64 floats, offsets, gaps between signals and bytes
after them. Byte-aligned little-endian integers and floats of struct's sizes are packed by
:mod:`struct`, everything else by cantools (:mod:`dbc.frame`). The messages on CiA 301's
service COB-IDs (NMT, SYNC, EMCY, SDO, heartbeat: :func:`dbc.cia301.is_service`) describe
the rest of the bus for other tools and are not process data: the codec skips them.

A DBC ``X.dbc`` may come with ``X_ab.dbc``: the same bus with the setpoints in the (a, b)
frame (no DBC tool can tell two layouts on one COB-ID apart, so each file has one). The
codec reads both: the messages only ``X_ab.dbc`` has (``RPDO2_AB``) are alternatives of the
message of ``X.dbc`` on their COB-ID.

``load_codec(node_id)`` returns a :class:`PdoCodec`: ``encode``/``decode``/``quantize``
per message name (``RPDO1``, ``RPDO2``, ``RPDO2_AB``, ``RPDO3``, ``TPDO1``..``TPDO3``)
with COB-ID = DBC id − 1 + node id.
"""

from __future__ import annotations

import functools
import logging
import math
import struct
from collections.abc import Callable, Iterable, Mapping
from dataclasses import dataclass
from importlib import resources
from pathlib import Path
from typing import Any

from dbc import diskcache
from dbc.cia301 import is_service
from dbc.filecache import FileMemo, resolved
from dbc.frame import FLOAT_BITS, MAX_BITS, SignalSpec, frame_layout

__all__ = [
    "AB_DBC_PATH",
    "DBC_PATH",
    "EDS_PATH",
    "INT_SIGNALS",
    "STANDARD_DBC_PATH",
    "WRAPPING_SIGNALS",
    "MessageCodec",
    "PdoCodec",
    "SignalSpec",
    "ab_companion",
    "load_codec",
    "load_database",
    "message_codec",
    "parse_dbc",
    "scaling",
    "signal_specs",
]

_FILES = resources.files("dbc")
#: CiA 306 EDS of the emulated drive (``canopen.import_od(str(EDS_PATH), node_id)``).
EDS_PATH: Path = Path(str(_FILES / "drive.eds"))
#: DBC of the emulated drive's bus for node 1, (d, q) setpoints (scalings: the single
#: source).
DBC_PATH: Path = Path(str(_FILES / "drive.dbc"))
#: The same bus with the setpoints in the (a, b) frame (``RPDO2_AB`` on RPDO2's COB-ID).
AB_DBC_PATH: Path = Path(str(_FILES / "drive_ab.dbc"))
#: The emulated drive's bus in CiA 402's standard cyclic modes (CST, CSV), node 1.
STANDARD_DBC_PATH: Path = Path(str(_FILES / "standard.dbc"))
#: What the name of a DBC's (a, b) companion adds to its stem.
AB_SUFFIX = "_ab"

#: Signals decoded as ``int`` (bit fields and counters, factor 1).
INT_SIGNALS: frozenset[str] = frozenset({"controlword", "statusword", "sync_counter"})
#: Signals that wrap instead of saturating (angles). A float signal has no integer range to
#: wrap in: it carries the value as it is.
WRAPPING_SIGNALS: frozenset[str] = frozenset({"eps_0"})
#: The DBC ids are those of node 1.
DBC_NODE_ID = 1
#: The longest PDO on classical CAN, bytes.
MAX_PDO_BYTES = 8


@dataclass(frozen=True, slots=True)
class _Message:
    name: str
    frame_id: int  # node 1
    length: int
    signals: tuple[SignalSpec, ...]  # placed: each with its start bit
    #: the message of the main DBC on the same COB-ID, for one of its (a, b) companion
    alternative_of: str | None = None


def ab_companion(path: Path) -> Path:
    """Where the (a, b) companion of the DBC ``path`` would be (``X.dbc`` → ``X_ab.dbc``)."""
    return path.with_name(f"{path.stem}{AB_SUFFIX}{path.suffix}")


#: Databases read, kept while their files are unchanged (a campaign's points read the same
#: DBC again and again): :func:`_load`'s results by path.
_DATABASES: FileMemo[tuple[Any, dict[str, str | None]]] = FileMemo()
#: :func:`parse_dbc`'s results by path, likewise.
_PARSED: FileMemo[tuple[dict[str, _Message], dict[str, SignalSpec]]] = FileMemo()


def load_database(path: Path = DBC_PATH):
    """``path`` (default ``drive.dbc``) as a cantools database, with the messages that only
    its (a, b) companion (:func:`ab_companion`) has, if there is one; without cantools'
    warning that such a message shares a frame id (it does on purpose). ValueError naming
    the file when one cannot be read. Read once while the files are unchanged
    (:mod:`dbc.filecache`): the database is shared, read-only."""
    return _load(Path(path))[0]


def _load(path: Path) -> tuple[Any, dict[str, str | None]]:
    """The database of :func:`load_database` and its messages taken from the companion:
    name → the message of ``path`` on the same frame id (None if none)."""
    return _DATABASES.get(resolved(path), lambda: (_read(path),
                                                    (path, ab_companion(path))))


def _read(path: Path) -> tuple[Any, dict[str, str | None]]:
    """:func:`_load` from the files."""
    import cantools

    log = logging.getLogger("cantools.database.can.database")
    quiet = _DropDuplicateIdWarning()
    log.addFilter(quiet)
    try:
        try:
            db = cantools.database.load_file(str(path))
        except Exception as exc:  # cantools raises many kinds on a bad file
            raise ValueError(f"{path}: not a readable DBC ({type(exc).__name__}: {exc})"
                             ) from None
        companion = ab_companion(path)
        if not companion.is_file():
            return db, {}
        try:
            ab = cantools.database.load_file(str(companion))
        except Exception as exc:
            raise ValueError(f"{companion}: the (a, b) companion of {path.name} is not a "
                             f"readable DBC ({type(exc).__name__}: {exc})") from None
        by_id = {m.frame_id: m.name for m in db.messages}
        known = {m.name for m in db.messages}
        alternatives: dict[str, str | None] = {}
        for m in ab.messages:
            if m.name not in known:
                db.messages.append(m)
                alternatives[m.name] = by_id.get(m.frame_id)
        db.refresh()
        return db, alternatives
    finally:
        log.removeFilter(quiet)


def parse_dbc(path: Path = DBC_PATH) -> tuple[dict[str, _Message], dict[str, SignalSpec]]:
    """Parse a DBC (and its (a, b) companion) once with cantools, again only when a file
    changed (:mod:`dbc.filecache`; a shared result: read-only): its PDO messages and their
    signals by name; the CANopen service messages are skipped.

    What the codec cannot take raises :class:`ValueError` naming it and what to do: an
    unreadable file, a multiplexed message, an extended (29-bit) id, a message longer than
    8 bytes, a signal longer than 64 bits, a float that is not a REAL32 or REAL64, a factor
    of 0, a signal name used twice with different encodings.
    """
    path = Path(path)
    return _PARSED.get(resolved(path), lambda: (_parse_kept(path),
                                                 (path, ab_companion(path))))


def _parse_kept(path: Path) -> tuple[dict[str, _Message], dict[str, SignalSpec]]:
    """:func:`_parse`, kept on disk between processes (:mod:`dbc.diskcache`: the parse and
    cantools' import were 0.3 s of every command that encodes frames)."""
    companion = ab_companion(path)
    here = Path(__file__).parent
    entry = diskcache.key("dbc", [path, companion if companion.is_file() else None],
                          [here / "codec.py", here / "frame.py", here / "cia301.py"],
                          packages=("cantools",))
    return diskcache.cached(entry, lambda: _parse(path))


def _parse(path: Path) -> tuple[dict[str, _Message], dict[str, SignalSpec]]:
    """:func:`parse_dbc` from the files."""
    db, alternatives = _load(path)
    messages: dict[str, _Message] = {}
    specs: dict[str, SignalSpec] = {}
    for m in db.messages:
        if not m.is_extended_frame and is_service(m.frame_id):
            continue
        where = f"{path}: message {m.name}"
        if m.is_extended_frame:
            raise ValueError(f"{where} has an extended (29-bit) id 0x{m.frame_id:X}; CANopen "
                             "PDOs use 11-bit COB-IDs: give the message its PDO's COB-ID")
        if m.is_multiplexed():
            mux = next(s.name for s in m.signals if s.is_multiplexer)
            raise ValueError(f"{where} is multiplexed (signal {mux}); the codec takes one "
                             "layout per message: describe each layout as a message of its "
                             "own (an alternative mapping in an (a, b) companion DBC)")
        sigs = tuple(_signal_spec(where, s) for s in sorted(m.signals, key=lambda s: s.start))
        if m.length > MAX_PDO_BYTES:
            raise ValueError(f"{where} is {m.length} bytes; a CANopen PDO on classical CAN has "
                             f"at most {MAX_PDO_BYTES}: split it into PDOs of {MAX_PDO_BYTES} "
                             "bytes or fewer")
        for spec in sigs:
            if specs.setdefault(spec.name, spec.unplaced) != spec.unplaced:
                raise ValueError(f"{path}: signal {spec.name} is defined twice, differently "
                                 "(size, type or scaling): give one of them another name")
        try:
            frame_layout(sigs, m.length)  # cantools checked that they fit
        except ValueError as exc:
            raise ValueError(f"{where}: {exc}") from None
        messages[m.name] = _Message(m.name, m.frame_id, m.length, sigs,
                                    alternatives.get(m.name))
    return messages, specs


def _signal_spec(where: str, s: Any) -> SignalSpec:
    """The :class:`SignalSpec` of cantools signal ``s`` of a PDO message (``where``: the
    file and the message, for the refusal of what the codec cannot take)."""
    if s.length > MAX_BITS:
        raise ValueError(f"{where}: signal {s.name} is {s.length} bits; a signal is at most "
                         f"{MAX_BITS} bits: split it into signals of {MAX_BITS} bits or fewer")
    if s.is_float and s.length not in FLOAT_BITS:
        raise ValueError(f"{where}: signal {s.name} is a {s.length}-bit float; a float signal "
                         "is a REAL32 (32 bits) or a REAL64 (64 bits)")
    if not s.scale or not math.isfinite(s.scale) or not math.isfinite(s.offset):
        raise ValueError(f"{where}: signal {s.name} has the scaling ({s.scale},{s.offset}); "
                         "give a finite, non-zero factor and a finite offset")
    return SignalSpec(s.name, float(s.scale), s.length, bool(s.is_signed) or bool(s.is_float),
                      float(s.offset), bool(s.is_float), s.start,
                      s.byte_order == "big_endian", s.unit or "")


def _parse_dbc() -> tuple[dict[str, _Message], dict[str, SignalSpec]]:
    """The built-in ``drive.dbc`` (with its (a, b) companion), parsed."""
    return parse_dbc(DBC_PATH)


class _DropDuplicateIdWarning(logging.Filter):
    """An (a, b) companion's message shares a frame id on purpose."""

    def filter(self, record: logging.LogRecord) -> bool:
        return "identical masked frame ids" not in record.getMessage()


def signal_specs() -> dict[str, SignalSpec]:
    """All DBC signals by name."""
    return dict(_parse_dbc()[1])


def scaling(signal_name: str) -> tuple[float, int, bool]:
    """(factor, bits, signed) of a DBC signal; KeyError naming the known signals otherwise."""
    specs = _parse_dbc()[1]
    try:
        s = specs[signal_name]
    except KeyError:
        raise KeyError(
            f"{signal_name!r} is not a signal of {DBC_PATH.name}; known: {', '.join(specs)}"
        ) from None
    return s.factor, s.bits, s.signed


@functools.lru_cache(maxsize=256)
def _build_raw_function(signals: tuple[SignalSpec, ...]) -> Callable[[Mapping], tuple]:
    """Generate ``values -> raw tuple`` (once per layout: compiling takes about half a
    millisecond, and every run builds its codecs): (value − offset) / factor rounded to nearest (a
    float: to the nearest REAL32/REAL64) and saturated at the raw range; integers of
    :data:`WRAPPING_SIGNALS` wrap modulo their range instead. NaN raises ValueError."""
    lines = ["def raw(v):"]
    out = []
    for k, s in enumerate(signals):
        x = f"x{k}"
        value = f"v[{s.name!r}]" if not s.offset else f"(v[{s.name!r}] - {s.offset!r})"
        lines.append(f"    {x} = {value}" if _exact_int(s) else f"    {x} = {value} / {s.factor!r}")
        if s.is_float:
            nearest = f"_real32({x})" if s.bits == 32 else x
            lines += [f"    if {x} != {x}:", f"        _nan({s.name!r})",
                      f"    {x} = {s.hi!r} if {x} >= {s.hi!r} else "
                      f"({s.lo!r} if {x} <= {s.lo!r} else {nearest})"]
        elif s.name in WRAPPING_SIGNALS and not s.signed:
            lines.append(f"    {x} = round({x}) & {s.hi}")
        elif s.name in WRAPPING_SIGNALS:
            lines.append(f"    {x} = ((round({x}) - {s.lo}) & {s.hi - s.lo}) + {s.lo}")
        else:
            lines.append(
                f"    {x} = {s.hi} if {x} >= {s.hi} else ({s.lo} if {x} <= {s.lo} else round({x}))"
            )
        out.append(x)
    lines.append(f"    return ({', '.join(out)},)" if out else "    return ()")
    ns: dict = {"_real32": _real32, "_nan": _nan}
    exec("\n".join(lines), ns)
    return ns["raw"]


def _exact_int(s: SignalSpec) -> bool:
    """An integer signal of factor 1 wider than a float's 53-bit mantissa: its values stay
    ints, or a float would round them (as cantools does)."""
    return not s.is_float and s.bits > 53 and s.factor == 1.0 and not s.offset


_REAL32 = struct.Struct("<f")


def _real32(x: float) -> float:
    """The REAL32 nearest to ``x`` (|x| within the REAL32 range)."""
    return _REAL32.unpack(_REAL32.pack(x))[0]


def _nan(name: str) -> None:
    raise ValueError(f"{name} is NaN: a signal carries numbers")


@functools.lru_cache(maxsize=256)
def _build_phys_function(signals: tuple[SignalSpec, ...]) -> Callable[[tuple], dict]:
    """Generate (once per layout) ``raw tuple -> {name: raw × factor + offset}`` (the raw
    value itself, an int, for :data:`INT_SIGNALS`)."""
    items = []
    for k, s in enumerate(signals):
        if (s.name in INT_SIGNALS and not s.is_float) or _exact_int(s):
            items.append(f"{s.name!r}: r[{k}]")
        elif s.offset:
            items.append(f"{s.name!r}: r[{k}] * {s.factor!r} + {s.offset!r}")
        else:
            items.append(f"{s.name!r}: r[{k}] * {s.factor!r}")
    ns: dict = {}
    exec(f"def phys(r):\n    return {{{', '.join(items)}}}", ns)
    return ns["phys"]


class MessageCodec:
    """Encoder/decoder of one PDO layout (a DBC message or a mapping built by the device).

    ``raw(values)`` → tuple of raw values (ints; floats for REAL32/REAL64 signals);
    ``pack(*raws)`` → bytes; ``encode(values)`` → bytes; ``decode_raw(data)`` → tuple;
    ``decode(data)`` → {name: physical value}; ``phys(raws)`` → {name: physical value}.
    ``length`` in bytes (default: up to the last signal); ``names`` in order; ``fast``: packed
    by :mod:`struct` (else by cantools, :mod:`dbc.frame`). Signals with a start bit sit there;
    signals without follow each other from bit 0. ``decode``/``decode_raw`` raise
    :class:`struct.error` on a wrong length.
    """

    __slots__ = ("decode_raw", "fast", "frame_id", "length", "name", "names", "pack", "phys",
                 "raw", "signals")

    def __init__(self, name: str, frame_id: int, signals: Iterable[SignalSpec],
                 length: int | None = None) -> None:
        self.name = name
        self.frame_id = frame_id
        self.signals = tuple(signals)
        self.names = tuple(s.name for s in self.signals)
        layout = frame_layout(self.signals, length)
        self.length = layout.length
        self.pack = layout.pack
        self.decode_raw = layout.unpack
        self.fast = layout.fast
        self.raw = _build_raw_function(self.signals)
        self.phys = _build_phys_function(self.signals)

    def encode(self, values: Mapping[str, float]) -> bytes:
        """Physical values (SI; ints for bit fields) → frame data; KeyError if one is missing."""
        return self.pack(*self.raw(values))

    def decode(self, data: bytes | bytearray) -> dict[str, float]:
        """Frame data → physical values (raw × factor + offset)."""
        return self.phys(self.decode_raw(data))

    def __repr__(self) -> str:
        return f"MessageCodec({self.name!r}, 0x{self.frame_id:03X}, {list(self.names)})"


def message_codec(name: str, frame_id: int, signal_names: Iterable[str]) -> MessageCodec:
    """A codec for a custom layout of DBC signals (e.g. a PDO remapped by SDO)."""
    specs = _parse_dbc()[1]
    sigs = []
    for n in signal_names:
        if n not in specs:
            raise KeyError(f"{n!r} is not a signal of {DBC_PATH.name}")
        sigs.append(specs[n])
    return MessageCodec(name, frame_id, sigs)


class PdoCodec:
    """The default PDO frames of one node: ``encode``/``decode``/``quantize`` by message name.

    ``frame_id(name)``: COB-ID for this node. ``names``: message names. ``by_frame_id``:
    COB-ID → name of the default message (``RPDO2_AB`` shares the COB-ID of ``RPDO2``).
    ``messages``: name → :class:`MessageCodec`.
    """

    def __init__(self, node_id: int = 1) -> None:
        if not 1 <= node_id <= 127:
            raise ValueError(f"node id {node_id!r} is outside 1..127")
        self.node_id = node_id
        parsed = _parse_dbc()[0]
        off = node_id - DBC_NODE_ID
        self.messages: dict[str, MessageCodec] = {
            m.name: MessageCodec(m.name, m.frame_id + off, m.signals, m.length)
            for m in parsed.values()
        }
        self.names: tuple[str, ...] = tuple(self.messages)
        self.by_frame_id: dict[int, str] = {
            m.frame_id + off: m.name for m in parsed.values() if m.alternative_of is None
        }
        self._enc = {n: c.encode for n, c in self.messages.items()}
        self._dec = {n: c.decode for n, c in self.messages.items()}

    def frame_id(self, name: str) -> int:
        """COB-ID of message ``name`` for this node."""
        return self.messages[name].frame_id

    def encode(self, name: str, values: Mapping[str, float]) -> bytes:
        """Physical values → frame data (round to nearest, saturate; ``eps_0`` wraps)."""
        return self._enc[name](values)

    def decode(self, name: str, data: bytes | bytearray) -> dict[str, float]:
        """Frame data → physical values (raw × factor; bit fields and counters as int)."""
        return self._dec[name](data)

    def quantize(self, name: str, values: Mapping[str, float]) -> dict[str, float]:
        """What the receiver sees: ``decode(encode(values))``."""
        c = self.messages[name]
        return c.phys(c.raw(values))


def load_codec(node_id: int = 1) -> PdoCodec:
    """The codec of the default PDO frames for ``node_id`` (DBC parsed once per process)."""
    return PdoCodec(node_id)
