"""Lean process data for 2 kHz on 1 Mbit/s: a cycle's bus time, and lockstep at 500 us.

    .venv/bin/python bench/bench_lean.py [--repeats N] [--json [FILE]]

Figures, the lean mapping (`--mapping lean`, gateway/drives/emulator-lean.toml) beside its
baseline, the default mapping (gateway/drives/emulator.toml):

* bus time per cycle: the bits of one cycle's frames (SYNC with its counter, the TPDOs, the
  RPDOs) with worst-case bit stuffing at the profile's bit rate (dbc/busload.py, the bound
  `hil-gateway profile check` prints), its share of a 500 us period (target: at most the
  85 % limit) and the shortest period each mapping fits;
* `hil-gateway sim --profile profiles/paper.toml --period 500us --mapping lean` in lockstep
  (the emulated drive in the same process), ``--repeats`` runs: cycles, missed cycles
  (target 0), the speed error's RMS and max (the accuracy, deterministic) and the wall time
  (median); beside it the default mapping at 1 ms, the shortest period it fits.

A run that does not complete is a failed measurement (bench/_common.py). ``--json [FILE]``
keys: ``python``, ``repeats``, ``<mapping>_bits``, ``<mapping>_bus_time_us``,
``<mapping>_load_500us``, ``<mapping>_min_period_us`` (mapping ``lean`` or ``default``),
``lean_500us_cycles``, ``lean_500us_missed``, ``lean_500us_rms_rad_s``,
``lean_500us_max_rad_s``, ``lean_500us_wall_s``, the same for ``default_1ms``,
``target_met`` (the lean cycle fits 500 us and its run missed no cycle; null when not
measured), ``failed``.
"""

from __future__ import annotations

import argparse
import statistics
import sys
import tempfile
from pathlib import Path

from _common import (
    Figures,
    add_json_option,
    read_summary,
    require_completed,
    run_command,
    the_run,
    warm_env,
)

from gateway.bustime import profile_load
from gateway.drive_profile import load_drive_profile

ROOT = Path(__file__).resolve().parents[1]
PERIOD_S = 500e-6
MAPPINGS = {"default": "emulator", "lean": "emulator-lean"}


def bus_time(builtin: str) -> dict[str, float]:
    """The cycle's bus time of a built-in emulator profile."""
    with the_run(f"drive profile {builtin}"):
        load = profile_load(load_drive_profile(None, builtin))
    return {"bits": load.busiest_bits, "bus_time_us": load.busiest_time * 1e6,
            "load_500us": load.load(PERIOD_S), "min_period_us": load.min_period() * 1e6}


def lockstep(words: list[str], repeats: int, work: Path) -> dict[str, float]:
    """`hil-gateway sim` of the paper profile in lockstep, ``repeats`` runs: the first run's
    cycles, missed and speed error (deterministic), the median wall time."""
    walls, first = [], None
    for r in range(repeats):
        out = work / f"run{r}"
        cmd = [sys.executable, "-m", "gateway", "sim", "--profile",
               str(ROOT / "profiles" / "paper.toml"), *words, "--no-figures",
               "--out", str(out), "--force"]
        with the_run(f"run {r + 1} of {repeats}"):
            run_command(cmd, ROOT, warm_env(), timeout=600)
            summary = read_summary(out)
        require_completed(summary, out)
        run = summary["run"]
        walls.append(run["wall_time_s"])
        if first is None:
            first = {"cycles": run["cycles"], "missed": run["missed_cycles"],
                     "rms_rad_s": summary["speed_error"]["rms"],
                     "max_rad_s": summary["speed_error"]["max"]}
    assert first is not None
    return {**first, "wall_s": statistics.median(walls)}


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--repeats", type=int, default=3,
                    help="lockstep runs of each mapping (default 3; the wall time's median)")
    add_json_option(ap)
    args = ap.parse_args(argv)
    if args.repeats < 1:
        ap.error("--repeats must be at least 1")
    python = sys.version.split()[0]
    fig = Figures(python=python, repeats=args.repeats)
    print(f"Python {python}; one cycle's frames at 1 Mbit/s (worst-case stuffing), and the "
          f"paper profile in lockstep (`sim`, median wall of {args.repeats})")
    for name, builtin in MAPPINGS.items():
        keys = [f"{name}_{k}" for k in ("bits", "bus_time_us", "load_500us", "min_period_us")]
        got = fig.measure_all(keys, lambda b=builtin, n=name: {
            f"{n}_{k}": v for k, v in bus_time(b).items()})
        if got is None:
            print(f"{name:8s} bus time: {fig.show(keys[0])}")
            continue
        print(f"{name:8s} bus time per cycle {got[keys[0]]:4d} bits = {got[keys[1]]:4.0f} us, "
              f"{got[keys[2]]:6.1%} of 500 us (limit 85 %), fits periods from "
              f"{got[keys[3]]:.0f} us")
    runs = {"lean_500us": ["--period", "500us", "--mapping", "lean"],
            "default_1ms": ["--period", "1ms"]}
    with tempfile.TemporaryDirectory(prefix="bench-lean-") as tmp:
        for label, words in runs.items():
            keys = [f"{label}_{k}" for k in ("cycles", "missed", "rms_rad_s", "max_rad_s",
                                              "wall_s")]
            work = Path(tmp) / label
            work.mkdir()
            got = fig.measure_all(keys, lambda w=words, d=work, lb=label: {
                f"{lb}_{k}": v for k, v in lockstep(w, args.repeats, d).items()})
            what = f"sim {' '.join(words)}"
            if got is None:
                print(f"{what:38s} {fig.show(keys[0])}")
                continue
            print(f"{what:38s} cycles {got[keys[0]]}, missed {got[keys[1]]}, speed error RMS "
                  f"{got[keys[2]] * 1e3:.2f} mrad/s (max {got[keys[3]] * 1e3:.2f}), wall "
                  f"{got[keys[4]]:.2f} s")
    measured = all(fig.ok(k) for k in ("lean_load_500us", "lean_500us_missed"))
    met = measured and (fig.values["lean_load_500us"] <= 0.85 + 1e-12
                        and fig.values["lean_500us_missed"] == 0)
    fig.put("target_met", met if measured else None)
    print(f"lean mapping at 500 us: {'meets' if met else 'MISSES'} the target (fits the "
          "period, 0 missed)" if measured else "lean mapping at 500 us: not measured")
    fig.report_failures()
    fig.emit(args.json)
    return fig.exit_status(bool(met))


if __name__ == "__main__":
    sys.exit(main())
