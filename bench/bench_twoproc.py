"""Two processes over SocketCAN: `hil-plant run` and `hil-gateway run` at 1 ms.

Run where vcan0 exists, e.g. inside the sandbox:
    scripts/vcan-run -- .venv/bin/python bench/bench_twoproc.py [--seconds 60] [--quick]

Figures (from each run's summary.json, written by the gateway):

* real time: `hil-gateway run --timing realtime --period 1ms` for N seconds, SYNC from the
  kernel's broadcast manager (the gateway's choice on socketcan): cycles, missed cycles
  (target 0), late RPDOs, SYNC jitter (|SYNC period − 1 ms|), SYNC → TPDO (the drive's
  answer) and reaction (last TPDO → RPDOs sent, target p99 ≤ 200 µs), median/p99/max;
  the emulator's own account (cycles, SYNC gaps);
* lockstep: cycles per second of the paper scenario (2500 cycles at 1 ms) across the two
  processes, `--repeats` runs.

A fresh `hil-plant run` for each gateway run. The missed-cycle limits (in a row, and the
rate within 100 ms) are lifted so the real time run lasts its N seconds whatever happens and
the count is reported; ``--seconds 0`` skips it. With
`--no-deadlines` the real-time run uses a copy of gateway/drives/emulator.toml with the
drive's RPDO deadline (0x1400.5) and heartbeat consumer (0x1016) at their longest, 65.535 s
(longer than any run up to a minute), and the gateway's watch on the drive's heartbeat at
5 s: where the two processes cannot keep up with 1 ms
(the UML sandbox: one CPU) the drive otherwise trips (EMCY 0x8250 or 0x8130) and ends the
run within seconds, and the figures would describe only that.

A run that does not complete (`hil-plant` that does not start, `hil-gateway` without a
summary.json, a timeout, or a stop reason other than the end of the profile, e.g. the drive
tripped) is a failed measurement: ``FAILED: <reason>`` (the real-time figures up to the stop
are still printed), the other measurements go on, exit status 1 (bench/_common.py).
``--json [FILE]`` (one line on stdout, or FILE): ``where``, ``deadlines``, ``realtime``
({"run", "timing", "plant"}) or null (then ``realtime_until_stop``: the same up to the stop,
where the run got that far), ``lockstep_cycles_per_s`` (the runs) or null, ``failed``.
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import signal
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path

from _common import Figures, RunError, add_json_option, failed_text, require_completed, the_run

REPO = Path(__file__).resolve().parents[1]
BIN = Path(sys.executable).parent


def _cmd(name: str, module: str) -> list[str]:
    exe = BIN / name
    return [str(exe)] if exe.exists() else [sys.executable, "-m", module]


def where() -> str:
    """The machine the figures are from: native kernel or the UML sandbox, and CPUs."""
    vendor = ""
    try:
        with open("/proc/cpuinfo") as f:
            vendor = next((ln.split(":", 1)[1].strip() for ln in f
                           if ln.startswith("vendor_id")), "")
    except OSError:
        pass
    kinds = {"uml": "User-Mode Linux sandbox", "qemu": "QEMU sandbox",
             "native": "native kernel"}
    # scripts/vcan-run says which sandbox it started; without it, UML tells by its CPU
    kind = kinds.get(os.environ.get("VCAN_RUN_SANDBOX_KIND", ""),
                     "User-Mode Linux sandbox" if vendor == "User Mode Linux"
                     else "native kernel")
    return f"{kind}, Linux {platform.release()}, {os.cpu_count()} CPU(s)"


class Plant:
    """`hil-plant run` in its own session until its ready line; SIGTERM on exit."""

    def __init__(self, channel: str, logdir: Path):
        self.out = logdir / "plant.out"
        self.err = logdir / "plant.err"
        with open(self.out, "wb") as fo, open(self.err, "wb") as fe:
            self.p = subprocess.Popen([*_cmd("hil-plant", "plant"), "run", "-i", "socketcan",
                                       "-c", channel], stdin=subprocess.DEVNULL, stdout=fo,
                                      stderr=fe, cwd=REPO, start_new_session=True,
                                      env={**os.environ, "PYTHONUNBUFFERED": "1"})
        deadline = time.monotonic() + 120
        while not self.out.read_text().strip():
            if self.p.poll() is not None or time.monotonic() > deadline:
                self.stop()
                raise RunError(f"hil-plant did not start: {_tail(self.err)}")
            time.sleep(0.05)

    def stop(self) -> str:
        """Its account line (cycles, SYNC gaps, faults)."""
        if self.p.poll() is None:
            os.killpg(self.p.pid, signal.SIGTERM)
            try:
                self.p.wait(30)
            except subprocess.TimeoutExpired:
                os.killpg(self.p.pid, signal.SIGKILL)
                self.p.wait(10)
        lines = self.out.read_text().strip().splitlines()
        return lines[-1] if len(lines) > 1 else ""


def _tail(path: Path, lines: int = 3) -> str:
    """The last lines of a log, on one line."""
    try:
        text = path.read_text(errors="replace").strip().splitlines()[-lines:]
    except OSError as exc:
        return f"({path}: {exc.strerror or exc})"
    return " | ".join(text) or f"(nothing in {path.name})"


def gateway(channel: str, out: Path, logdir: Path, *args: str, timeout: float) -> dict:
    """The run's summary.json, however the run ended; RunError without one."""
    cmd = [*_cmd("hil-gateway", "gateway"), "run", "-i", "socketcan", "-c", channel,
           "--out", str(out), *args]
    with the_run("hil-gateway"):
        with open(logdir / "gateway.out", "wb") as fo, open(logdir / "gateway.err", "wb") as fe:
            p = subprocess.run(cmd, stdin=subprocess.DEVNULL, stdout=fo, stderr=fe, cwd=REPO,
                               timeout=timeout, check=False)
        if not (out / "summary.json").exists():
            raise RunError(f"exit {p.returncode}, no summary.json: "
                           f"{_tail(logdir / 'gateway.err')}")
        if p.returncode != 0:
            print(f"hil-gateway exit {p.returncode}: {_tail(logdir / 'gateway.err', 1)}")
        return json.loads((out / "summary.json").read_text())


def us(x: float) -> str:
    return f"{x * 1e6:.0f} µs"


def relaxed_drive() -> str:
    """gateway/drives/emulator.toml with the drive's deadlines (the RPDO deadline 0x1400.5,
    the heartbeat consumer 0x1016) at the longest the objects hold, UNSIGNED16 ms = 65.5 s
    (the drive profile refuses 0, which would switch the drive's watch off rather than relax
    it), and the gateway's watch of the drive's heartbeat at 5 s (``--no-deadlines``)."""
    drive = (REPO / "gateway" / "drives" / "emulator.toml").read_text()
    for old, new in (("rpdo_timeout_ms = 300", "rpdo_timeout_ms = 65535"),
                     ("heartbeat_timeout_ms = 300", "heartbeat_timeout_ms = 65535"),
                     ("drive_heartbeat_timeout_ms = 500", "drive_heartbeat_timeout_ms = 5000")):
        if old not in drive:
            raise RunError(f"--no-deadlines: {old!r} not in gateway/drives/emulator.toml")
        drive = drive.replace(old, new)
    return drive


def realtime(args: argparse.Namespace, root: Path) -> tuple[dict, str]:
    """(summary, the emulator's account line) of the real-time run, however it ended."""
    d = root / "realtime"
    d.mkdir(exist_ok=True)
    extra: list[str] = []
    if args.no_deadlines:
        (d / "drive.toml").write_text(relaxed_drive())
        extra = ["--drive", str(d / "drive.toml")]
    with the_run():
        pl = Plant(args.channel, d)
        try:
            s = gateway(args.channel, d / "run", d, "--timing", "realtime", "--period",
                        args.period, "--duration", f"{args.seconds:g}s", "--max-missed",
                        "1000000", "--max-miss-rate", "1", *extra, timeout=args.seconds * 3 + 300)
        finally:
            account = pl.stop()
        return s, account


def print_realtime(args: argparse.Namespace, s: dict, account: str) -> None:
    r, t = s["run"], s.get("timing", {})
    total = r["cycles"] + r["missed_cycles"]
    print(f"\nreal time, period {args.period}, {args.seconds:g} s, SYNC by the kernel's BCM"
          f"{', drive deadlines at 65.5 s' if args.no_deadlines else ''}:")
    print(f"  cycles {r['cycles']}, missed {r['missed_cycles']} "
          f"({100 * r['missed_cycles'] / max(total, 1):.2f} %), late RPDO {r['late_rpdo']}, "
          f"wall {r['wall_time_s']:.1f} s, stopped: {r['stop_reason']}")
    for key, label in (("sync_period", "SYNC period"), ("sync_jitter", "SYNC jitter"),
                       ("sync_to_tpdo", "SYNC → TPDO"), ("reaction", "TPDO → RPDO")):
        if key in t:
            v = t[key]
            print(f"  {label:12s} median {us(v['median']):>9s}  p99 {us(v['p99']):>9s}  "
                  f"max {us(v['max']):>9s}")
    print(f"  {account}")
    for f in s.get("faults", []):
        print(f"  fault at {f['time']:.1f} s: {f['kind']} 0x{f['code'] or 0:04X} {f['text']}")


def lockstep(args: argparse.Namespace, root: Path) -> list[float]:
    """Cycles/s of each lockstep run; RunError at the first that does not complete."""
    rates = []
    for k in range(args.repeats):
        d = root / f"lockstep{k}"
        d.mkdir(exist_ok=True)
        with the_run(f"lockstep run {k + 1} of {args.repeats}"):
            pl = Plant(args.channel, d)
            try:
                s = gateway(args.channel, d / "run", d, "--timing", "lockstep", "--profile",
                            "profiles/paper.toml", "--period", args.period, timeout=900)
            finally:
                pl.stop()
            require_completed(s)
        r = s["run"]
        rates.append(r["cycles"] / r["wall_time_s"])
        print(f"lockstep run {k + 1}: {r['cycles']} cycles in {r['wall_time_s']:.2f} s = "
              f"{rates[-1]:.0f} cycles/s, reaction median "
              f"{us(s['timing']['reaction']['median'])}, p99 {us(s['timing']['reaction']['p99'])}")
    return rates


def _realtime(args: argparse.Namespace, root: Path, fig: Figures) -> None:
    """The real-time run's figures into ``fig`` (failed with the reason it stopped)."""
    try:
        s, account = realtime(args, root)
    except RunError as exc:
        fig.fail("realtime", f"real-time run: {exc}")
        print(f"\nreal time, period {args.period}, {args.seconds:g} s: "
              f"{failed_text(fig.failed['realtime'])}")
    else:
        print_realtime(args, s, account)
        figures = {"run": s["run"], "timing": s.get("timing"), "plant": account}
        try:
            require_completed(s)
            fig.put("realtime", figures)
        except RunError as exc:
            fig.fail("realtime", f"real-time run: {exc}")
            fig.put("realtime_until_stop", figures)
            print(f"  {failed_text(fig.failed['realtime'])}")


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("-c", "--channel", default="vcan0")
    ap.add_argument("--seconds", type=float, default=None,
                    help="real-time run length (60; --quick 10; 0: no real-time run)")
    ap.add_argument("--period", default="1ms")
    ap.add_argument("--repeats", type=int, default=None,
                    help="lockstep runs (3; --quick 1; 0: none)")
    ap.add_argument("--quick", action="store_true",
                    help="10 s of real time, 1 lockstep run (unless given)")
    ap.add_argument("--out", type=Path, help="keep the run directories here")
    add_json_option(ap)
    ap.add_argument("--no-deadlines", action="store_true",
                    help="real-time run with the drive's deadlines at their longest, 65.5 s "
                         "(see above)")
    args = ap.parse_args(argv)
    if args.seconds is None:
        args.seconds = 10.0 if args.quick else 60.0
    if args.repeats is None:
        args.repeats = 1 if args.quick else 3
    root = args.out or Path(tempfile.mkdtemp(prefix="bench-twoproc-"))
    root.mkdir(parents=True, exist_ok=True)
    print(f"two processes on socketcan:{args.channel}; {where()}; runs under {root}")
    fig = Figures(where=where(), deadlines=not args.no_deadlines)

    # ------------------------------------------------------------------ real time
    if args.seconds <= 0:
        print("real time: not run (--seconds 0)")
    else:
        _realtime(args, root, fig)
    # ------------------------------------------------------------------ lockstep
    rates = fig.measure("lockstep_cycles_per_s", lockstep, args, root)
    if rates is None:
        print(f"lockstep across two processes: {failed_text(fig.failed['lockstep_cycles_per_s'])}")
    elif rates:
        print(f"lockstep across two processes: median {statistics.median(rates):.0f} cycles/s "
              f"({', '.join(f'{x:.0f}' for x in rates)})")
    fig.report_failures()
    fig.emit(args.json)
    return fig.exit_status()


if __name__ == "__main__":
    sys.exit(main())
