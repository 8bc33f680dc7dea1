"""One signal as a DBC describes it, and how the raw values of a frame become its bytes.

A :class:`SignalSpec` is a signal's encoding: its raw value is an integer of ``bits`` bits
(1..64, signed or not) or an IEEE 754 float (REAL32 or REAL64), physical = raw × factor +
offset; with ``start`` it also has its place in a frame (the DBC start bit, Intel or
Motorola byte order), without it the signal follows the previous one, as a CiA 301 PDO
mapping packs its objects (little-endian, one after the other).

:func:`frame_layout` packs and unpacks a frame's raw values. The struct path (one
precompiled :class:`struct.Struct`) serves the common case: every signal byte-aligned,
little-endian, an 8/16/32/64-bit integer or a REAL32/REAL64, in frame order; gaps between
signals and bytes after the last one are zero padding. Anything else a DBC allows (any start
bit, Motorola byte order, any length 1..64) goes through cantools, imported only then.
"""

from __future__ import annotations

import struct
import sys
from collections.abc import Callable
from dataclasses import dataclass, field, replace

__all__ = ["FLOAT_BITS", "MAX_BITS", "FrameLayout", "SignalSpec", "frame_layout"]

#: The longest signal the codec takes, bits (a raw value is at most a 64-bit integer).
MAX_BITS = 64
#: Sizes of the float signals (REAL32, REAL64).
FLOAT_BITS = (32, 64)
#: Largest finite REAL32 and REAL64.
_FLOAT_MAX = {32: struct.unpack("<f", b"\xff\xff\x7f\x7f")[0], 64: sys.float_info.max}
_INT_CODES = {8: "b", 16: "h", 32: "i", 64: "q"}
_FLOAT_CODES = {32: "f", 64: "d"}


@dataclass(frozen=True, slots=True)
class SignalSpec:
    """One signal: name, physical value = raw × factor + offset, raw value of ``bits`` bits
    (an integer, or with ``is_float`` a REAL32/REAL64); ``start``: its DBC start bit in its
    message (None: right after the previous signal), ``big_endian``: Motorola byte order."""

    name: str
    factor: float
    bits: int
    signed: bool
    offset: float = 0.0
    is_float: bool = False
    start: int | None = None
    big_endian: bool = False
    #: the DBC's unit of the physical value (not part of the encoding: not compared)
    unit: str = field(default="", compare=False)

    @property
    def lo(self) -> int | float:
        """Smallest raw value (the largest negative float for a float signal)."""
        if self.is_float:
            return -_FLOAT_MAX[self.bits]
        return -(1 << (self.bits - 1)) if self.signed else 0

    @property
    def hi(self) -> int | float:
        """Largest raw value (the largest finite float for a float signal)."""
        if self.is_float:
            return _FLOAT_MAX[self.bits]
        return (1 << (self.bits - 1)) - 1 if self.signed else (1 << self.bits) - 1

    @property
    def struct_char(self) -> str:
        """The :mod:`struct` code of the raw value; ValueError for a size struct has none
        for (such a signal is packed by cantools)."""
        if self.is_float:
            code = _FLOAT_CODES.get(self.bits)
        else:
            code = _INT_CODES.get(self.bits)
            code = code if code is None or self.signed else code.upper()
        if code is None:
            raise ValueError(f"signal {self.name}: a {self.bits}-bit "
                             f"{'float' if self.is_float else 'integer'} has no struct code")
        return code

    @property
    def unplaced(self) -> SignalSpec:
        """The same encoding without a place in a frame (for a layout built elsewhere)."""
        return replace(self, start=None)


@dataclass(frozen=True, slots=True)
class FrameLayout:
    """``pack(*raws)`` → frame bytes of ``length``; ``unpack(data)`` → the raw values in
    signal order (:class:`struct.error` when ``data`` is not ``length`` bytes); ``fast``:
    the struct path, else cantools."""

    length: int
    pack: Callable[..., bytes]
    unpack: Callable[[bytes | bytearray], tuple]
    fast: bool


def frame_layout(signals: tuple[SignalSpec, ...], length: int | None = None) -> FrameLayout:
    """The packing of ``signals`` in a frame of ``length`` bytes (default: up to the last
    signal's last byte). Signals are placed at their ``start``, or, when none has one, one
    after the other from bit 0 (then each must be little-endian). ValueError when they do
    not fit in the frame, overlap, or mix placed and unplaced signals."""
    signals = _placed(signals)
    end = max((_last_byte(s) + 1 for s in signals), default=0)
    length = end if length is None else length
    if end > length:
        raise ValueError(f"the signals need {end} bytes, the frame has {length}")
    fmt = _struct_format(signals, length)
    if fmt is not None:
        st = struct.Struct(fmt)
        return FrameLayout(length, st.pack, st.unpack, True)
    return _cantools_layout(signals, length)


def _placed(signals: tuple[SignalSpec, ...]) -> tuple[SignalSpec, ...]:
    """The signals with their start bits (a mapping's: one after the other)."""
    starts = [s.start for s in signals]
    if all(x is not None for x in starts):
        return signals
    if any(x is not None for x in starts):
        raise ValueError("some signals have a start bit and some have none: give every "
                         "signal its place, or none")
    out, bit = [], 0
    for s in signals:
        if s.big_endian:
            raise ValueError(f"signal {s.name} is big-endian (Motorola) and has no start bit: "
                             "a PDO mapping packs little-endian values one after the other")
        out.append(replace(s, start=bit))
        bit += s.bits
    return tuple(out)


def _last_byte(s: SignalSpec) -> int:
    """Index of the last byte a placed signal touches."""
    assert s.start is not None
    if not s.big_endian:
        return (s.start + s.bits - 1) // 8
    # Motorola: ``start`` is the most significant bit; the signal runs down to bit 0 of that
    # byte, then on through bits 7..0 of the following bytes.
    first, room = s.start // 8, s.start % 8 + 1
    return first + max(0, -(-(s.bits - room) // 8))


def _struct_format(signals: tuple[SignalSpec, ...], length: int) -> str | None:
    """The struct format of the common case (see the module docstring); None otherwise."""
    parts, pos = ["<"], 0
    for s in signals:
        assert s.start is not None
        if s.big_endian or s.start % 8 or s.start < pos:
            return None
        try:
            code = s.struct_char
        except ValueError:
            return None
        parts.append("x" * ((s.start - pos) // 8) + code)
        pos = s.start + s.bits
    parts.append("x" * (length - pos // 8))
    return "".join(parts)


def _cantools_layout(signals: tuple[SignalSpec, ...], length: int) -> FrameLayout:
    """Raw values ↔ bytes through a cantools message of these signals (no scaling: the
    codec quantises; unused bits are 0)."""
    from cantools.database.can import Message, Signal
    from cantools.database.conversion import IdentityConversion
    from cantools.database.errors import Error

    sigs = [Signal(s.name, s.start or 0, s.bits,
                   "big_endian" if s.big_endian else "little_endian", s.signed,
                   conversion=IdentityConversion(is_float=s.is_float)) for s in signals]
    try:
        msg = Message(0, "frame", length, sigs, strict=True)
    except Error as exc:
        raise ValueError(str(exc)) from None
    names = tuple(s.name for s in signals)
    encode, decode = msg.encode, msg.decode

    def pack(*raws: int | float) -> bytes:
        if len(raws) != len(names):
            raise struct.error(f"pack expected {len(names)} items for packing (got {len(raws)})")
        return encode(dict(zip(names, raws, strict=True)), scaling=False, strict=False)

    def unpack(data: bytes | bytearray) -> tuple:
        if len(data) != length:
            raise struct.error(f"unpack requires a buffer of {length} bytes")
        values = decode(bytes(data), decode_choices=False, scaling=False)
        return tuple(values[n] for n in names)

    return FrameLayout(length, pack, unpack, False)
