"""Helpers for the two-process vcan tests (tests/test_two_process.py).

Real processes on a SocketCAN channel: the emulator (`hil-plant run`), the gateway
(`hil-gateway run/scan`) and a third-party logger (`candump -L`, can-utils). Every process
runs in its own session (process group) with a time limit and is killed, with its whole
group, when the ``with`` block or the call ends — whatever happened.
"""

from __future__ import annotations

import contextlib
import os
import re
import shutil
import signal
import subprocess
import sys
import time
from collections.abc import Iterator, Sequence
from dataclasses import dataclass
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]
#: Time limits here catch hangs; under QEMU's TCG (scripts/vcan-run's last resort, which sets
#: VCAN_RUN_SANDBOX_KIND) every process runs 20-40x slower than natively, so they are longer.
IN_QEMU = os.environ.get("VCAN_RUN_SANDBOX_KIND") == "qemu"
SLOW = 4.0 if IN_QEMU else 1.0
_BIN = Path(sys.executable).parent


def _entry(name: str, module: str) -> list[str]:
    """The console script next to this Python (the venv's), else ``python -m module``."""
    exe = _BIN / name
    return [str(exe)] if exe.exists() else [sys.executable, "-m", module]


def gateway_cmd() -> list[str]:
    return _entry("hil-gateway", "gateway")


def plant_cmd() -> list[str]:
    return _entry("hil-plant", "plant")


def _env() -> dict[str, str]:
    env = dict(os.environ)
    # Each line reaches its file at once, even where a program only flushes on a tty.
    env["PYTHONUNBUFFERED"] = "1"
    env.pop("CAN_INTERFACE", None)
    env.pop("CAN_CHANNEL", None)
    return env


def _kill_group(p: subprocess.Popen, sig: int = signal.SIGKILL) -> None:
    with contextlib.suppress(ProcessLookupError, PermissionError):
        os.killpg(p.pid, sig)


@dataclass
class Proc:
    """A process in its own session, stdout and stderr to files."""

    popen: subprocess.Popen
    out: Path
    err: Path
    stopping: bool = False  #: stopped on purpose (no "ended during the test")

    @classmethod
    def start(cls, cmd: Sequence[str], logdir: Path, name: str) -> Proc:
        logdir.mkdir(parents=True, exist_ok=True)
        out, err = logdir / f"{name}.out", logdir / f"{name}.err"
        with open(out, "wb") as fo, open(err, "wb") as fe:
            p = subprocess.Popen(list(cmd), stdin=subprocess.DEVNULL, stdout=fo, stderr=fe,
                                 cwd=REPO, env=_env(), start_new_session=True)
        return cls(p, out, err)

    @property
    def pid(self) -> int:
        return self.popen.pid

    def stdout(self) -> str:
        return self.out.read_text(errors="replace")

    def stderr(self) -> str:
        return self.err.read_text(errors="replace")

    def describe(self) -> str:
        return (f"{self.popen.args!r} exit {self.popen.returncode}\n--- stdout\n"
                f"{self.stdout()[-3000:]}\n--- stderr\n{self.stderr()[-3000:]}")

    def wait(self, timeout: float) -> int:
        """Exit status; on timeout (× :data:`SLOW`) the group is killed and the test fails."""
        timeout *= SLOW
        try:
            return self.popen.wait(timeout)
        except subprocess.TimeoutExpired:
            self.kill()
            raise AssertionError(f"did not finish within {timeout:g} s: "
                                 f"{self.describe()}") from None

    def signal(self, sig: int) -> None:
        _kill_group(self.popen, sig)

    def kill(self) -> None:
        """SIGKILL the whole group and reap (idempotent)."""
        _kill_group(self.popen)
        with contextlib.suppress(subprocess.TimeoutExpired):
            self.popen.wait(10)


def run(cmd: Sequence[str], logdir: Path, name: str, timeout: float) -> Proc:
    """Run to completion (time limit ``timeout``); the finished :class:`Proc`."""
    p = Proc.start(cmd, logdir, name)
    try:
        p.wait(timeout)
    finally:
        p.kill()
    return p


def wait_for(cond, timeout: float, what: str, alive: Proc | None = None,
             poll: float = 0.02) -> None:
    """Poll ``cond()`` until true; fail after ``timeout`` s (× :data:`SLOW`) or when ``alive``
    exits."""
    timeout *= SLOW
    deadline = time.monotonic() + timeout
    while not cond():
        if alive is not None and alive.popen.poll() is not None:
            raise AssertionError(f"waiting for {what}: the process ended: {alive.describe()}")
        if time.monotonic() > deadline:
            raise AssertionError(f"waiting for {what}: not within {timeout:g} s"
                                 + (f": {alive.describe()}" if alive else ""))
        time.sleep(poll)


# ------------------------------------------------------------------------- the emulator


@contextlib.contextmanager
def plant(channel: str, logdir: Path, *args: str, name: str = "plant",
          ready_timeout: float = 60.0) -> Iterator[Proc]:
    """`hil-plant run -i socketcan -c CHANNEL ARGS` until its ready line; stopped by SIGTERM
    (then SIGKILL) when the block ends. Its account is in ``proc.stdout()`` afterwards."""
    cmd = [*plant_cmd(), "run", "-i", "socketcan", "-c", channel, *args]
    p = Proc.start(cmd, logdir, name)
    try:
        wait_for(lambda: p.stdout().strip() != "", ready_timeout, "hil-plant's ready line", p)
        yield p
        ended = not p.stopping and p.popen.poll() is not None
        assert not ended, f"hil-plant ended during the test: {p.describe()}"
    finally:
        if p.popen.poll() is None:
            p.signal(signal.SIGTERM)
            with contextlib.suppress(subprocess.TimeoutExpired):
                p.popen.wait(15)
        p.kill()


def stop_plant(p: Proc, timeout: float = 15.0) -> int:
    """SIGTERM, the way a user ends it; its exit status."""
    p.stopping = True
    p.signal(signal.SIGTERM)
    return p.wait(timeout)


# ------------------------------------------------------------------------------ candump


def cansend(channel: str, frame: str) -> None:
    subprocess.run(["cansend", channel, frame], check=True, timeout=10,
                   stdin=subprocess.DEVNULL, capture_output=True)


PROBE_ID = 0x7E0  # not a CANopen service of the pre-defined set (LSS is 0x7E4/0x7E5)


@dataclass
class Candump:
    proc: Proc
    path: Path
    channel: str

    def text(self) -> str:
        return self.path.read_text(errors="replace")

    def count(self, needle: str) -> int:
        return self.text().count(needle)

    def mark(self, tag: int, timeout: float = 20.0) -> None:
        """Send probe frame PROBE_ID#tag until candump has logged it (it is listening, and
        everything before it is in the file)."""
        timeout *= SLOW
        frame = f"{PROBE_ID:03X}#{tag:02X}"
        deadline = time.monotonic() + timeout
        while frame not in self.text():
            assert self.proc.popen.poll() is None, f"candump ended: {self.proc.describe()}"
            assert time.monotonic() < deadline, f"candump did not log {frame} in {timeout:g} s"
            cansend(self.channel, frame)
            t_end = time.monotonic() + 0.2
            while frame not in self.text() and time.monotonic() < t_end:
                time.sleep(0.01)


@contextlib.contextmanager
def candump(channel: str, logdir: Path, name: str = "candump") -> Iterator[Candump]:
    """`candump -L CHANNEL` > logdir/NAME.log, listening when the block starts; everything up
    to the end of the block is in the file when it returns (a probe frame marks the end)."""
    assert shutil.which("candump") and shutil.which("cansend"), "can-utils not installed"
    logdir.mkdir(parents=True, exist_ok=True)
    path = logdir / f"{name}.log"
    with open(path, "wb") as fo, open(logdir / f"{name}.err", "wb") as fe:
        # -r: a 4 MiB socket receive buffer, so that a slow sandbox (QEMU under TCG) does not
        # make candump drop frames while it is descheduled (the default holds ~1,000 frames)
        p = subprocess.Popen(["candump", "-L", "-r", str(4 << 20), channel],
                             stdin=subprocess.DEVNULL, stdout=fo,
                             stderr=fe, start_new_session=True)
    proc = Proc(p, path, logdir / f"{name}.err")
    dump = Candump(proc, path, channel)
    try:
        dump.mark(0x01)
        yield dump
        dump.mark(0x02)
    finally:
        if p.poll() is None:
            _kill_group(p, signal.SIGTERM)
            with contextlib.suppress(subprocess.TimeoutExpired):
                p.wait(10)
        proc.kill()


def frames_without_probes(messages) -> list:
    return [m for m in messages if m.arbitration_id != PROBE_ID or m.is_extended_id]


def frame_key(m) -> tuple:
    """What a frame is on the bus, without time and interface."""
    return (m.arbitration_id, m.is_extended_id, m.is_remote_frame, m.is_error_frame,
            m.dlc, bytes(m.data))


def find_stretch(whole: Sequence, part: Sequence) -> list[int]:
    """Every index i with whole[i:i + len(part)] == part."""
    n = len(part)
    if n == 0:
        return []
    first = part[0]
    return [i for i in range(len(whole) - n + 1)
            if whole[i] == first and whole[i:i + n] == part]


def find_stretch_concurrent(whole: Sequence, part: Sequence, max_shift: int = 8) -> list[int]:
    """Every index i where whole[i:i + len(part)] holds the same frames as ``part``, each CAN
    id's frames in the same order, none more than ``max_shift`` places from where ``part``
    has it. Each id has one sender, so this is "every sender's frames in its order"; frames of
    two senders on the bus at the same moment may be seen in either order by two sockets on an
    SMP kernel (each CPU delivers the frames it received), which a one-CPU sandbox (UML)
    never shows. Frames are keys of :func:`frame_key` (the id first)."""
    n = len(part)
    if n == 0 or n > len(whole):
        return []
    need: dict = {}
    for k in part:
        need[k] = need.get(k, 0) + 1
    for k in whole[:n]:
        need[k] = need.get(k, 0) - 1
    off = sum(1 for v in need.values() if v)
    starts = []
    for i in range(len(whole) - n + 1):
        if i:
            for k, d in ((whole[i - 1], 1), (whole[i + n - 1], -1)):
                before = need.get(k, 0)
                need[k] = before + d
                off += (need[k] != 0) - (before != 0)
        if off == 0 and _same_order_per_id(whole[i:i + n], part, max_shift):
            starts.append(i)
    return starts


def _same_order_per_id(window: Sequence, part: Sequence, max_shift: int) -> bool:
    pos_w: dict = {}
    pos_p: dict = {}
    for j, k in enumerate(window):
        pos_w.setdefault(k[0], []).append((k, j))
    for j, k in enumerate(part):
        pos_p.setdefault(k[0], []).append((k, j))
    for cob, seq_w in pos_w.items():
        seq_p = pos_p.get(cob, [])
        if [k for k, _ in seq_w] != [k for k, _ in seq_p]:
            return False
        if any(abs(a - b) > max_shift for (_, a), (_, b) in zip(seq_w, seq_p, strict=True)):
            return False
    return True


def stretch_mismatch(whole: Sequence, part: Sequence) -> str:
    """Why ``part`` is not a stretch of ``whole``: where the best alignment of its first
    frame breaks, the frames around it, and whether the frames are the same as a multiset
    (a reordering) or some are missing or extra."""
    from collections import Counter

    best, at = -1, -1
    for i in (j for j, k in enumerate(whole) if part and k == part[0]):
        n = 0
        while n < len(part) and i + n < len(whole) and whole[i + n] == part[n]:
            n += 1
        if n > best:
            best, at = n, i
    if at < 0:
        return "the first logged frame is not in the whole at all"
    window = whole[at:at + len(part)]
    diff_w, diff_p = Counter(window) - Counter(part), Counter(part) - Counter(window)
    kind = ("the same frames in another order" if not diff_w and not diff_p else
            f"{sum(diff_p.values())} logged frames not in the window, {sum(diff_w.values())} "
            "window frames not logged")
    fmt = lambda ks: [f"{k[0]:03x}#{k[5].hex()}" for k in ks]  # noqa: E731
    return (f"aligned at {at}, equal for {best} of {len(part)} frames; then whole "
            f"{fmt(whole[at + best:at + best + 4])} vs part {fmt(part[best:best + 4])}; "
            f"over the whole length: {kind}")


# -------------------------------------------------------------------------------- SDO


def sdo_upload(channel: str, node_id: int, index: int, sub: int = 0,
               timeout: float = 1.0, interface: str = "socketcan") -> bytes:
    """One SDO upload by python-canopen, as a third-party master would do it."""
    import canopen

    network = canopen.Network()
    network.connect(interface=interface, channel=channel)
    try:
        node = canopen.RemoteNode(node_id, canopen.ObjectDictionary())
        node.sdo.RESPONSE_TIMEOUT = timeout
        network.add_node(node)
        return bytes(node.sdo.upload(index, sub))
    finally:
        network.disconnect()


def bcm_tx_ops() -> str:
    """The kernel's broadcast manager state (/proc/net/can-bcm/*), all sockets."""
    root = Path("/proc/net/can-bcm")
    text = []
    with contextlib.suppress(OSError):
        for f in root.iterdir():
            with contextlib.suppress(OSError):
                text.append(f.read_text(errors="replace"))
    return "\n".join(text)


def candump_lines(text: str) -> list[tuple[float, int, bytes]]:
    """(timestamp, COB-ID, data) of each complete standard-frame line of ``candump -L``."""
    out = []
    for line in text.splitlines(keepends=True):
        if not line.endswith("\n"):
            break  # candump is still writing it
        m = _CANDUMP_LINE.match(line)
        if m:
            out.append((float(m[1]), int(m[2], 16), bytes.fromhex(m[3])))
    return out


_CANDUMP_LINE = re.compile(r"^\((\d+\.\d+)\) \S+ ([0-9A-F]{3})#([0-9A-F]*)\s*$")
