"""Controller step cost: median µs per `Controller.step` (target ≤ 20 µs in CPython 3.11).

Run: .venv/bin/python bench/bench_control.py [--quick]

Each configuration steps the controller through the paper's scenario on recorded samples
(from a sampled simulation), so the cost includes the flux estimator, the frame rotations
and the law, but not the plant. Reported: median over repeats of the mean step time, and
the ratio to the 1 ms period budget. Also: `Profile.at` alone, and the sampled closed-loop
simulation (plant + controller + PDO quantisation) in simulated seconds per wall second.
"""

from __future__ import annotations

import argparse
import statistics
import sys
import time

from dbc.motor import MotorParams
from gateway.control.controller import Controller, ControllerConfig, Sample
from gateway.reference import paper_profile
from gateway.simulate import SimConfig, run

TARGET_US = 20.0


def _samples(law: str, n: int) -> list[tuple[object, Sample]]:
    """(references, sample) pairs from a sampled run of the paper scenario."""
    motor = MotorParams.paper()
    prof = paper_profile()
    drive = "ideal" if law == "current-fed" else "voltage"
    sig = run(prof, motor, SimConfig(law=law, drive_mode=drive, duration=n * 1e-3)).arrays()
    out = []
    for k in range(len(sig["t"])):
        t = float(sig["t"][k])
        s = Sample(complex(sig["i_sa"][k], sig["i_sb"][k]), complex(sig["u_sa"][k], sig["u_sb"][k]),
                   complex(sig["psi_r_mod"][k], 0.0))
        out.append((prof.at(t), s))
    return out


def bench_step(law: str, flux: str, samples, repeats: int) -> float:
    """Median over repeats of the mean µs per step."""
    motor = MotorParams.paper()
    times = []
    for _ in range(repeats):
        ctl = Controller(motor, ControllerConfig(law=law, flux=flux))  # type: ignore[arg-type]
        step = ctl.step
        t0 = time.perf_counter()
        for refs, s in samples:
            step(refs, s)
        times.append((time.perf_counter() - t0) / len(samples) * 1e6)
    return statistics.median(times)


def bench_profile(repeats: int, n: int = 20000) -> float:
    prof = paper_profile()
    at = prof.at
    times = []
    for _ in range(repeats):
        t0 = time.perf_counter()
        for k in range(n):
            at(k * 1.25e-4)
        times.append((time.perf_counter() - t0) / n * 1e6)
    return statistics.median(times)


def bench_simulate(repeats: int, duration: float) -> dict[str, float]:
    """Simulated seconds per wall second of the sampled loop, per drive model."""
    motor = MotorParams.paper()
    prof = paper_profile()
    out = {}
    for law, drive in (("current-fed", "ideal"), ("current-fed", "current-loop"),
                       ("full-order", "voltage")):
        walls = []
        for _ in range(repeats):
            t0 = time.perf_counter()
            run(prof, motor, SimConfig(law=law, drive_mode=drive, duration=duration))
            walls.append(time.perf_counter() - t0)
        out[f"{law}/{drive}"] = duration / statistics.median(walls)
    return out


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--quick", action="store_true", help="fewer steps and repeats")
    args = ap.parse_args(argv)
    n, repeats = (500, 3) if args.quick else (2500, 7)
    print(f"Python {sys.version.split()[0]}; controller step, median of {repeats} repeats "
          f"over {n} steps of the paper scenario (budget: {TARGET_US:g} us, period 1000 us)")
    print(f"{'law':12s} {'flux':10s} {'us/step':>8s} {'vs target':>10s}")
    worst = 0.0
    for law in ("current-fed", "full-order"):
        samples = _samples(law, n)
        for flux in ("estimated", "true"):
            us = bench_step(law, flux, samples, repeats)
            worst = max(worst, us)
            print(f"{law:12s} {flux:10s} {us:8.2f} {us / TARGET_US:9.2f}x")
    print(f"Profile.at: {bench_profile(repeats):.2f} us per call")
    print("sampled closed loop (plant + controller + INT16 PDO codec), 1 ms period, "
          "drive inner loop 10 kHz:")
    for key, speed in bench_simulate(max(1, repeats // 2), 0.5 if args.quick else 2.5).items():
        print(f"  {key:26s} {speed:6.1f}x real time")
    ok = worst <= TARGET_US
    print(f"worst step {worst:.2f} us: {'meets' if ok else 'MISSES'} the {TARGET_US:g} us target")
    return 0 if ok else 1


if __name__ == "__main__":
    sys.exit(main())
