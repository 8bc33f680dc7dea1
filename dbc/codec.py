"""The PDO frames: ``drive.eds`` (object dictionary), ``drive.dbc`` (frames and scalings)
and a fast struct-based codec built once from the DBC.

Scalings live only in ``drive.dbc``. Every manufacturer object a PDO maps has an EDS
ParameterName equal to its DBC signal name, so the device derives each object's factor
from the name (:func:`scaling`). Encoding rounds to nearest and saturates at the integer
range, except ``eps_0``, which wraps modulo 2π (modulo 65536 counts).

``load_codec(node_id)`` returns a :class:`PdoCodec`: ``encode``/``decode``/``quantize``
per message name (``RPDO1``, ``RPDO2``, ``RPDO2_AB``, ``RPDO3``, ``TPDO1``..``TPDO3``)
with COB-ID = DBC id − 1 + node id. cantools is used only while loading.
"""

from __future__ import annotations

import functools
import logging
import struct
from collections.abc import Callable, Iterable, Mapping
from dataclasses import dataclass
from importlib import resources
from pathlib import Path

__all__ = [
    "DBC_PATH",
    "EDS_PATH",
    "INT_SIGNALS",
    "WRAPPING_SIGNALS",
    "MessageCodec",
    "PdoCodec",
    "SignalSpec",
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
#: DBC of the default PDO frames for node 1 (scalings: the single source).
DBC_PATH: Path = Path(str(_FILES / "drive.dbc"))

#: Signals decoded as ``int`` (bit fields and counters, factor 1).
INT_SIGNALS: frozenset[str] = frozenset({"controlword", "statusword", "sync_counter"})
#: Signals that wrap instead of saturating (angles).
WRAPPING_SIGNALS: frozenset[str] = frozenset({"eps_0"})
#: The DBC ids are those of node 1.
DBC_NODE_ID = 1
#: Alternative mappings that share the COB-ID of a default one.
ALTERNATIVES: Mapping[str, str] = {"RPDO2_AB": "RPDO2"}


@dataclass(frozen=True, slots=True)
class SignalSpec:
    """One PDO signal: name, physical value = raw × factor, raw integer of ``bits`` bits."""

    name: str
    factor: float
    bits: int
    signed: bool

    @property
    def lo(self) -> int:
        """Smallest raw value."""
        return -(1 << (self.bits - 1)) if self.signed else 0

    @property
    def hi(self) -> int:
        """Largest raw value."""
        return (1 << (self.bits - 1)) - 1 if self.signed else (1 << self.bits) - 1

    @property
    def struct_char(self) -> str:
        """The :mod:`struct` code of the raw integer."""
        code = {8: "b", 16: "h", 32: "i"}[self.bits]
        return code if self.signed else code.upper()


@dataclass(frozen=True, slots=True)
class _Message:
    name: str
    frame_id: int  # node 1
    length: int
    signals: tuple[SignalSpec, ...]


def load_database(path: Path = DBC_PATH):
    """``path`` (default ``drive.dbc``) as a cantools database, without cantools' warning
    that RPDO2 and RPDO2_AB share a frame id (they do on purpose)."""
    import cantools

    log = logging.getLogger("cantools.database.can.database")
    quiet = _DropDuplicateIdWarning()
    log.addFilter(quiet)
    try:
        return cantools.database.load_file(str(path))
    finally:
        log.removeFilter(quiet)


@functools.cache
def parse_dbc(path: Path = DBC_PATH) -> tuple[dict[str, _Message], dict[str, SignalSpec]]:
    """Parse a DBC once with cantools (immutable result): messages and signals by name.

    The fast codec needs byte-aligned little-endian 8/16/32-bit integer signals without
    offset, filling their message; anything else raises :class:`ValueError` naming it.
    """
    try:
        db = load_database(path)
    except Exception as exc:  # cantools raises many kinds on a bad file
        raise ValueError(f"{path}: not a readable DBC ({type(exc).__name__}: {exc})") from None
    messages: dict[str, _Message] = {}
    specs: dict[str, SignalSpec] = {}
    for m in db.messages:
        sigs = []
        bit = 0
        for s in sorted(m.signals, key=lambda s: s.start):
            if s.byte_order != "little_endian" or s.start != bit or s.length not in (8, 16, 32):
                raise ValueError(
                    f"{path}: signal {m.name}.{s.name} is not a byte-aligned little-endian "
                    f"8/16/32-bit integer following the previous one; the fast codec needs that"
                )
            if s.offset != 0 or s.is_float:
                raise ValueError(f"{path}: signal {s.name} has an offset or is a float")
            bit += s.length
            spec = SignalSpec(s.name, float(s.scale), s.length, bool(s.is_signed))
            if specs.setdefault(s.name, spec) != spec:
                raise ValueError(f"{path}: signal {s.name} is defined twice, differently")
            sigs.append(spec)
        if bit != 8 * m.length:
            raise ValueError(
                f"{path}: message {m.name} is {m.length} bytes, signals {bit} bits"
            )
        messages[m.name] = _Message(m.name, m.frame_id, m.length, tuple(sigs))
    return messages, specs


def _parse_dbc() -> tuple[dict[str, _Message], dict[str, SignalSpec]]:
    """The built-in ``drive.dbc``, parsed."""
    return parse_dbc(DBC_PATH)


class _DropDuplicateIdWarning(logging.Filter):
    """RPDO2 and RPDO2_AB share a frame id on purpose."""

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


def _build_raw_function(signals: tuple[SignalSpec, ...]) -> Callable[[Mapping], tuple]:
    """Generate ``values -> raw tuple`` (round to nearest, saturate; wrap for angles)."""
    lines = ["def raw(v):"]
    out = []
    for k, s in enumerate(signals):
        x = f"x{k}"
        lines.append(f"    {x} = v[{s.name!r}] / {s.factor!r}")
        if s.name in WRAPPING_SIGNALS:
            lines.append(f"    {x} = round({x}) & {s.hi}")
        else:
            lines.append(
                f"    {x} = {s.hi} if {x} >= {s.hi} else ({s.lo} if {x} <= {s.lo} else round({x}))"
            )
        out.append(x)
    lines.append(f"    return ({', '.join(out)},)" if out else "    return ()")
    ns: dict = {}
    exec("\n".join(lines), ns)
    return ns["raw"]


def _build_phys_function(signals: tuple[SignalSpec, ...]) -> Callable[[tuple], dict]:
    """Generate ``raw tuple -> {name: raw × factor}`` (ints for :data:`INT_SIGNALS`)."""
    items = []
    for k, s in enumerate(signals):
        if s.name in INT_SIGNALS:
            items.append(f"{s.name!r}: r[{k}]")
        else:
            items.append(f"{s.name!r}: r[{k}] * {s.factor!r}")
    ns: dict = {}
    exec(f"def phys(r):\n    return {{{', '.join(items)}}}", ns)
    return ns["phys"]


class MessageCodec:
    """Encoder/decoder of one PDO layout (a DBC message or a mapping built by the device).

    ``raw(values)`` → tuple of raw integers; ``encode(values)`` → bytes;
    ``decode_raw(data)`` → tuple; ``decode(data)`` → {name: physical value};
    ``phys(raws)`` → {name: physical value}. ``length`` in bytes; ``names`` in order.
    ``decode``/``decode_raw`` raise :class:`struct.error` on a wrong length.
    """

    __slots__ = ("decode_raw", "frame_id", "length", "name", "names", "pack", "phys", "raw",
                 "signals")

    def __init__(self, name: str, frame_id: int, signals: Iterable[SignalSpec]) -> None:
        self.name = name
        self.frame_id = frame_id
        self.signals = tuple(signals)
        self.names = tuple(s.name for s in self.signals)
        st = struct.Struct("<" + "".join(s.struct_char for s in self.signals))
        self.length = st.size
        self.pack = st.pack
        self.decode_raw = st.unpack
        self.raw = _build_raw_function(self.signals)
        self.phys = _build_phys_function(self.signals)

    def encode(self, values: Mapping[str, float]) -> bytes:
        """Physical values (SI; ints for bit fields) → frame data; KeyError if one is missing."""
        return self.pack(*self.raw(values))

    def decode(self, data: bytes | bytearray) -> dict[str, float]:
        """Frame data → physical values (raw × factor)."""
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
            m.name: MessageCodec(m.name, m.frame_id + off, m.signals) for m in parsed.values()
        }
        self.names: tuple[str, ...] = tuple(self.messages)
        self.by_frame_id: dict[int, str] = {
            c.frame_id: c.name for c in self.messages.values() if c.name not in ALTERNATIVES
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
