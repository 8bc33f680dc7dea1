"""Controller step cost: median µs per `Controller.step` (target ≤ 20 µs in CPython 3.11).

Run: .venv/bin/python bench/bench_control.py [--quick]

Each configuration steps the controller through the paper's scenario on recorded samples
(from a sampled simulation), so the cost includes the flux estimator, the frame rotations
and the law, but not the plant. Reported: median over repeats of the mean step time, and
the ratio to the 1 ms period budget. Also: `Profile.at` alone, and the sampled closed-loop
simulation (plant + controller + PDO quantisation) in simulated seconds per wall second.

A run that fails (an exception from the simulation or the controller) is a failed
measurement: ``FAILED: <reason>`` in place of its figure, the others go on, exit status 1
(bench/_common.py); so is a step over the target. ``--json [FILE]`` keys: ``python``,
``steps``, ``repeats``, ``<law>/<flux>/<design>_us_per_step`` (law ``current-fed`` or
``full-order``, flux ``estimated`` or ``true``, design ``euler`` or ``exact``),
``profile_at_us``, ``simulate_<law>/<drive>_x_real_time``, ``worst_us_per_step`` (over the
measured steps), ``target_met`` (null when a step figure failed), ``failed``.
"""

from __future__ import annotations

import argparse
import statistics
import sys
import time

from _common import Figures, RunError, add_json_option, the_run

from dbc.motor import MotorParams
from gateway.control.controller import ControllerConfig, Sample
from gateway.control.sampled import make_controller
from gateway.reference import paper_profile
from gateway.session import run
from gateway.spec import RunSpec

TARGET_US = 20.0


def _samples(law: str, n: int) -> list[tuple[object, Sample]]:
    """(references, sample) pairs from a sampled run of the paper scenario."""
    motor = MotorParams.paper()
    prof = paper_profile()
    drive = "ideal" if law == "current-fed" else "voltage"
    with the_run(f"the {law} samples' simulation"):
        sig = run(RunSpec(law=law, drive_mode=drive, duration=n * 1e-3), prof, motor).sig
    out = []
    for k in range(len(sig["t"])):
        t = float(sig["t"][k])
        s = Sample(complex(sig["i_sa"][k], sig["i_sb"][k]), complex(sig["u_sa"][k], sig["u_sb"][k]),
                   complex(sig["psi_r_mod"][k], 0.0))
        out.append((prof.at(t), s))
    return out


def bench_step(law: str, flux: str, samples, repeats: int, disc: str = "euler") -> float:
    """Median over repeats of the mean µs per step."""
    motor = MotorParams.paper()
    prof = paper_profile()
    times = []
    for _ in range(repeats):
        with the_run():
            cfg = ControllerConfig(law=law, flux=flux, discretisation=disc)
            ctl = make_controller(motor, cfg, prof.at)
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
        with the_run():
            t0 = time.perf_counter()
            for k in range(n):
                at(k * 1.25e-4)
            times.append((time.perf_counter() - t0) / n * 1e6)
    return statistics.median(times)


SIMULATED = (("current-fed", "ideal"), ("current-fed", "current-loop"), ("full-order", "voltage"))


def bench_simulate(law: str, drive: str, repeats: int, duration: float) -> float:
    """Simulated seconds per wall second of the sampled loop with this drive model."""
    motor = MotorParams.paper()
    prof = paper_profile()
    walls = []
    for _ in range(repeats):
        with the_run():
            t0 = time.perf_counter()
            run(RunSpec(law=law, drive_mode=drive, duration=duration), prof, motor)
            walls.append(time.perf_counter() - t0)
    return duration / statistics.median(walls)


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--quick", action="store_true", help="fewer steps and repeats")
    add_json_option(ap)
    args = ap.parse_args(argv)
    n, repeats = (500, 3) if args.quick else (2500, 7)
    python = sys.version.split()[0]
    fig = Figures(python=python, steps=n, repeats=repeats)
    print(f"Python {python}; controller step, median of {repeats} repeats "
          f"over {n} steps of the paper scenario (budget: {TARGET_US:g} us, period 1000 us)")
    print(f"{'law':12s} {'flux':10s} {'design':7s} {'us/step':>8s} {'vs target':>10s}")
    steps = []
    for law in ("current-fed", "full-order"):
        try:
            samples, why = _samples(law, n), ""
        except RunError as exc:  # every step figure of this law fails with it
            samples, why = None, str(exc)
        for flux in ("estimated", "true"):
            for disc in ("euler", "exact"):
                name = f"{law}/{flux}/{disc}_us_per_step"
                steps.append(name)
                if samples is None:
                    fig.fail(name, why)
                else:
                    fig.measure(name, bench_step, law, flux, samples, repeats, disc)
                cell = fig.show(name, lambda us: f"{us:8.2f} {us / TARGET_US:9.2f}x")
                print(f"{law:12s} {flux:10s} {disc:7s} {cell}")
    fig.measure("profile_at_us", bench_profile, repeats)
    print(f"Profile.at: {fig.show('profile_at_us', '{:.2f} us per call')}")
    print("sampled closed loop (plant + controller + INT16 PDO codec), 1 ms period, "
          "drive inner loop 10 kHz:")
    for law, drive in SIMULATED:
        name = f"simulate_{law}/{drive}_x_real_time"
        fig.measure(name, bench_simulate, law, drive, max(1, repeats // 2),
                    0.5 if args.quick else 2.5)
        print(f"  {law + '/' + drive:26s} {fig.show(name, '{:6.1f}x real time')}")
    measured = [fig.values[k] for k in steps if fig.ok(k)]
    worst = fig.put("worst_us_per_step", max(measured) if measured else None)
    ok = worst is not None and worst <= TARGET_US
    fig.put("target_met", ok if len(measured) == len(steps) else None)
    if worst is None:
        print("worst step: no step measured")
    else:
        print(f"worst step {worst:.2f} us: {'meets' if ok else 'MISSES'} the {TARGET_US:g} us "
              f"target{'' if len(measured) == len(steps) else ' (of the steps measured)'}")
    fig.report_failures()
    fig.emit(args.json)
    return fig.exit_status(ok)


if __name__ == "__main__":
    sys.exit(main())
