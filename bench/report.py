"""The performance targets, each beside its baseline, measured in one run.

    .venv/bin/python bench/report.py                 # measure and print the table
    .venv/bin/python bench/report.py --write         # ... and put it in BENCHMARKS.md
    .venv/bin/python bench/report.py --quick         # shorter runs of each benchmark
    .venv/bin/python bench/report.py --vcan          # also two processes over vcan
    .venv/bin/python bench/report.py --vcan uml,qemu # ... in each sandbox kind

Runs the benchmarks that hold the targets, one after the other, each with ``--json`` (its
figures and its baseline come from the same run of that benchmark), and prints one table:
the controller step (`bench_control.py`), the plant against motulator (`bench_motulator.py`;
motulator comes with the ``bench`` extra: ``.venv/bin/pip install -e '.[bench]'``), the
command a user waits for and scripts/demo (`bench_command.py --sim`), the lean process data
at 500 us (`bench_lean.py`), the lockstep loop in one process (`bench_loop.py`, lockstep
only) and, with ``--vcan``, the two-process lockstep rate over SocketCAN inside whichever
sandbox `scripts/vcan-run` starts on this host, or in each kind named (``--vcan uml,qemu``)
(`bench_twoproc.py --seconds 0`, lockstep only; it has no target: the rate is reported with
the sandbox's kind). Each benchmark's own
output streams through; its full table and method are in BENCHMARKS.md's section on it.

``--write`` replaces the section of BENCHMARKS.md between the ``bench/report.py`` markers (or
puts it before the first section when there is none) with the table, the date, the commit
and the host it ran on (CPU, cores, AVX-512/AMX, load average); the rest of the file, the
history of earlier measurements, stays. The file is written whole or not at all.

A benchmark that does not run or fails leaves its rows ``FAILED: <reason>``; the others are
still measured. Exit status: 0 when every target was measured and met, 1 otherwise (a failed
measurement or a missed target; the table says which). ``--json [FILE]`` gives the rows as
one JSON line: ``host``, ``rows`` (``target``, ``figure``, ``baseline``, ``goal``,
``status`` met / missed / failed / reported / not run, ``value``), ``failed``.
"""

from __future__ import annotations

import argparse
import datetime as dt
import json
import os
import platform
import subprocess
import sys
import tempfile
from collections.abc import Callable
from dataclasses import dataclass, replace
from enum import Enum
from pathlib import Path
from typing import Any

ROOT = Path(__file__).resolve().parents[1]
BENCHMARKS = ROOT / "BENCHMARKS.md"
#: The sandboxes --vcan can name (scripts/vcan-run's --uml, --qemu; auto: its choice).
VCAN_KINDS = ("auto", "uml", "qemu")
BEGIN = "<!-- bench/report.py: begin; written by `bench/report.py --write`, edit the script -->"
END = "<!-- bench/report.py: end -->"


#: The rows, by target (one name each: the table's first column).
STEP_CF = "controller step, current-fed law, sampled-data design (CPU µs, median)"
STEP_FO = "controller step, full-order law, sampled-data design (CPU µs, median)"
PLANT = "plant (current loop, model (1)) against motulator at 250 µs, same run"
RATE = "the emulator's internal rate at that speed"
SIMULATE = "`hil-gateway simulate`, paper scenario, with its figures (wall s, warm)"
DEMO = "`scripts/demo`, warm (wall s)"
BUS = "lean process data: one cycle's bus time at 1 Mbit/s (worst-case stuffing)"
LEAN = "lean mapping, `sim` at 500 µs in lockstep: missed cycles (accuracy)"
LOOP = "lockstep loop in one process, paper scenario (cycles/s, median)"
TWOPROC_ROW = "two processes over SocketCAN vcan, lockstep (cycles/s)"


class Status(Enum):
    MET = "met"
    MISSED = "missed"
    FAILED = "failed"
    REPORTED = "reported"  # a figure without a target
    NOT_RUN = "not run"


@dataclass(frozen=True)
class Row:
    target: str
    figure: str
    baseline: str
    goal: str
    status: Status
    value: float | None = None


@dataclass(frozen=True)
class Bench:
    """A benchmark script, its arguments, and how its JSON becomes rows."""

    script: str
    args: tuple[str, ...]
    quick_args: tuple[str, ...]
    #: the rows of its JSON (given no figures, its rows failed: their names and goals)
    rows: Callable[[dict[str, Any]], list[Row]]
    timeout_s: float = 1800


def _ok(data: dict[str, Any], *names: str) -> str | None:
    """None when every figure is there, else the reason the first missing one failed."""
    for name in names:
        if data.get(name) is None:
            return (data.get("failed") or {}).get(name) or f"no figure {name}"
    return None


def _target(name: str, goal: str, data: dict[str, Any], keys: tuple[str, ...],
            figure: Callable[[], str], baseline: Callable[[], str],
            met: Callable[[], bool | None], value: str) -> Row:
    why = _ok(data, *keys)
    if why is not None:
        return Row(name, f"FAILED: {why}", "", goal, Status.FAILED)
    verdict = met()
    status = (Status.REPORTED if verdict is None else Status.MET if verdict else Status.MISSED)
    return Row(name, figure(), baseline(), goal, status, data[value])


def control_rows(d: dict[str, Any]) -> list[Row]:
    rows = []
    for name, key, goal in ((STEP_CF, "current_fed", 10.0), (STEP_FO, "full_order", 12.0)):
        us = f"exact_{key}_cpu_us"
        rows.append(_target(
            name, f"≤ {goal:g} µs", d, (us, f"euler_{key}_cpu_us"),
            lambda us=us: f"{d[us]:.2f} µs",
            lambda key=key, us=us: (f"Euler design {d[f'euler_{key}_cpu_us']:.2f} µs "
                                    f"(× {d[us] / d[f'euler_{key}_cpu_us']:.2f}); "
                                    f"recorded before {d[f'recorded_{key}_us']:g} µs"),
            lambda us=us, goal=goal: d[us] <= goal, us))
    return rows


def motulator_rows(d: dict[str, Any]) -> list[Row]:
    name = PLANT
    if d.get("motulator") is None and not d.get("failed"):
        note = d.get("motulator_note") or "motulator not installed"
        return [Row(name, f"FAILED: motulator {note}", "", "≥ 40×", Status.FAILED),
                _rate_row(d)]
    return [_target(name, "≥ 40×", d, ("ratio", "motulator_250us_ZOH_x_real_time"),
                    lambda: f"{d['ratio']:.1f}×",
                    lambda: (f"ours {d['ours_x_real_time']:.1f}× real time, motulator "
                             f"{d['motulator_250us_ZOH_x_real_time']:.2f}× (motulator "
                             f"{d['motulator']})"),
                    lambda: d["ratio"] >= 40.0, "ratio"),
            _rate_row(d)]


def _rate_row(d: dict[str, Any]) -> Row:
    return _target(RATE, "≥ 10 kHz", d,
                   ("ours_internal_rate_hz", "ours_x_real_time"),
                   lambda: f"{d['ours_internal_rate_hz'] / 1e3:g} kHz",
                   lambda: f"{d['ours_x_real_time']:.1f}× real time",
                   lambda: d["ours_internal_rate_hz"] >= 10e3, "ours_internal_rate_hz")


def command_rows(d: dict[str, Any]) -> list[Row]:
    return [
        _target(SIMULATE, f"≤ {d.get('target_s', 1.0):g} s", d, ("simulate_s",),
                lambda: f"{d['simulate_s']:.2f} s (CPU {d['simulate_cpu_s']:.2f} s)",
                lambda: (f"without figures {d['simulate_no_figures_s']:.2f} s; recorded "
                         f"before {d['recorded_simulate_s']:g} s"
                         if d.get("simulate_no_figures_s") is not None
                         else f"recorded before {d.get('recorded_simulate_s')} s"),
                lambda: d["simulate_s"] <= d.get("target_s", 1.0), "simulate_s"),
        _target(DEMO, f"≤ {d.get('demo_target_s', 2.0):g} s", d, ("demo_s",),
                lambda: f"{d['demo_s']:.2f} s (CPU {d['demo_cpu_s']:.2f} s)",
                lambda: (f"its `sim` alone {d['sim_s']:.2f} s; recorded before "
                         f"{d['recorded_sim_s']:g} s" if d.get("sim_s") is not None else ""),
                lambda: d["demo_s"] <= d.get("demo_target_s", 2.0), "demo_s"),
    ]


def lean_rows(d: dict[str, Any]) -> list[Row]:
    return [
        _target(BUS, "fits 500 µs (≤ 85 %)", d, ("lean_bits", "lean_load_500us", "default_bits"),
                lambda: (f"{d['lean_bits']} bits = {d['lean_bus_time_us']:.0f} µs, "
                         f"{d['lean_load_500us']:.0%} of 500 µs"),
                lambda: (f"default mapping {d['default_bits']} bits, "
                         f"{d['default_load_500us']:.0%} of 500 µs (fits from "
                         f"{d['default_min_period_us']:.0f} µs)"),
                lambda: d["lean_load_500us"] <= 0.85 + 1e-12, "lean_load_500us"),
        _target(LEAN, "0 missed", d, ("lean_500us_missed", "lean_500us_rms_rad_s"),
                lambda: (f"{d['lean_500us_missed']} of {d['lean_500us_cycles']}; speed error "
                         f"RMS {d['lean_500us_rms_rad_s'] * 1e3:.2f} mrad/s"),
                lambda: (f"default mapping at 1 ms: RMS "
                         f"{d['default_1ms_rms_rad_s'] * 1e3:.2f} mrad/s"
                         if d.get("default_1ms_rms_rad_s") is not None else ""),
                lambda: d["lean_500us_missed"] == 0, "lean_500us_missed"),
    ]


def loop_rows(d: dict[str, Any]) -> list[Row]:
    return [_target(LOOP, "≥ 5000", d, ("inprocess_cycles_per_s",),
                    lambda: f"{d['inprocess_cycles_per_s']:.0f}",
                    lambda: (f"python-can's virtual bus {d['virtual_cycles_per_s']:.0f}; "
                             "recorded before 3803"
                             if d.get("virtual_cycles_per_s") is not None
                             else "recorded before 3803"),
                    lambda: d["inprocess_cycles_per_s"] >= 5000, "inprocess_cycles_per_s")]


def twoproc_rows(d: dict[str, Any]) -> list[Row]:
    rates = d.get("lockstep_cycles_per_s")
    name = TWOPROC_ROW
    if not rates:
        why = (d.get("failed") or {}).get("lockstep_cycles_per_s") or "no lockstep run"
        return [Row(name, f"FAILED: {why}", "", "reported", Status.FAILED)]
    rates = sorted(rates)
    median = rates[len(rates) // 2]
    return [Row(name, f"{median:.0f}", f"where: {d.get('where', '?')}", "reported",
                Status.REPORTED, median)]


BENCHES = (
    Bench("bench_control.py", (), ("--quick",), control_rows),
    Bench("bench_motulator.py", (), ("--quick",), motulator_rows),
    Bench("bench_command.py", ("--sim",), ("--sim", "--repeats", "3"), command_rows),
    Bench("bench_lean.py", (), ("--repeats", "1"), lean_rows),
    Bench("bench_loop.py", ("--realtime-seconds", "0"),
          ("--quick", "--realtime-seconds", "0"), loop_rows),
)
TWOPROC = Bench("bench_twoproc.py", ("--seconds", "0", "--repeats", "3"),
                ("--seconds", "0", "--repeats", "1"), twoproc_rows)


def run_bench(bench: Bench, quick: bool, work: Path, vcan: str | None = None
              ) -> tuple[dict[str, Any] | None, str]:
    """Run one benchmark (its output streams through); (its JSON or None, why not).
    ``vcan``: inside scripts/vcan-run's sandbox of that kind (``auto``: its own choice)."""
    out = work / f"{Path(bench.script).stem}{'-' + vcan if vcan else ''}.json"
    args = bench.quick_args if quick else bench.args
    cmd = [sys.executable, str(ROOT / "bench" / bench.script), *args, "--json", str(out)]
    if vcan:
        kind = [] if vcan == "auto" else [f"--{vcan}"]
        cmd = [str(ROOT / "scripts" / "vcan-run"), "--timeout", f"{bench.timeout_s:.0f}",
               *kind, "--", *cmd]
    print(f"\n$ {' '.join(Path(c).name if i < 2 else c for i, c in enumerate(cmd))}",
          flush=True)
    try:
        done = subprocess.run(cmd, cwd=ROOT, stdin=subprocess.DEVNULL,
                              timeout=bench.timeout_s)
    except subprocess.TimeoutExpired:
        return None, f"{bench.script}: no end after {bench.timeout_s:g} s"
    except OSError as exc:
        return None, f"{bench.script}: cannot start ({exc.strerror or exc})"
    try:
        return json.loads(out.read_text()), ""
    except (OSError, ValueError):
        return None, f"{bench.script} gave no figures (exit status {done.returncode})"


def rows_of(bench: Bench, data: dict[str, Any] | None, why: str) -> list[Row]:
    """The benchmark's rows; without its JSON, each failed for ``why``."""
    if data is None:
        return [replace(r, figure=f"FAILED: {why}", baseline="", status=Status.FAILED,
                        value=None) for r in bench.rows({})]
    return bench.rows(data)


def host() -> dict[str, Any]:
    """What the figures depend on: CPU, cores, AVX-512/AMX, load, Python, commit."""
    model, flags = "", set()
    try:
        with open("/proc/cpuinfo") as f:
            for line in f:
                key, _, val = line.partition(":")
                if key.strip() == "model name" and not model:
                    model = val.strip()
                elif key.strip() == "flags" and not flags:
                    flags = set(val.split())
    except OSError:
        pass
    try:
        commit = subprocess.run(["git", "rev-parse", "--short", "HEAD"], cwd=ROOT, text=True,
                                capture_output=True, timeout=10).stdout.strip()
        dirty = subprocess.run(["git", "status", "--porcelain", "--untracked-files=no"],
                               cwd=ROOT, text=True, capture_output=True,
                               timeout=10).stdout.strip()
    except (OSError, subprocess.SubprocessError):
        commit, dirty = "", ""
    return {"cpu": model or platform.processor() or platform.machine(),
            "cores": os.cpu_count(),
            "avx512f": "avx512f" in flags, "amx": any(f.startswith("amx") for f in flags),
            "load_start": os.getloadavg()[0], "python": sys.version.split()[0],
            "commit": (commit + (" with uncommitted changes" if dirty else "")) or "unknown",
            "date": dt.datetime.now(dt.UTC).strftime("%Y-%m-%d %H:%M UTC")}


def markdown(rows: list[Row], info: dict[str, Any], command: str) -> str:
    yes = {True: "yes", False: "no"}
    lines = [
        "## The performance targets, one run — `bench/report.py`",
        "",
        f"`{command}`, {info['date']}, commit {info['commit']}; host: {info['cpu']}, "
        f"{info['cores']} cores, AVX-512 {yes[info['avx512f']]}, AMX {yes[info['amx']]}, "
        f"load average {info['load_start']:.2f} at the start and {info['load_end']:.2f} at "
        f"the end; Python {info['python']}. Each figure and its baseline come from the same "
        "run of its benchmark (the sections below give each benchmark's method and earlier "
        "measurements). Absolute times depend on the host: the ratios travel.",
        "",
        "| target | figure | baseline, same run | goal | |",
        "|---|---|---|---|---|",
    ]
    for r in rows:
        mark = {Status.MET: "met", Status.MISSED: "**missed**", Status.FAILED: "**failed**",
                Status.REPORTED: "reported", Status.NOT_RUN: "not run"}[r.status]
        lines.append(f"| {r.target} | {r.figure} | {r.baseline} | {r.goal} | {mark} |")
    return "\n".join(lines) + "\n"


def replace_section(text: str, section: str) -> str:
    """``text`` with the part between the markers replaced by ``section`` (markers kept), or
    with the marked section put before the first ``## `` heading (at the end if none)."""
    block = f"{BEGIN}\n{section}{END}\n"
    start, end = text.find(BEGIN), text.find(END)
    if start >= 0 and end > start:
        return text[:start] + block + "\n" + text[end + len(END):].lstrip("\n")
    if start >= 0 or end >= 0:
        raise ValueError("only one of the bench/report.py markers is there: put both back, "
                         "or remove the one left")
    at = text.find("\n## ")
    if at < 0:
        return text.rstrip("\n") + "\n\n" + block
    return text[:at + 1] + block + "\n" + text[at + 1:]


def write_atomically(path: Path, text: str) -> None:
    tmp = path.with_name(f".{path.name}.{os.getpid()}.tmp")
    try:
        with open(tmp, "w", encoding="utf-8") as f:
            f.write(text)
            f.flush()
            os.fsync(f.fileno())
        os.replace(tmp, path)
    except BaseException:
        tmp.unlink(missing_ok=True)
        raise


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(
        description=__doc__.splitlines()[0],
        epilog="Writes nothing but BENCHMARKS.md's marked section (with --write).")
    ap.add_argument("--quick", action="store_true", help="shorter runs of each benchmark")
    ap.add_argument("--vcan", nargs="?", const="auto", metavar="KINDS",
                    help="also two processes over vcan in lockstep (bench_twoproc.py inside "
                         "scripts/vcan-run's sandbox, about a minute under UML): the one it "
                         "chooses, or each of KINDS (comma-separated: uml, qemu; QEMU under "
                         "TCG boots in about 20 s more)")
    ap.add_argument("--write", action="store_true",
                    help="put the table in BENCHMARKS.md (its bench/report.py section)")
    ap.add_argument("--benchmarks", type=Path, default=BENCHMARKS, metavar="FILE",
                    help="the file --write updates (default BENCHMARKS.md)")
    ap.add_argument("--json", nargs="?", const="-", metavar="FILE",
                    help="also the rows as one JSON line on stdout (--json) or into FILE")
    args = ap.parse_args(argv)
    kinds = [k.strip() for k in args.vcan.split(",")] if args.vcan else []
    if any(k not in VCAN_KINDS for k in kinds) or len(set(kinds)) != len(kinds):
        ap.error(f"--vcan {args.vcan}: name sandbox kinds from {', '.join(VCAN_KINDS)}, "
                 "each once (comma-separated), or give none for scripts/vcan-run's choice")
    if args.write:  # refuse a file --write cannot update before measuring for minutes
        try:
            replace_section(args.benchmarks.read_text(encoding="utf-8"), "")
        except (OSError, ValueError) as exc:
            print(f"report.py: cannot update {args.benchmarks}: "
                  f"{getattr(exc, 'strerror', None) or exc}", file=sys.stderr)
            return 1
    info = host()
    rows: list[Row] = []
    with tempfile.TemporaryDirectory(prefix="bench-report-") as tmp:
        for bench in BENCHES:
            data, why = run_bench(bench, args.quick, Path(tmp))
            rows += rows_of(bench, data, why)
        for kind in kinds:
            data, why = run_bench(TWOPROC, args.quick, Path(tmp), vcan=kind)
            rows += [replace(r, target=f"{r.target}, sandbox: {kind}")
                     for r in rows_of(TWOPROC, data, why)]
        if not kinds:
            rows.append(Row(TWOPROC_ROW, "not run here (`--vcan` runs it)", "", "reported",
                            Status.NOT_RUN))
    info["load_end"] = os.getloadavg()[0]
    command = ".venv/bin/python bench/report.py" + "".join(
        f" --{o}" for o in ("quick", "write") if getattr(args, o)) + (
        "" if not kinds else " --vcan" if args.vcan == "auto" else f" --vcan {args.vcan}")
    table = markdown(rows, info, command)
    print("\n" + table)
    status = 0 if all(r.status in (Status.MET, Status.REPORTED, Status.NOT_RUN)
                      for r in rows) else 1
    if args.write:
        try:
            text = args.benchmarks.read_text(encoding="utf-8")
            write_atomically(args.benchmarks, replace_section(text, table))
        except (OSError, ValueError) as exc:
            print(f"report.py: {args.benchmarks} not written: "
                  f"{getattr(exc, 'strerror', None) or exc}", file=sys.stderr)
            return 1
        print(f"wrote {args.benchmarks} (its bench/report.py section)")
    if args.json:
        line = json.dumps({"host": info, "rows": [
            {"target": r.target, "figure": r.figure, "baseline": r.baseline, "goal": r.goal,
             "status": r.status.value, "value": r.value} for r in rows],
            "failed": {r.target: r.figure.removeprefix("FAILED: ") for r in rows
                       if r.status is Status.FAILED}}, ensure_ascii=False)
        if args.json == "-":
            print(line)
        else:
            Path(args.json).write_text(line + "\n")
    missed = [r.target for r in rows if r.status in (Status.MISSED, Status.FAILED)]
    if missed:
        print(f"{len(missed)} target(s) missed or not measured: {'; '.join(missed)}",
              file=sys.stderr)
    return status


if __name__ == "__main__":
    sys.exit(main())
