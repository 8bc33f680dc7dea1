"""`hil-gateway log`: record the bus to a file, optionally decode the drive's PDOs.

The raw log goes through python-can's writers, chosen by the file suffix
(:data:`LOG_SUFFIXES`). With ``--decode`` the PDOs of one node are decoded with the DBC
(SI units) and shown live, at most 10 times a second; with ``--csv FILE`` every decoded
frame becomes one CSV row (time, message name, signals).

Frames are received by a :class:`can.Notifier` thread; on every exit path (duration over,
Ctrl-C, SIGTERM, bus error) the notifier is stopped first and the files are closed after
it, so everything received is written.

The same decoding serves recorded logs: ``decode_frames(read_log("run.blf"), node_id=1)``.
"""

from __future__ import annotations

import argparse
import contextlib
import csv
import functools
import io
import logging
import signal
import struct
import sys
import threading
import time
from collections import Counter, deque
from collections.abc import Iterable, Iterator
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, NamedTuple, TextIO

import can

from dbc.bus import add_bus_options, bus_config, open_bus
from gateway.drive_profile import DriveProfile
from gateway.errors import UserError
from gateway.logformat import LOG_SUFFIXES
from gateway.outpath import check_writable

log = logging.getLogger(__name__)

#: The live display refreshes at most this often (s); a pipe gets one line per message/s.
DISPLAY_PERIOD = 0.1
PIPE_PERIOD = 1.0

# CANopen pre-defined connection set: function code (COB-ID & 0x780) → name.
_FUNCTION = {0x180: "TPDO1", 0x200: "RPDO1", 0x280: "TPDO2", 0x300: "RPDO2", 0x380: "TPDO3",
             0x400: "RPDO3", 0x480: "TPDO4", 0x500: "RPDO4", 0x580: "SDO tx", 0x600: "SDO rx",
             0x700: "heartbeat", 0x080: "EMCY"}


# ----------------------------------------------------------------------------- files


def check_log_path(path: str | Path, option: str = "-o") -> Path:
    """Validate a log file name: known suffix, existing writable directory; UserError if not."""
    p = Path(path)
    known = ", ".join(f"{s} ({what})" for s, what in LOG_SUFFIXES.items())
    suffix = p.suffix.lower()
    if not suffix:
        raise UserError(f"{option} {str(path)!r} has no suffix, so the log format is unknown: "
                        f"name the file with one of {known}, e.g. {p.name}.blf")
    if suffix not in LOG_SUFFIXES:
        raise UserError(f"{option} {str(path)!r}: unknown log format {suffix!r}; use one of "
                        f"{known}")
    check_writable(p, option)
    return p


def write_frame(writer: can.Listener, msg: can.Message) -> None:
    """Write one frame with a python-can writer. BLF stores the channel as a small integer
    taken from the digits of its name; a name whose number does not fit (virtual channels
    named with a counter or a clock) is written as the default channel instead."""
    try:
        writer.on_message_received(msg)
    except struct.error:
        msg.channel = None
        writer.on_message_received(msg)


#: The bus log's queue holds at most this many frames (beyond, frames are dropped, counted).
MAX_QUEUED = 200_000
#: The bus log is flushed to the file this often, s.
FLUSH_PERIOD = 1.0


class BusRecorder(can.Listener):
    """The raw bus log: frames queued in the receive thread, written by a writer thread.

    Queuing costs the control cycle a deque append. The queue is bounded
    (:data:`MAX_QUEUED` frames): beyond it frames are dropped and counted. The writer thread
    flushes the file every :data:`FLUSH_PERIOD` s, so after a crash (kill -9) the log is
    readable up to the last flush. A write error (a full disk) stops the writing and is
    kept in :attr:`error`; the run goes on and reports it. :meth:`stop` drains what is
    queued and closes the file on every exit path.
    """

    def __init__(self, path: Path) -> None:
        try:
            self._writer = can.Logger(str(path))
        except (OSError, ValueError) as exc:
            raise UserError(f"cannot write the bus log {str(path)!r}: {exc}") from exc
        self.path = path
        self.count = 0
        self.dropped = 0
        self.error = ""
        self._queue: deque[can.Message] = deque()
        self._stop = threading.Event()
        self._lock = threading.Lock()  # one writer at a time (thread, or stop())
        self._thread = threading.Thread(target=self._drain_loop, name="bus-log", daemon=True)
        self._thread.start()

    def on_message_received(self, msg: can.Message) -> None:
        if len(self._queue) < MAX_QUEUED and not self.error:
            self._queue.append(msg)
        else:
            self.dropped += 1

    def _drain(self) -> None:
        q = self._queue
        writer = self._writer
        while q:
            msg = q.popleft()
            if self.error:
                self.dropped += 1
                continue
            try:
                write_frame(writer, msg)
                self.count += 1
            except (OSError, ValueError) as exc:
                self.error = f"writing {self.path} failed after {self.count} frames: {exc}"
                self.dropped += 1
                log.error("bus log: %s", self.error)

    def _flush(self) -> None:
        """Make what was written readable after a crash (BLF: close the open container)."""
        if self.error:
            return
        try:
            flush_container = getattr(self._writer, "_flush", None)  # BLFWriter's container
            if flush_container is not None:
                flush_container()
            file = getattr(self._writer, "file", None)
            if file is not None:
                file.flush()
        except (OSError, ValueError) as exc:
            self.error = f"writing {self.path} failed after {self.count} frames: {exc}"
            log.error("bus log: %s", self.error)

    def _drain_loop(self) -> None:
        next_flush = time.monotonic() + FLUSH_PERIOD
        while not self._stop.wait(0.05):
            with self._lock:
                self._drain()
                if time.monotonic() >= next_flush:
                    next_flush += FLUSH_PERIOD
                    self._flush()

    def stop(self) -> None:
        """Write what is queued, flush and close (idempotent)."""
        if self._stop.is_set():
            return
        self._stop.set()
        self._thread.join(2.0)
        with self._lock:
            self._drain()
            try:
                self._writer.stop()
            except (OSError, ValueError) as exc:
                if not self.error:
                    self.error = f"closing {self.path} failed after {self.count} frames: {exc}"

    def account(self) -> dict[str, Any]:
        """For the summary: frames written, dropped, the error if any."""
        return {"bus_log": self.path.name, "bus_frames_logged": self.count,
                "bus_frames_dropped": self.dropped, "bus_log_error": self.error or None}


class Frames(list):
    """The frames of a log; :attr:`damaged` counts what could not be read (lines of a text
    log, or the unreadable tail of a binary one), :attr:`damage` says what and where ("" when
    the log is whole)."""

    damaged: int = 0
    damage: str = ""

    def note(self, what: str, count: int = 1) -> None:
        """Count ``count`` damaged records, described by ``what``."""
        self.damaged += count
        self.damage = f"{self.damage}; {what}" if self.damage else what


#: The text readers, for reading a damaged log line by line.
_TEXT_READERS = {".asc": can.ASCReader, ".csv": can.CSVReader,
                 ".log": can.CanutilsLogReader, ".trc": can.TRCReader}

#: How the end of a log cut short is described, and what to do about it.
_CUT_HINT = ("the frames before it are kept, the rest is lost (a run killed mid-write or a copy "
             "cut short: copy the log again if its original is whole)")


def _is_header(suffix: str, line: str, index: int) -> bool:
    if suffix == ".csv":
        return index == 0
    if suffix == ".trc":
        return line.startswith(";")
    return False


def _is_event(suffix: str, line: str) -> bool:
    """A line of a text log that is neither header nor frame (ASC events, blank lines)."""
    return not line.strip() or (suffix == ".asc" and ("Start of measurement" in line
                                                      or line.startswith("End")))


class _TextLog(NamedTuple):
    """A text log split for reading line by line."""

    header: str  # the lines every frame line is read with
    body: list[str]  # the lines that should each be a frame
    end: str  # why the end of the file is damaged; "" if it is not
    cut: bool  # the last line was cut mid-line: it is not in ``body``


def _text_end(suffix: str, lines: list[str]) -> tuple[str, bool]:
    """Why the end of a text log is damaged ("" if it is not), and whether its last line was
    cut mid-line. python-can's writers end every line, so a last line without its line end
    was cut; an ASC log ends with "End TriggerBlock"."""
    last = lines[-1] if lines else ""
    if suffix == ".asc" and last.strip().lower() == "end triggerblock":
        return "", False
    if last and not last.endswith(("\n", "\r")):
        return (f"the last line is cut mid-line (no line end): {last.strip()[:40]!r} is not "
                f"read; {_CUT_HINT}. A log edited by hand: end its last line"), True
    tail = next((line for line in reversed(lines) if line.strip()), "")
    if suffix == ".asc" and lines and tail.strip().lower() != "end triggerblock":
        return ("it ends without \"End TriggerBlock\": its writer never closed it; "
                f"{_CUT_HINT}"), False
    return "", False


def _frame_lines(p: Path, suffix: str) -> _TextLog:
    """The header of a text log, its lines that should each be a frame, and its end."""
    lines = p.read_text(encoding="utf-8", errors="replace").splitlines(keepends=True)
    end, cut = _text_end(suffix, lines)
    if cut:
        lines = lines[:-1]
    if suffix == ".asc":  # the header ends with "Begin Triggerblock"
        first = next((i + 1 for i, line in enumerate(lines)
                      if line.lower().startswith("begin triggerblock")), 0)
        header, rest = "".join(lines[:first]), lines[first:]
        return _TextLog(header, [line for line in rest if not _is_event(suffix, line)], end,
                        cut)
    header = "".join(line for i, line in enumerate(lines) if _is_header(suffix, line, i))
    body = [line for i, line in enumerate(lines)
            if not _is_header(suffix, line, i) and not _is_event(suffix, line)]
    return _TextLog(header, body, end, cut)


def _read_lines(header: str, body: list[str], suffix: str) -> Frames:
    """A damaged text log, line by line: each frame line read with the file's header; a
    line that gives no frame is damaged."""
    reader = _TEXT_READERS[suffix]
    out = Frames()
    bad: list[str] = []
    for line in body:
        try:
            got = list(reader(io.StringIO(header + line)))
        except Exception:  # python-can's readers raise anything on a bad line
            got = []
        if got:
            out.extend(got)
        else:
            bad.append(line)
    if bad:
        out.note(f"{len(bad)} line(s) give no frame, the first: {bad[0].strip()[:40]!r}",
                 len(bad))
    return out


def _blf_damage(p: Path) -> str:
    """Why the BLF log ``p`` is damaged, "" if it is whole: its objects (log containers) are
    walked by their headers, and the file's size is compared with the one its file header
    names (written when the log is closed)."""
    from can.io.blf import FILE_HEADER_STRUCT, OBJ_HEADER_BASE_STRUCT

    size = p.stat().st_size
    with p.open("rb") as f:
        head = f.read(FILE_HEADER_STRUCT.size)
        if len(head) < FILE_HEADER_STRUCT.size:
            return f"the file header is cut (the file has {size} bytes)"
        fields = FILE_HEADER_STRUCT.unpack(head)
        if fields[0] != b"LOGG":
            return "no BLF file header (it does not start with 'LOGG')"
        header_size, file_size = fields[1], fields[10]
        pos = header_size
        while pos < size:
            f.seek(pos)
            base = f.read(OBJ_HEADER_BASE_STRUCT.size)
            if len(base) < OBJ_HEADER_BASE_STRUCT.size:
                return f"cut inside the object header at byte {pos}"
            signature, _, _, obj_size, _ = OBJ_HEADER_BASE_STRUCT.unpack(base)
            if signature != b"LOBJ" or obj_size < OBJ_HEADER_BASE_STRUCT.size:
                return f"no valid object at byte {pos} (overwritten or not a BLF log)"
            if pos + obj_size > size:
                return (f"the log container at byte {pos} is cut: {size - pos} of its "
                        f"{obj_size} bytes are in the file")
            pos += obj_size + obj_size % 4  # the padding
    if file_size > size:
        return f"cut short: {size} of the {file_size} bytes its header names"
    if file_size < size:
        return (f"never closed: its header names {file_size} of its {size} bytes (its writer "
                "was killed or failed before closing it); frames after its last flush are "
                "missing")
    return ""


def read_log(path: str | Path) -> Frames:
    """All frames of a log written by `hil-gateway log` or a run (any python-can-readable
    log). Damaged lines are skipped and counted (:attr:`Frames.damaged`, described by
    :attr:`Frames.damage`), so is a last line cut mid-line; a binary log is read up to its
    damage (e.g. the tail of a log cut by kill -9, or a file cut short), which counts 1."""
    p = Path(path)
    suffix = p.suffix.lower()
    if suffix not in LOG_SUFFIXES:
        raise UserError(f"{str(path)!r}: unknown log format {p.suffix!r}; python-can reads "
                        f"{', '.join(LOG_SUFFIXES)}")
    if not p.is_file():
        raise UserError(f"cannot read the log {str(p)!r}: no such file")
    out = Frames()
    failed = ""
    try:
        with can.LogReader(p) as reader:
            for msg in reader:
                out.append(msg)
    except OSError as exc:
        raise UserError(f"cannot read the log {str(p)!r}: {exc.strerror or exc}") from exc
    except Exception as exc:  # a damaged record: the text readers retry line by line below
        name = type(exc).__name__
        if name == "error":  # struct.error, zlib.error
            name = f"{type(exc).__module__}.error"
        failed = f"{name}: {exc}" if str(exc) else name
    if suffix in _TEXT_READERS:
        text = _frame_lines(p, suffix)
        if failed or text.cut or len(out) != len(text.body):  # a line skipped or failed
            out = _read_lines(text.header, text.body, suffix)
        if text.end:
            out.note(text.end)
    elif suffix == ".blf":
        why = _blf_damage(p)
        if failed:
            why = f"{why or f'unreadable after {len(out)} frames'} ({failed})"
        if why:
            out.note(f"{why}; {_CUT_HINT}")
    elif failed:
        out.note(f"unreadable after {len(out)} frames ({failed}); {_CUT_HINT}")
    if out.damaged:
        log.warning("%s: %d damaged, %d frames read: %s", p, out.damaged, len(out),
                    out.damage)
    return out


# -------------------------------------------------------------------------- decoding


def _codec(node_id: int) -> Any:
    from dbc import load_codec

    try:
        return load_codec(node_id)
    except ValueError as exc:
        raise UserError(f"--node {node_id}: {exc}; a CANopen node id is 1..127") from exc


def _checked(codec: Any) -> Any:
    """``codec.decode`` refusing (struct.error) a frame not of the PDO's length."""
    def decode(data: bytes) -> dict[str, float]:
        if len(data) != codec.length:
            raise struct.error(f"{len(data)} bytes, the PDO has {codec.length}")
        return codec.decode(data)
    return decode


def _profile_decoders(drive: DriveProfile, node_id: int | None
                      ) -> dict[int, tuple[str, Any]]:
    """COB-ID → (message name, decode → {role: value}) of a drive profile's PDOs (its DBC,
    its [signals]; the setpoint layout is the profile's setpoint message)."""
    from gateway.process_data import process_data

    pd = process_data(drive, node_id)
    return {p.cob_id: (p.name, _checked(p.codec)) for p in pd.pdos}


def _drive_columns(drive: DriveProfile, node_id: int | None) -> list[str]:
    from gateway.process_data import process_data

    cols = ["t", "name"]
    for p in sorted(process_data(drive, node_id).pdos, key=lambda p: p.name):
        cols += [r for r in p.roles if r not in cols]
    return cols


def _decoders(node_id: int | None, prefer: Iterable[str] = (),
              drive: DriveProfile | None = None) -> dict[int, tuple[str, Any]]:
    """COB-ID → (message name, decode(data) → {signal: value}) for the node's PDOs.

    With ``drive`` the drive profile's process data (values by role name, at ``node_id`` or
    the profile's node). Without it the built-in DBC at ``node_id``: ``prefer`` names
    alternative layouts that share a COB-ID (``RPDO2_AB``) to use instead of the default
    one. A frame whose length is not its PDO's raises ``struct.error``.
    """
    if drive is not None:
        if prefer:
            raise UserError("with a drive profile its setpoint message gives the layout; "
                            "prefer is for the built-in DBC")
        return _profile_decoders(drive, node_id)
    node_id = 1 if node_id is None else node_id
    codec = _codec(node_id)
    table = {fid: (name, _checked(codec.messages[name]))
             for fid, name in codec.by_frame_id.items()}
    for name in prefer:
        if name not in codec.messages:
            raise UserError(f"{name!r} is not a message of the DBC; known: "
                            f"{', '.join(codec.names)}")
        c = codec.messages[name]
        table[c.frame_id] = (name, _checked(c))
    return table


def _iter_decoded(messages: Iterable[can.Message], table: dict[int, tuple[str, Any]],
                  errors: Counter[str] | None = None) -> Iterator[dict[str, Any]]:
    """Decoded rows; frames of a PDO's COB-ID with another length are counted in ``errors``
    (by message name), not decoded."""
    for m in messages:
        if m.is_extended_id or m.is_remote_frame or m.is_error_frame:
            continue
        entry = table.get(m.arbitration_id)
        if entry is None:
            continue
        name, decode = entry
        try:
            values = decode(bytes(m.data))
        except struct.error:  # wrong length: not this PDO's frame
            if errors is not None:
                errors[name] += 1
            continue
        yield {"t": m.timestamp, "name": name, **values}


def decode_frames(messages: Iterable[can.Message], node_id: int | None = None,
                  prefer: Iterable[str] = (), drive: DriveProfile | None = None,
                  errors: Counter[str] | None = None) -> list[dict[str, Any]]:
    """Decode the PDOs of ``node_id`` among ``messages`` with the DBC, in order.

    Each row is ``{'t': timestamp, 'name': 'TPDO1', <signal>: <physical value>, ...}`` (SI
    units; controlword, statusword and sync_counter as int). Frames that are not one of the
    node's PDOs, or have the wrong length for it, are skipped. ``prefer=("RPDO2_AB",)``
    decodes COB-ID 0x300 + node with the (a, b) setpoint layout instead of (d, q).

    ``drive``: decode with that drive profile's process data instead (role names, its DBC's
    scalings, its setpoint layout); ``node_id`` defaults to the profile's (else 1). Frames
    of a PDO's COB-ID with another length are counted in ``errors`` (by name) if given.
    """
    return list(_iter_decoded(messages, _decoders(node_id, prefer, drive), errors))


def csv_columns(node_id: int | None = 1, prefer: Iterable[str] = (),
                drive: DriveProfile | None = None) -> list[str]:
    """The header of the decoded CSV: t, name and every signal of the decoded messages."""
    if drive is not None:
        return _drive_columns(drive, node_id)
    node_id = 1 if node_id is None else node_id
    cols = ["t", "name"]
    codec = _codec(node_id)
    for name, _ in sorted(_decoders(node_id, prefer).values(), key=lambda e: e[0]):
        cols += [s for s in codec.messages[name].names if s not in cols]
    return cols


@functools.cache
def _units() -> dict[str, str]:
    """Signal name → unit, from the DBC (for the live display)."""
    from dbc import load_database

    db = load_database()
    return {s.name: (s.unit or "") for m in db.messages for s in m.signals}


def _fmt(name: str, value: Any) -> str:
    if name in ("controlword", "statusword"):
        return f"{name}=0x{int(value):04X}"
    if isinstance(value, int):
        return f"{name}={value}"
    unit = _units().get(name, "")
    return f"{name}={value:.4g}" + (f" {unit}" if unit else "")


def classify(msg: can.Message, node_id: int, pdo_names: dict[int, str]) -> str:
    """A short label for the per-message account: the node's PDO name or the CANopen service."""
    if msg.is_error_frame:
        return "error frame"
    if msg.is_extended_id:
        return "extended id"
    cob = msg.arbitration_id
    if cob in pdo_names:
        return pdo_names[cob]
    if cob == 0x000:
        return "NMT"
    if cob == 0x080:
        return "SYNC"
    if cob == 0x100:
        return "TIME"
    if cob in (0x7E4, 0x7E5):
        return "LSS"
    func, node = cob & 0x780, cob & 0x7F
    if func in _FUNCTION and node:
        kind = _FUNCTION[func]
        if func == 0x700 and msg.dlc >= 1 and msg.data[0] == 0:
            kind = "boot-up"
        return f"{kind} node {node}"
    return f"0x{cob:03X}"


# ---------------------------------------------------------------------------- record


@dataclass
class LogResult:
    """What a logging run did (the account printed at the end)."""

    path: Path
    frames: int = 0
    decoded: int = 0
    duration: float = 0.0
    counts: Counter[str] = field(default_factory=Counter)
    csv_path: Path | None = None
    error: BaseException | None = None
    #: frames on a decoded PDO's COB-ID whose length is not the PDO's, by message name
    decode_errors: Counter[str] = field(default_factory=Counter)
    #: the raw log: frames written, frames not written (a full disk, a full queue), and why
    written: int = 0
    dropped: int = 0
    write_error: str = ""

    def account(self) -> str:
        """Frames logged, per-message counts and duration, a few lines."""
        rate = self.frames / self.duration if self.duration > 0 else 0.0
        lines = [f"logged {self.written} frames in {self.duration:.2f} s ({rate:.0f}/s) to "
                 f"{self.path}"]
        if self.write_error or self.dropped:
            lines[0] = (f"received {self.frames} frames in {self.duration:.2f} s; "
                        f"{self.written} written to {self.path}, {self.dropped} NOT written"
                        + (f" ({self.write_error})" if self.write_error else ""))
        if self.csv_path is not None:
            lines[0] += f"; {self.decoded} decoded rows to {self.csv_path}"
        if self.counts:
            items = [f"{k} {v}" for k, v in sorted(self.counts.items(),
                                                    key=lambda kv: (-kv[1], kv[0]))]
            lines.append("  " + ", ".join(items))
        if self.decode_errors:
            items = [f"{k} {v}" for k, v in sorted(self.decode_errors.items())]
            lines.append(f"  {sum(self.decode_errors.values())} frame(s) not decoded, their "
                         f"length is not their PDO's: {', '.join(items)}")
        return "\n".join(lines)


class _Recorder(can.Listener):
    """Hands every frame to the raw log (:class:`BusRecorder`, the writer a run uses too);
    decodes the node's PDOs for the display and CSV.

    Runs in the notifier thread; :meth:`close` (idempotent, also called by the notifier's
    ``stop``) drains and closes the files; frames arriving after it are dropped.
    """

    def __init__(self, writer: BusRecorder, node_id: int, decode: bool,
                 csv_file: TextIO | None, prefer: Iterable[str] = (),
                 drive: DriveProfile | None = None, sampler: Any = None) -> None:
        self.writer = writer
        self.node_id = node_id
        self.table = _decoders(node_id, prefer, drive)
        self.errors: Counter[str] = Counter()
        self.pdo_names = {fid: name for fid, (name, _) in self.table.items()}
        self.sampler = sampler  # the live scope's rows (LatestValues), or None
        self.decode = decode or csv_file is not None or sampler is not None
        self.lock = threading.Lock()
        self.frames = 0
        self.decoded = 0
        self.counts: Counter[str] = Counter()
        self.latest: dict[str, dict[str, Any]] = {}
        self.fresh: set[str] = set()
        self.error: BaseException | None = None
        self.t_first: float | None = None  # timestamp of the first frame
        self.closed = False
        self.csv_file = csv_file
        self.csv: csv.DictWriter | None = None
        if csv_file is not None:
            self.csv = csv.DictWriter(csv_file, csv_columns(node_id, prefer, drive),
                                      restval="",
                                      lineterminator="\n")
            self.csv.writeheader()

    def on_message_received(self, msg: can.Message) -> None:
        with self.lock:
            if self.closed:
                return
            self.writer.on_message_received(msg)
            if self.t_first is None:
                self.t_first = msg.timestamp
            self.frames += 1
            self.counts[classify(msg, self.node_id, self.pdo_names)] += 1
            if not self.decode:
                return
            for row in _iter_decoded((msg,), self.table, self.errors):
                self.decoded += 1
                self.latest[row["name"]] = row
                self.fresh.add(row["name"])
                if self.sampler is not None:
                    self.sampler.update(row["t"], row)
                if self.csv is not None:
                    self.csv.writerow(row)

    def on_error(self, exc: Exception) -> None:
        """A receive error ends the run (the notifier thread stops after this)."""
        self.error = exc

    def flush(self) -> None:
        """Push the decoded CSV to the OS (called from the main thread about once a second)."""
        with self.lock:
            if not self.closed and self.csv_file is not None:
                self.csv_file.flush()

    def close(self) -> None:
        """Flush and close the raw log and the CSV, once."""
        with self.lock:
            if self.closed:
                return
            self.closed = True
            try:
                self.writer.stop()
            finally:
                if self.csv_file is not None:
                    self.csv_file.close()

    def stop(self) -> None:
        """Called by :meth:`can.Notifier.stop`."""
        self.close()


class _Display:
    """The live view: a refreshing table on a terminal, one line per message/s on a pipe."""

    def __init__(self, out: TextIO, rec: _Recorder, decode: bool, tty: bool | None) -> None:
        self.out = out
        self.rec = rec
        self.decode = decode
        self.tty = out.isatty() if tty is None else tty
        self.period = DISPLAY_PERIOD if self.tty else PIPE_PERIOD
        self._next = time.monotonic() + self.period
        self._lines = 0
        self._t0 = time.monotonic()

    def tick(self, final: bool = False) -> None:
        now = time.monotonic()
        if now < self._next and not final:
            return
        self._next = now + self.period
        with self.rec.lock:
            latest = {k: dict(v) for k, v in self.rec.latest.items()}
            fresh, self.rec.fresh = self.rec.fresh, set()
            frames = self.rec.frames
        if self.tty:
            self._redraw(latest, frames, now - self._t0)
        elif self.decode:
            for name in sorted(fresh):
                self.out.write(self._line(latest[name]) + "\n")
            self.out.flush()

    def _line(self, row: dict[str, Any]) -> str:
        sigs = " ".join(_fmt(k, v) for k, v in row.items() if k not in ("t", "name"))
        t = row["t"] - (self.rec.t_first or 0.0)  # since the first frame logged
        return f"{t:8.3f} {row['name']:<8} {sigs}"

    def _redraw(self, latest: dict[str, dict[str, Any]], frames: int, elapsed: float) -> None:
        lines = [f"{frames} frames, {elapsed:.1f} s"]
        if self.decode:
            lines += [self._line(latest[name]) for name in sorted(latest)]
        text = ""
        if self._lines:
            text += f"\x1b[{self._lines}F"  # cursor up to the first line of the table
        text += "".join(f"\x1b[2K{line}\n" for line in lines)
        self._lines = len(lines)
        self.out.write(text)
        self.out.flush()


@dataclass(frozen=True)
class LogOptions:
    """What :func:`run_log` decodes besides the raw log, and when it stops.

    ``node_id``: the node whose PDOs are decoded (None: the drive profile's, else 1);
    ``decode``: show them live (SI units); ``csv_path``: one CSV row per decoded frame
    (decodes even without ``decode``); ``prefer``: alternative layouts of the built-in DBC
    sharing a COB-ID (``RPDO2_AB``); ``drive``: decode with this drive profile's process data
    instead; ``duration``: stop after this long (s), None: only on the caller's ``stop`` or a
    bus error.
    """

    node_id: int | None = None
    decode: bool = False
    csv_path: str | Path | None = None
    prefer: Iterable[str] = ()
    drive: DriveProfile | None = None
    duration: float | None = None
    #: the live scope's rows (:class:`gateway.scope.feed.LatestValues`), fed with every
    #: decoded frame
    sampler: Any = None

    @property
    def node(self) -> int:
        """The node decoded: ``node_id``, else the drive profile's node, else 1."""
        if self.node_id is not None:
            return self.node_id
        return self.drive.node if self.drive is not None else 1


def run_log(bus: can.BusABC, path: str | Path, options: LogOptions | None = None, *,
            stop: threading.Event | None = None, quiet: bool = False,
            out: TextIO | None = None, tty: bool | None = None) -> LogResult:
    """Log ``bus`` to ``path`` until ``options.duration`` (s) elapsed, ``stop`` is set or a
    bus error; ``options`` (default :class:`LogOptions()`: raw log only, no time limit) says
    what is decoded.

    The live display goes to ``out`` (standard output), as a refreshing table when ``tty``
    (default: ``out.isatty()``); none when ``quiet``. The caller owns the bus (opens and shuts
    it down). Returns the account; a bus error is in :attr:`LogResult.error` (the files are
    complete up to it). Raises UserError for a bad path or node before anything is received.
    """
    opts = LogOptions() if options is None else options
    out = sys.stdout if out is None else out
    stop = threading.Event() if stop is None else stop
    p, cp = _log_paths(path, opts.csv_path)
    rec = _open_recorder(p, cp, opts)
    display = None if quiet else _live_display(out, rec, opts.decode, tty)
    elapsed = _receive(bus, rec, display, opts.duration, stop)
    writer = rec.writer
    return LogResult(path=p, csv_path=cp, duration=elapsed, frames=rec.frames,
                     decoded=rec.decoded, write_error=writer.error, written=writer.count,
                     dropped=writer.dropped, counts=Counter(rec.counts),
                     decode_errors=Counter(rec.errors), error=rec.error)


def _log_paths(path: str | Path, csv_path: str | Path | None) -> tuple[Path, Path | None]:
    """The raw log's path (``-o``, see :func:`check_log_path`) and the decoded CSV's
    (``--csv``: in a writable directory, not the raw log itself); UserError if not."""
    p = check_log_path(path)
    if csv_path is None:
        return p, None
    cp = Path(csv_path)
    check_writable(cp, "--csv")
    if cp.resolve() == p.resolve():
        raise UserError(f"--csv {str(cp)!r} is the raw log file itself; give another name")
    return p, cp


def _open_recorder(p: Path, cp: Path | None, opts: LogOptions) -> _Recorder:
    """The listener writing the raw log ``p`` and the CSV ``cp`` (if any) of ``opts``' node.

    UserError for a bad node, message or drive profile before any file is opened, and for a
    file that cannot be opened (the other one is closed again).
    """
    node_id = opts.node
    _decoders(node_id, opts.prefer, opts.drive)  # bad node/message/profile → UserError
    writer = BusRecorder(p)  # UserError when it cannot be opened
    csv_file = None
    try:
        if cp is not None:
            try:
                csv_file = open(cp, "w", newline="", encoding="utf-8")  # noqa: SIM115
            except OSError as exc:
                raise UserError(f"cannot write --csv {str(cp)!r}: {exc.strerror or exc}") from exc
        return _Recorder(writer, node_id, opts.decode, csv_file, opts.prefer, opts.drive,
                         opts.sampler)
    except BaseException:
        writer.stop()
        if csv_file is not None:
            csv_file.close()
        raise


def _live_display(out: TextIO, rec: _Recorder, decode: bool, tty: bool | None
                  ) -> _Display | None:
    """The live view of ``rec`` on ``out``; None on a pipe without ``decode`` (nothing useful
    to print there)."""
    display = _Display(out, rec, decode, tty)
    return None if not display.tty and not decode else display


def _receive(bus: can.BusABC, rec: _Recorder, display: _Display | None,
             duration: float | None, stop: threading.Event) -> float:
    """Receive from ``bus`` into ``rec`` through a :class:`can.Notifier` thread until
    :func:`_wait` returns. On every exit path the notifier is stopped first, then the files
    are closed, then the display is drawn a last time. Returns the time it took (s)."""
    t0 = time.monotonic()
    notifier = None
    try:
        notifier = can.Notifier(bus, [rec], timeout=0.1)
        _wait(rec, display, duration, stop, t0)
    finally:
        if notifier is not None:
            notifier.stop(timeout=2.0)  # joins the receive thread, then rec.stop()
        rec.close()
        elapsed = time.monotonic() - t0
        if display is not None:
            with contextlib.suppress(Exception):
                display.tick(final=True)
    return elapsed


def _wait(rec: _Recorder, display: _Display | None, duration: float | None,
          stop: threading.Event, t0: float) -> None:
    """Wait until ``duration`` (s) since ``t0`` (time.monotonic) elapsed, ``rec`` saw a receive
    error or ``stop`` is set; meanwhile refresh the display (every :data:`DISPLAY_PERIOD` s at
    most) and flush the CSV (about once a second)."""
    last_flush = t0
    while True:
        now = time.monotonic()
        if duration is not None and now - t0 >= duration:
            return
        if rec.error is not None:
            return
        wait = DISPLAY_PERIOD if duration is None else min(DISPLAY_PERIOD,
                                                            duration - (now - t0))
        if stop.wait(max(wait, 0.0)):
            return
        if display is not None:
            display.tick()
        if now - last_flush >= 1.0:
            rec.flush()
            last_flush = now


# ------------------------------------------------------------------------------- CLI


@contextlib.contextmanager
def _stop_on_signals(stop: threading.Event) -> Iterator[None]:
    """SIGINT and SIGTERM set ``stop`` (main thread only); the old handlers come back after."""
    if threading.current_thread() is not threading.main_thread():
        yield
        return
    old = {}
    for sig in (signal.SIGINT, signal.SIGTERM):
        old[sig] = signal.signal(sig, lambda *_: stop.set())
    try:
        yield
    finally:
        for sig, handler in old.items():
            signal.signal(sig, handler)


def cmd_log(args: argparse.Namespace) -> int:
    """`hil-gateway log`: record the bus; decode the drive's PDOs; print the account."""
    from gateway.scope import live_scope
    from gateway.scope.feed import LatestValues
    from gateway.units import format_duration, parse_duration

    path = check_log_path(args.output)
    if args.csv is not None:
        check_writable(Path(args.csv), "--csv")
    duration = None if args.duration is None else parse_duration(args.duration, "--duration")
    drive = None
    if args.drive is not None:
        from gateway.drive_profile import load_drive_profile

        drive = load_drive_profile(args.drive)
    node = args.node if args.node is not None else (drive.node if drive is not None else 1)
    _decoders(node, (), drive)
    cfg = bus_config(args)
    bus = open_bus(cfg, receive_own_messages=False)
    stop = threading.Event()
    try:
        if not args.quiet:
            until = f"for {format_duration(duration)}" if duration else "until Ctrl-C"
            what = f", decoding node {node}" if args.decode or args.csv else ""
            if what and drive is not None:
                what += f" with {drive.source}"
            print(f"logging {cfg.label()} to {path}{what} {until}", flush=True)
        with _stop_on_signals(stop), live_scope(args.scope, f"log {cfg.label()}",
                                                     args.plotjuggler) as feed:
            sampler = None
            if feed is not None:
                sampler = LatestValues(c for c in csv_columns(node, (), drive)
                                       if c not in ("t", "name"))
                feed.attach(sampler)
            options = LogOptions(node_id=node, decode=args.decode, csv_path=args.csv,
                                 duration=duration, drive=drive, sampler=sampler)
            result = run_log(bus, path, options, stop=stop, quiet=args.quiet)
    finally:
        bus.shutdown()
    print(result.account())
    if result.write_error:
        raise UserError(f"the log {path} holds the first {result.written} of "
                        f"{result.frames} frames: {result.write_error}. Free space or choose "
                        "another -o", exit_code=1)
    if result.error is not None:
        raise UserError(f"receiving from {cfg.label()} failed: {result.error}. The log {path} "
                        f"is complete up to that point ({result.frames} frames).")
    return 0


def add_parser(sub: Any) -> None:
    """Register `log` on the subcommand parsers of `hil-gateway`."""
    formats = "; ".join(f"{s} {what}" for s, what in LOG_SUFFIXES.items())
    p = sub.add_parser(
        "log", help="record the CAN bus to a file (.blf/.asc/.csv/.log/.trc), decode the PDOs",
        description="Record every frame on the bus to a log file through python-can's writers; "
                    "the format follows the suffix of -o: " + formats + ". With --decode the "
                    "drive's PDOs are decoded with the DBC (SI units) and shown live; with "
                    "--csv each decoded frame is one CSV row. Stops after --duration or on "
                    "Ctrl-C/SIGTERM; the files are always complete. Read a log back in "
                    "Python with gateway.buslog.read_log() and decode_frames().")
    p.add_argument("-o", "--output", required=True, metavar="FILE",
                   help="raw log file; its suffix picks the format (.blf, .asc, .csv, .log, .trc)")
    p.add_argument("--decode", action="store_true",
                   help="decode the drive's PDOs and show the latest values live (≤ 10 Hz)")
    p.add_argument("--csv", metavar="FILE",
                   help="write one row per decoded PDO (t, name, signals in SI units)")
    p.add_argument("--duration", metavar="S",
                   help="stop after this long (10, 2.5s, 500ms); default: until Ctrl-C")
    p.add_argument("--node", type=int, metavar="N",
                   help="node id of the drive whose PDOs are decoded (default: the drive "
                        "profile's, 1 for the emulator)")
    p.add_argument("--drive", metavar="PROFILE",
                   help="drive profile (TOML) whose process data decodes the PDOs (its DBC, "
                        "roles and setpoint layout); default: the built-in emulator DBC")
    p.add_argument("--quiet", action="store_true",
                   help="no live output; only the account at the end")
    p.add_argument("--scope", metavar="[HOST:]PORT",
                   help="serve a live scope of the decoded signals at http://HOST:PORT/ "
                        "(HOST 127.0.0.1 by default; PORT 0: any free port, printed)")
    p.add_argument("--plotjuggler", metavar="[HOST:]PORT", nargs="?", const="9870",
                   help="stream the decoded signals to PlotJuggler's UDP server (JSON, one "
                        "datagram a row, timestamp field t; HOST 127.0.0.1 by default, PORT "
                        "9870 when not given)")
    add_bus_options(p)
    p.set_defaults(func=cmd_log)
