"""`hil-gateway log` (gateway/buslog.py) on python-can's virtual bus.

Known PDO frames, encoded with cantools from the DBC, are logged in every format, read back
with ``read_log`` and decoded with ``decode_frames`` to exactly cantools' physical values.
"""

from __future__ import annotations

import argparse
import csv
import itertools
import logging
import threading
import time
import uuid
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import can
import cantools
import pytest

from dbc import DBC_PATH
from gateway import buslog
from gateway.buslog import LOG_SUFFIXES, LogOptions, decode_frames, read_log, run_log
from gateway.errors import UserError

#: Signal values (SI) per message; not all on the integer grid, so the codec must round.
VALUES: dict[str, dict[str, float]] = {
    "RPDO1": {"controlword": 0x000F, "eps_0": 1.2345, "w_0": -150.5},
    "RPDO2": {"i_sd_ref": 2.5, "i_sq_ref": -1.2344, "u_sd_ref": 120.03, "u_sq_ref": -3.3},
    "RPDO3": {"T_L": 4.567},
    "TPDO1": {"statusword": 0x0427, "i_sa": 1.234, "i_sb": -0.5005, "sync_counter": 7},
    "TPDO2": {"u_sa": 230.01, "u_sb": -229.99, "u_dc": 560.0},
    "TPDO3": {"w_m": 314.15, "psi_ra": 0.9876, "psi_rb": -0.1234, "T_e": -12.34},
}


@pytest.fixture(scope="module")
def db() -> cantools.database.Database:
    log = logging.getLogger("cantools.database.can.database")
    level = log.level
    log.setLevel(logging.ERROR)  # RPDO2/RPDO2_AB share a frame id on purpose
    try:
        return cantools.database.load_file(str(DBC_PATH))
    finally:
        log.setLevel(level)


def frames(db: cantools.database.Database, node_id: int = 1,
           names: tuple[str, ...] = tuple(VALUES)) -> list[tuple[str, can.Message]]:
    """(name, frame) for each message of VALUES, for ``node_id`` (COB-ID = DBC id - 1 + node)."""
    out = []
    for name in names:
        m = db.get_message_by_name(name)
        out.append((name, can.Message(arbitration_id=m.frame_id - 1 + node_id,
                                      data=m.encode(VALUES[name]), is_extended_id=False)))
    return out


def expected(db: cantools.database.Database, name: str, data: bytes) -> dict[str, Any]:
    """cantools' physical values of a frame."""
    return dict(db.get_message_by_name(name).decode(bytes(data), decode_choices=False))


@pytest.fixture
def channel() -> str:
    return f"test-buslog-{uuid.uuid4().hex[:8]}"


@pytest.fixture
def buses(channel: str) -> Iterator[tuple[can.BusABC, can.BusABC]]:
    """(sender, logger's bus) on one virtual channel."""
    tx = can.Bus(interface="virtual", channel=channel)
    rx = can.Bus(interface="virtual", channel=channel)
    yield tx, rx
    tx.shutdown()
    rx.shutdown()


class Background:
    """run_log in a thread, stopped by its event; join with a timeout (tests never hang)."""

    def __init__(self, bus: can.BusABC, path: Path, options: LogOptions | None = None,
                 **kw: Any) -> None:
        self.stop = threading.Event()
        self.result: buslog.LogResult | None = None
        self.error: BaseException | None = None
        self.thread = threading.Thread(target=self._run, args=(bus, path, options), kwargs=kw,
                                       daemon=True)

    def _run(self, bus: can.BusABC, path: Path, options: LogOptions | None, **kw: Any) -> None:
        try:
            self.result = run_log(bus, path, options, stop=self.stop, **kw)
        except BaseException as exc:  # reported by finish()
            self.error = exc

    def __enter__(self) -> Background:
        self.thread.start()
        time.sleep(0.15)  # the notifier is receiving
        return self

    def finish(self) -> buslog.LogResult:
        self.stop.set()
        self.thread.join(timeout=5.0)
        assert not self.thread.is_alive(), "run_log did not stop within 5 s"
        if self.error is not None:
            raise self.error
        assert self.result is not None
        return self.result

    def __exit__(self, *exc: object) -> None:
        self.stop.set()
        self.thread.join(timeout=5.0)


@pytest.mark.parametrize("suffix", list(LOG_SUFFIXES))
def test_round_trip_exact_values(suffix: str, db, buses, tmp_path: Path) -> None:
    tx, rx = buses
    sent = frames(db)
    path = tmp_path / f"run{suffix}"
    with Background(rx, path, quiet=True) as bg:
        for _, msg in sent:
            tx.send(msg)
        tx.send(can.Message(arbitration_id=0x080, data=b"", is_extended_id=False))  # SYNC
        tx.send(can.Message(arbitration_id=0x701, data=b"\x05", is_extended_id=False))
        time.sleep(0.2)  # the virtual bus delivers at once; the notifier polls at 0.1 s
        result = bg.finish()
    assert result.frames == len(sent) + 2
    assert result.error is None
    assert result.counts == {**{name: 1 for name, _ in sent}, "SYNC": 1, "heartbeat node 1": 1}

    logged = read_log(path)
    assert len(logged) == len(sent) + 2
    assert [m.arbitration_id for m in logged] == [m.arbitration_id for _, m in sent] + [0x80,
                                                                                        0x701]
    rows = decode_frames(logged, node_id=1)
    assert [r["name"] for r in rows] == [name for name, _ in sent]
    for row, (name, msg) in zip(rows, sent, strict=True):
        signals = {k: v for k, v in row.items() if k not in ("t", "name")}
        assert signals == expected(db, name, msg.data)  # bit-exact physical values
        for key, value in VALUES[name].items():  # and within half an LSB of what was sent
            factor = db.get_message_by_name(name).get_signal_by_name(key).scale
            assert signals[key] == pytest.approx(value, abs=factor / 2 + 1e-12)
    ts = [r["t"] for r in rows]
    assert ts == sorted(ts)


def test_decoded_csv_and_live_lines(db, buses, tmp_path: Path) -> None:
    tx, rx = buses
    sent = frames(db, node_id=3)
    out = _Out()
    with Background(rx, tmp_path / "run.asc",
                    LogOptions(node_id=3, decode=True, csv_path=tmp_path / "sig.csv"),
                    out=out, tty=False) as bg:
        for _, msg in sent:
            tx.send(msg)
        # node 1's frames are logged but not decoded for node 3
        for _, msg in frames(db, node_id=1, names=("TPDO1",)):
            tx.send(msg)
        time.sleep(0.2)  # on a pipe: one line per message per second, and at the end
        result = bg.finish()
    assert result.frames == len(sent) + 1
    assert result.decoded == len(sent)
    assert result.counts["TPDO1 node 1"] == 1
    with open(tmp_path / "sig.csv", newline="") as f:
        table = list(csv.DictReader(f))
    assert [r["name"] for r in table] == [name for name, _ in sent]
    for r, (name, msg) in zip(table, sent, strict=True):
        for key, value in expected(db, name, msg.data).items():
            assert float(r[key]) == value
        assert float(r["t"]) > 0
    text = out.getvalue()
    assert "TPDO1" in text and "statusword=0x0427" in text and "i_sa=1.234 A" in text
    assert len(text.splitlines()) <= 2 * len(sent)  # no flooding


class _Out:
    """A non-tty text sink that is safe to write from the logger's thread."""

    def __init__(self) -> None:
        self.parts: list[str] = []
        self.lock = threading.Lock()

    def write(self, s: str) -> int:
        with self.lock:
            self.parts.append(s)
        return len(s)

    def flush(self) -> None:
        pass

    def isatty(self) -> bool:
        return False

    def getvalue(self) -> str:
        with self.lock:
            return "".join(self.parts)


def test_duration_stops(buses, tmp_path: Path) -> None:
    _, rx = buses
    t0 = time.monotonic()
    result = run_log(rx, tmp_path / "run.blf", LogOptions(duration=0.3), quiet=True)
    wall = time.monotonic() - t0
    # at least the duration; at most late by what a loaded host holds a thread, not 10×
    assert 0.29 <= result.duration < 3.0
    assert wall < 5.0
    assert result.frames == 0
    assert read_log(tmp_path / "run.blf") == []


@pytest.mark.parametrize("suffix", [".blf", ".asc", ".trc"])
def test_interrupt_leaves_a_complete_file(suffix: str, db, buses, tmp_path: Path) -> None:
    """Stop (as Ctrl-C/SIGTERM do) while frames stream in: every counted frame is in the file."""
    tx, rx = buses
    path = tmp_path / f"run{suffix}"
    sending = threading.Event()
    sending.set()
    _, frame = frames(db, names=("TPDO1",))[0]

    def sender() -> None:
        for k in itertools.count():
            if not sending.is_set() or k > 100_000:
                return
            tx.send(frame)
            if k % 50 == 0:
                time.sleep(0.001)

    th = threading.Thread(target=sender, daemon=True)
    with Background(rx, path, LogOptions(decode=True), quiet=True) as bg:
        th.start()
        time.sleep(0.3)
        result = bg.finish()  # stop set from this thread while the sender keeps going
    sending.clear()
    th.join(timeout=5.0)
    assert result.frames > 100
    logged = read_log(path)
    assert len(logged) == result.frames
    rows = decode_frames(logged)
    assert len(rows) == result.frames
    assert rows[-1] == {"t": rows[-1]["t"], "name": "TPDO1", **expected(db, "TPDO1", frame.data)}


def test_decode_frames_skips_and_prefers(db) -> None:
    msgs = [m for _, m in frames(db, node_id=2)]
    short = can.Message(arbitration_id=0x182, data=b"\x01\x02", is_extended_id=False)
    ext = can.Message(arbitration_id=0x182, data=msgs[3].data, is_extended_id=True)
    other = can.Message(arbitration_id=0x181, data=msgs[3].data, is_extended_id=False)
    rows = decode_frames([short, ext, other, *msgs], node_id=2)
    assert [r["name"] for r in rows] == list(VALUES)
    ab = decode_frames(msgs, node_id=2, prefer=("RPDO2_AB",))
    assert ab[1]["name"] == "RPDO2_AB"
    assert ab[1]["i_sa_ref"] == rows[1]["i_sd_ref"]  # same bytes, (a, b) layout
    with pytest.raises(UserError, match="not a message"):
        decode_frames(msgs, prefer=("RPDO9",))
    with pytest.raises(UserError, match=r"1\.\.127"):
        decode_frames(msgs, node_id=0)


@pytest.mark.parametrize(("name", "match"), [
    ("run", "has no suffix"),
    ("run.mf5", "unknown log format"),
    ("missing-dir/run.blf", "does not exist"),
    ("adir.blf", "is a directory"),
])
def test_bad_paths(name: str, match: str, buses, tmp_path: Path) -> None:
    _, rx = buses
    (tmp_path / "adir.blf").mkdir()
    with pytest.raises(UserError, match=match):
        run_log(rx, tmp_path / name, LogOptions(duration=0.1), quiet=True)
    with pytest.raises(UserError, match="the raw log file itself"):
        run_log(rx, tmp_path / "a.csv", LogOptions(csv_path=tmp_path / "a.csv", duration=0.1),
                quiet=True)


def test_read_log_errors(tmp_path: Path) -> None:
    with pytest.raises(UserError, match="cannot read"):
        read_log(tmp_path / "nothing.blf")
    with pytest.raises(UserError, match="unknown log format"):
        read_log(tmp_path / "x.txt")


def _parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(prog="hil-gateway")
    sub = parser.add_subparsers(dest="command")
    buslog.add_parser(sub)
    return parser


def test_cli(channel: str, db, tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    args = _parser().parse_args(["log", "-o", str(tmp_path / "run.log"), "--decode",
                                 "--duration", "0.5", "-i", "virtual", "-c", channel,
                                 "--csv", str(tmp_path / "sig.csv")])
    tx = can.Bus(interface="virtual", channel=channel)
    try:
        timer = threading.Timer(0.2, lambda: [tx.send(m) for _, m in frames(db)])
        timer.start()
        assert args.func(args) == 0
        timer.join(timeout=2.0)
    finally:
        tx.shutdown()
    out = capsys.readouterr().out
    assert f"logged {len(VALUES)} frames" in out
    assert "TPDO3 1" in out
    assert len(decode_frames(read_log(tmp_path / "run.log"))) == len(VALUES)


def test_cli_bad_input(tmp_path: Path) -> None:
    parser = _parser()
    args = parser.parse_args(["log", "-o", str(tmp_path / "run"), "-i", "virtual", "-c", "x"])
    with pytest.raises(UserError, match="has no suffix"):
        args.func(args)
    args = parser.parse_args(["log", "-o", str(tmp_path / "run.blf"), "-i", "no-such-bus",
                              "-c", "x"])
    with pytest.raises(UserError, match="no-such-bus"):
        args.func(args)
    args = parser.parse_args(["log", "-o", str(tmp_path / "run.blf"), "--duration", "soon",
                              "-i", "virtual", "-c", "x"])
    with pytest.raises(UserError, match="--duration"):
        args.func(args)


@pytest.mark.parametrize("suffix", [".asc", ".blf"])
def test_cli_on_a_full_disk_says_what_was_kept(suffix: str, channel: str, db, tmp_path: Path,
                                               capsys: pytest.CaptureFixture[str]) -> None:
    """`log` to a file on a full disk (/dev/full): the run's own queued writer keeps the
    frames it could, the account says how many were not written and why, exit 1, no
    traceback (never a false "logged N frames")."""
    target = tmp_path / f"full{suffix}"
    target.symlink_to("/dev/full")
    args = _parser().parse_args(["log", "-o", str(target), "--duration", "0.5", "-i",
                                 "virtual", "-c", channel, "--quiet"])
    tx = can.Bus(interface="virtual", channel=channel)
    try:
        timer = threading.Timer(0.2, lambda: [tx.send(m) for _, m in frames(db) * 50])
        timer.start()
        with pytest.raises(UserError) as err:
            args.func(args)
        timer.join(timeout=2.0)
    finally:
        tx.shutdown()
    assert err.value.exit_code == 1
    assert "No space left on device" in str(err.value) and "Free space" in str(err.value)
    out = capsys.readouterr().out
    assert "NOT written" in out


# ------------------------------------------------------------------- logs cut short


def _numbered(n: int) -> list[can.Message]:
    """``n`` frames each telling its index (id and data), 1 ms apart."""
    return [can.Message(arbitration_id=0x181 + i % 3, data=i.to_bytes(4, "little") + b"\x02",
                        timestamp=1000.0 + i * 1e-3, is_extended_id=False) for i in range(n)]


def _is_prefix(got: list[can.Message], sent: list[can.Message]) -> bool:
    """``got`` are the first ``len(got)`` frames of ``sent``, ids and data exact."""
    return [(m.arbitration_id, bytes(m.data)) for m in got] == [
        (m.arbitration_id, bytes(m.data)) for m in sent[:len(got)]]


def _cut_offsets(data: bytes) -> list[int]:
    """Where to cut a log: its last byte, inside its last object/line, mid-file, early."""
    return sorted({len(data) - 1, len(data) - 3, len(data) - 100, len(data) // 2, 200,
                   100, 50}, reverse=True)


@pytest.mark.parametrize("writer", ["BLFWriter", "BusRecorder"])
def test_blf_cut_short_is_damaged_and_read_up_to_the_cut(writer: str, tmp_path: Path) -> None:
    """A whole BLF log reads back undamaged; the same log cut anywhere (in its last
    container, between containers, in its file header) counts as damaged, with the frames
    before the cut kept exactly."""
    sent = _numbered(3000)
    path = tmp_path / "whole.blf"
    if writer == "BLFWriter":  # many containers, so cuts also fall between them
        w = can.BLFWriter(str(path), max_container_size=4096)
        for m in sent:
            w.on_message_received(m)
        w.stop()
    else:
        rec = buslog.BusRecorder(path)
        for m in sent:
            rec.on_message_received(m)
        rec.stop()
        assert rec.account()["bus_frames_logged"] == len(sent)
    whole = read_log(path)
    assert whole.damaged == 0 and whole.damage == ""
    assert _is_prefix(whole, sent) and len(whole) == len(sent)
    data = path.read_bytes()
    for cut in _cut_offsets(data):
        short = tmp_path / f"cut{cut}.blf"
        short.write_bytes(data[:cut])
        frames_read = read_log(short)
        assert frames_read.damaged >= 1, (cut, len(data))
        assert "cut" in frames_read.damage and "kept" in frames_read.damage
        assert _is_prefix(frames_read, sent), cut
        assert len(frames_read) < len(sent) or cut >= len(data) - 100
    # a cut exactly between two containers (only the file header knows the size)
    if writer == "BLFWriter":
        from can.io.blf import FILE_HEADER_SIZE, OBJ_HEADER_BASE_STRUCT

        first = OBJ_HEADER_BASE_STRUCT.unpack_from(data, FILE_HEADER_SIZE)[3]
        cut = FILE_HEADER_SIZE + first + first % 4
        short = tmp_path / "between.blf"
        short.write_bytes(data[:cut])
        frames_read = read_log(short)
        assert frames_read.damaged == 1 and 0 < len(frames_read) < len(sent)
        assert _is_prefix(frames_read, sent)
        assert f"{cut} of the {len(data)} bytes" in frames_read.damage


def test_blf_of_a_killed_run_is_damaged_not_closed(tmp_path: Path) -> None:
    """The bus log of a run killed after a flush (its header never written at the end):
    every flushed frame is read, and it counts as damaged ("never closed"); once closed it
    is whole."""
    sent = _numbered(500)
    path = tmp_path / "killed.blf"
    rec = buslog.BusRecorder(path)
    try:
        for m in sent:
            rec.on_message_received(m)
        with rec._lock:  # what the writer thread does every second
            rec._drain()
            rec._flush()
        killed = read_log(path)
        assert killed.damaged == 1 and "never closed" in killed.damage
        assert len(killed) == len(sent) and _is_prefix(killed, sent)
    finally:
        rec.stop()
    closed = read_log(path)
    assert closed.damaged == 0 and len(closed) == len(sent)


def test_blf_with_a_damaged_container_keeps_the_frames_before(tmp_path: Path) -> None:
    """A container overwritten in the middle (zlib cannot inflate it): damaged, the frames
    of the containers before it kept."""
    sent = _numbered(3000)
    path = tmp_path / "run.blf"
    w = can.BLFWriter(str(path), max_container_size=4096)
    for m in sent:
        w.on_message_received(m)
    w.stop()
    data = bytearray(path.read_bytes())
    mid = len(data) // 2
    data[mid:mid + 64] = b"\xff" * 64
    path.write_bytes(bytes(data))
    got = read_log(path)
    assert got.damaged >= 1 and got.damage
    assert 0 < len(got) < len(sent) and _is_prefix(got, sent)


@pytest.mark.parametrize("suffix", [".asc", ".csv", ".log", ".trc"])
def test_text_log_cut_mid_line_is_damaged(suffix: str, tmp_path: Path) -> None:
    """A text log whose last line is cut mid-line: damaged, that line's frame (its data may
    be short) left out, the frames before it exact; a whole log is not damaged."""
    sent = _numbered(300)
    path = tmp_path / f"whole{suffix}"
    w = can.Logger(str(path))
    for m in sent:
        w.on_message_received(m)
    w.stop()
    whole = read_log(path)
    assert whole.damaged == 0 and whole.damage == ""
    assert len(whole) == len(sent) and _is_prefix(whole, sent)
    data = path.read_bytes()
    for cut in (len(data) - 5, len(data) - 12, len(data) - 100, len(data) // 2):
        while data[cut - 1:cut] in (b"\n", b"\r"):  # mid-line, not on a line end
            cut -= 1
        short = tmp_path / f"cut{cut}{suffix}"
        short.write_bytes(data[:cut])
        got = read_log(short)
        assert got.damaged >= 1, (cut, data[cut - 40:cut])
        assert "cut mid-line" in got.damage
        assert _is_prefix(got, sent), cut
        assert len(got) < len(sent) or (suffix == ".asc" and cut > len(data) - 20)


def test_asc_log_never_closed_is_damaged(tmp_path: Path) -> None:
    """An ASC log without its closing "End TriggerBlock" (its writer was killed) counts as
    damaged; all its frames are read."""
    sent = _numbered(50)
    path = tmp_path / "run.asc"
    w = can.Logger(str(path))
    for m in sent:
        w.on_message_received(m)
    w.stop()
    text = path.read_text()
    assert text.rstrip().endswith("End TriggerBlock")
    path.write_text(text[:text.rindex("End TriggerBlock")])
    got = read_log(path)
    assert got.damaged == 1 and "End TriggerBlock" in got.damage
    assert len(got) == len(sent) and _is_prefix(got, sent)
