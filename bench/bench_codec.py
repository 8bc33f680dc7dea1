"""Benchmark of the PDO codec (dbc/codec.py): the struct path against the cantools fallback.

    .venv/bin/python bench/bench_codec.py            # 20000 calls per repeat, 7 repeats
    .venv/bin/python bench/bench_codec.py --quick    # 2000 calls, 3 repeats

For the built-in TPDO1 (statusword, i_sa, i_sb, sync_counter: 7 bytes) and RPDO2 (four INT16
setpoints: 8 bytes) it times ``MessageCodec.encode`` (physical values → frame bytes: scale,
round, saturate, pack) and ``MessageCodec.decode`` (bytes → physical values) per frame, for
the message as the DBC has it (byte-aligned little-endian integers: the struct path) and
for the same signals in Motorola byte order (what a DBC of a big-endian drive would give:
packed by cantools). Both codecs quantise alike; the benchmark checks that they give the same
values before it times them. Printed: the median over the repeats of µs per frame and the
ratio fallback / fast.

A measurement that fails (the codecs disagree, a codec raises) is a failed measurement:
``FAILED: <reason>`` in its row, exit status 1 (bench/_common.py). ``--json [FILE]`` keys:
``python``, ``calls``, ``repeats``, per message and operation ``<MSG>_<op>_fast_us``,
``<MSG>_<op>_fallback_us`` and ``<MSG>_<op>_ratio`` (``op``: ``encode``, ``decode``),
``failed``.
"""

from __future__ import annotations

import argparse
import statistics
import sys
import timeit
from collections.abc import Callable
from dataclasses import replace

from _common import Figures, RunError, add_json_option, the_run

from dbc import MessageCodec, load_codec

#: Physical values of each message (SI; ints for bit fields and counters).
VALUES: dict[str, dict[str, float]] = {
    "TPDO1": {"statusword": 0x0237, "i_sa": 1.2345, "i_sb": -0.5005, "sync_counter": 7},
    "RPDO2": {"i_sd_ref": 2.5, "i_sq_ref": -1.2344, "u_sd_ref": 120.03, "u_sq_ref": -3.3},
}
OPS = ("encode", "decode")


def codecs(name: str) -> tuple[MessageCodec, MessageCodec]:
    """The built-in message (struct path) and the same signals in Motorola byte order
    (cantools), each signal at the same bytes."""
    fast = load_codec(1).messages[name]
    placed, bit = [], 0
    for s in fast.signals:
        placed.append(replace(s, start=bit + 7, big_endian=True))  # MSB of its first byte
        bit += s.bits
    slow = MessageCodec(name, fast.frame_id, placed, fast.length)
    return fast, slow


def checked_codecs(name: str) -> tuple[MessageCodec, MessageCodec]:
    """:func:`codecs`, with RunError unless they take the paths they are meant to and
    quantise the values alike."""
    with the_run(name):
        fast, slow = codecs(name)
        values = VALUES[name]
        if not fast.fast or slow.fast:
            raise RunError(f"the paths are not struct and cantools (fast: {fast.fast}, "
                           f"fallback: {slow.fast})")
        a, b = fast.decode(fast.encode(values)), slow.decode(slow.encode(values))
        if a != b:
            raise RunError(f"the codecs disagree: struct {a}, cantools {b}")
    return fast, slow


def per_call_us(fn: Callable[[], object], calls: int, repeats: int) -> float:
    """Median over ``repeats`` of µs per call of ``fn`` (``calls`` calls each)."""
    fn()  # warm-up
    return statistics.median(t / calls * 1e6 for t in
                             timeit.repeat(fn, number=calls, repeat=repeats))


def measure(name: str, calls: int, repeats: int) -> dict[str, float]:
    fast, slow = checked_codecs(name)
    values = VALUES[name]
    out: dict[str, float] = {}
    for op in OPS:
        times = []
        for codec in (fast, slow):
            if op == "encode":
                def call(c: MessageCodec = codec) -> object:
                    return c.encode(values)
            else:
                data = codec.encode(values)

                def call(c: MessageCodec = codec, d: bytes = data) -> object:
                    return c.decode(d)
            with the_run(f"{name} {op}"):
                times.append(per_call_us(call, calls, repeats))
        out[f"{name}_{op}_fast_us"], out[f"{name}_{op}_fallback_us"] = times
        out[f"{name}_{op}_ratio"] = times[1] / times[0]
    return out


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--quick", action="store_true", help="short run (2000 calls, 3 repeats)")
    add_json_option(ap)
    args = ap.parse_args(argv)
    calls, repeats = (2000, 3) if args.quick else (20000, 7)
    python = sys.version.split()[0]
    print(f"PDO codec: µs per frame, median of {repeats} repeats of {calls} calls "
          f"(Python {python})")
    print(f"{'message':<9}{'bytes':>6}  {'op':<8}{'fast':>8}{'fallback':>10}{'ratio':>9}")
    fig = Figures(python=python, calls=calls, repeats=repeats)
    for name in VALUES:
        keys = [f"{name}_{op}_{k}" for op in OPS for k in ("fast_us", "fallback_us", "ratio")]
        length = load_codec(1).messages[name].length
        if fig.measure_all(keys, measure, name, calls, repeats) is None:
            print(f"{name:<9}{length:>6}  {fig.show(keys[0])}")
            continue
        for op in OPS:
            v = {k: fig.values[f"{name}_{op}_{k}"] for k in ("fast_us", "fallback_us", "ratio")}
            print(f"{name:<9}{length:>6}  {op:<8}{v['fast_us']:>8.2f}{v['fallback_us']:>10.2f}"
                  f"{v['ratio']:>8.1f}x")
    print("fast: byte-aligned little-endian integers (struct); fallback: the same signals in "
          "Motorola byte order (cantools)")
    fig.report_failures()
    fig.emit(args.json)
    return fig.exit_status()


if __name__ == "__main__":
    raise SystemExit(main())
