"""Controller step cost: median µs per `Controller.step`, the sampled-data design (exact)
beside the Euler design in the same run and beside the figures recorded before.

Run: .venv/bin/python bench/bench_control.py [--quick]

Each configuration steps the controller through the paper's scenario on recorded samples
(from a sampled simulation), so the cost includes the flux estimator, the frame rotations,
the references (the profile's ``at``, as in a run) and the law, but not the plant. Each
repeat steps every design once, interleaved, so that a load on the machine weighs on both
alike. Reported per configuration: the median over repeats of the mean step time, wall
clock (``perf_counter``) and CPU time of the thread (``thread_time``: what the step costs
when it has a core; on a shared machine the wall figure also holds the time other
processes had the core). Targets (the sampled-data design, estimated flux, CPU time):
current-fed ≤ 10 µs, full-order ≤ 12 µs. Also: `Profile.at` alone, the sampled closed
loop (plant + controller + PDO quantisation) in simulated seconds per wall second, and the
one long step of a run: the cycle that ends the magnetisation solves the standstill
identification (ms, wall clock, at 1 ms and 5 ms periods, beside the figure recorded
before its fit was made one Gauss–Newton: in real time the cycles after it wait for it).

A run that fails (an exception from the simulation or the controller) is a failed
measurement: ``FAILED: <reason>`` in place of its figure, the others go on, exit status 1
(bench/_common.py); so is a missed target. ``--json [FILE]`` keys: ``python``, ``steps``,
``repeats``; ``<law>/<flux>/<design>_us_per_step`` and ``…_cpu_us_per_step`` (law
``current-fed`` or ``full-order``, flux ``estimated`` or ``true``, design ``euler`` or
``exact``); the headline figures, estimated flux: ``exact_current_fed_us``,
``exact_current_fed_cpu_us``, ``euler_current_fed_us``, ``euler_current_fed_cpu_us``,
``exact_current_fed_vs_euler`` (CPU ratio), ``recorded_current_fed_us`` (the median
recorded before this design was made faster, BENCHMARKS.md), ``exact_current_fed_vs_recorded``
(wall ratio), and the same with ``full_order``; ``profile_at_us``,
``simulate_<law>/<drive>_x_real_time``, ``identification_step_ms/<period>`` and
``recorded_identification_step_ms/<period>`` (period ``1ms``, ``5ms``), ``targets_us``,
``target_met`` (null when a headline figure failed), ``failed``.
"""

from __future__ import annotations

import argparse
import statistics
import sys
import time

from _common import Figures, RunError, add_json_option, the_run

from dbc.motor import MotorParams
from dbc.timing import Sampling
from gateway.control.controller import ControllerConfig, Sample
from gateway.control.sampled import make_controller
from gateway.reference import paper_profile
from gateway.session import run
from gateway.spec import RunSpec

#: The sampled-data design's targets, µs per step (CPU time, estimated flux).
TARGETS_US = {"current-fed": 10.0, "full-order": 12.0}
#: Median µs per step of the sampled-data design before it was made faster (BENCHMARKS.md,
#: "Controller"; wall clock on the shared machine, 2026-11-25).
RECORDED_US = {"current-fed": 27.9, "full-order": 35.0}
DESIGNS = ("euler", "exact")
#: The step that solves the identification, ms, before its fit was made one Gauss–Newton
#: (a grid of 41 α's; wall clock on the shared machine, 2026-11-27), by period in ms.
RECORDED_IDENT_MS = {1: 34.6, 5: 12.1}


def _samples(law: str, n: int, sampling: Sampling | None = None
             ) -> list[tuple[object, Sample]]:
    """(references, sample) pairs from a sampled run of the paper scenario, ``n`` periods
    (default: 1 ms)."""
    motor = MotorParams.paper()
    prof = paper_profile()
    drive = "ideal" if law == "current-fed" else "voltage"
    sampling = sampling or Sampling()
    with the_run(f"the {law} samples' simulation at {sampling.period * 1e3:g} ms"):
        sig = run(RunSpec(law=law, drive_mode=drive, sampling=sampling,
                          duration=n * sampling.period, identify=False), prof, motor).sig
    out = []
    for k in range(len(sig["t"])):
        t = float(sig["t"][k])
        s = Sample(complex(sig["i_sa"][k], sig["i_sb"][k]), complex(sig["u_sa"][k], sig["u_sb"][k]),
                   complex(sig["psi_r_mod"][k], 0.0))
        out.append((prof.at(t), s))
    return out


def _step_once(law: str, flux: str, disc: str, samples) -> tuple[float, float]:
    """(wall µs, CPU µs) per step, mean over the samples, one controller from its start."""
    motor = MotorParams.paper()
    prof = paper_profile()
    with the_run():
        cfg = ControllerConfig(law=law, flux=flux, discretisation=disc)
        ctl = make_controller(motor, cfg, prof.at)
        step = ctl.step
        t0, c0 = time.perf_counter(), time.thread_time()
        for refs, s in samples:
            step(refs, s)
        c1, t1 = time.thread_time(), time.perf_counter()
    return (t1 - t0) / len(samples) * 1e6, (c1 - c0) / len(samples) * 1e6


def bench_steps(law: str, flux: str, samples, repeats: int) -> dict[str, float]:
    """Medians over ``repeats`` of each design's mean µs per step (wall and CPU), the
    designs interleaved within each repeat."""
    wall: dict[str, list[float]] = {d: [] for d in DESIGNS}
    cpu: dict[str, list[float]] = {d: [] for d in DESIGNS}
    for _ in range(repeats):
        for disc in DESIGNS:
            w, c = _step_once(law, flux, disc, samples)
            wall[disc].append(w)
            cpu[disc].append(c)
    out = {}
    for disc in DESIGNS:
        out[f"{law}/{flux}/{disc}_us_per_step"] = statistics.median(wall[disc])
        out[f"{law}/{flux}/{disc}_cpu_us_per_step"] = statistics.median(cpu[disc])
    return out


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
            run(RunSpec(law=law, drive_mode=drive, duration=duration, identify=False), prof, motor)
            walls.append(time.perf_counter() - t0)
    return duration / statistics.median(walls)


def bench_identification(period_ms: int, repeats: int) -> float:
    """Median ms of the step that ends the magnetisation (the default controller, the
    identification on), over ``repeats`` controllers fed the same recorded samples."""
    motor = MotorParams.paper()
    prof = paper_profile()
    sampling = Sampling(period_ms * 1e-3, 1)
    samples = _samples("current-fed", round(400 / period_ms), sampling)
    times = []
    for _ in range(repeats):
        with the_run():
            ctl = make_controller(motor, ControllerConfig(sampling=sampling, identify=True),
                                  prof.at)
            for refs, s in samples:
                t0 = time.perf_counter()
                ctl.step(refs, s)
                dt = time.perf_counter() - t0
                if ctl.commissioning.result is not None:
                    times.append(dt * 1e3)
                    break
            else:
                raise RunError("the identification was not solved within 0.4 s")
    return statistics.median(times)


def _headline(fig: Figures, law: str) -> bool | None:
    """The law's headline figures (estimated flux) beside their baselines; whether the
    target is met (None when a figure failed)."""
    key = law.replace("-", "_")
    base = f"{law}/estimated"
    names = [f"{base}/{d}_{k}us_per_step" for d in DESIGNS for k in ("", "cpu_")]
    if not all(fig.ok(n) for n in names):
        return None
    exact, exact_cpu = fig.values[f"{base}/exact_us_per_step"], fig.values[
        f"{base}/exact_cpu_us_per_step"]
    euler, euler_cpu = fig.values[f"{base}/euler_us_per_step"], fig.values[
        f"{base}/euler_cpu_us_per_step"]
    fig.put(f"exact_{key}_us", exact)
    fig.put(f"exact_{key}_cpu_us", exact_cpu)
    fig.put(f"euler_{key}_us", euler)
    fig.put(f"euler_{key}_cpu_us", euler_cpu)
    fig.put(f"exact_{key}_vs_euler", exact_cpu / euler_cpu)
    fig.put(f"recorded_{key}_us", RECORDED_US[law])
    fig.put(f"exact_{key}_vs_recorded", exact / RECORDED_US[law])
    ok = exact_cpu <= TARGETS_US[law]
    print(f"{law:12s} exact {exact:6.2f} us (CPU {exact_cpu:5.2f}) | euler {euler:6.2f} us "
          f"(CPU {euler_cpu:5.2f}), exact/euler {exact_cpu / euler_cpu:4.2f} | recorded "
          f"before {RECORDED_US[law]:g} us, now/before {exact / RECORDED_US[law]:4.2f} | "
          f"target {TARGETS_US[law]:g} us (CPU): {'met' if ok else 'MISSED'}")
    return ok


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--quick", action="store_true", help="fewer steps and repeats")
    add_json_option(ap)
    args = ap.parse_args(argv)
    n, repeats = (500, 3) if args.quick else (2500, 9)
    python = sys.version.split()[0]
    fig = Figures(python=python, steps=n, repeats=repeats, targets_us=dict(TARGETS_US))
    print(f"Python {python}; controller step, median of {repeats} repeats over {n} steps of "
          "the paper scenario, designs interleaved (period 1000 us)")
    print(f"{'law':12s} {'flux':10s} {'design':7s} {'us/step':>8s} {'CPU us':>8s}")
    for law in ("current-fed", "full-order"):
        try:
            samples, why = _samples(law, n), ""
        except RunError as exc:  # every step figure of this law fails with it
            samples, why = None, str(exc)
        for flux in ("estimated", "true"):
            names = [f"{law}/{flux}/{d}_{k}us_per_step" for d in DESIGNS for k in ("", "cpu_")]
            if samples is None:
                fig.fail(names, why)
            else:
                fig.measure_all(names, bench_steps, law, flux, samples, repeats)
            for disc in DESIGNS:
                name = f"{law}/{flux}/{disc}_us_per_step"
                cpu = f"{law}/{flux}/{disc}_cpu_us_per_step"
                cell = fig.show(name, lambda us, cpu=cpu: f"{us:8.2f} "
                                f"{fig.values[cpu]:8.2f}")
                print(f"{law:12s} {flux:10s} {disc:7s} {cell}")
    print("the sampled-data design (exact), estimated flux, beside its baselines:")
    met = [_headline(fig, law) for law in ("current-fed", "full-order")]
    fig.measure("profile_at_us", bench_profile, repeats)
    print(f"Profile.at: {fig.show('profile_at_us', '{:.2f} us per call')}")
    print("sampled closed loop (plant + controller + INT16 PDO codec), 1 ms period, "
          "drive inner loop 10 kHz:")
    for law, drive in SIMULATED:
        name = f"simulate_{law}/{drive}_x_real_time"
        fig.measure(name, bench_simulate, law, drive, max(1, repeats // 2),
                    0.5 if args.quick else 2.5)
        print(f"  {law + '/' + drive:26s} {fig.show(name, '{:6.1f}x real time')}")
    print("the step that solves the standstill identification (the cycle that ends the "
          "magnetisation):")
    for period_ms in (1, 5):
        name = f"identification_step_ms/{period_ms}ms"
        fig.measure(name, bench_identification, period_ms, repeats)
        fig.put(f"recorded_identification_step_ms/{period_ms}ms", RECORDED_IDENT_MS[period_ms])
        ratio = (f", now/before {fig.values[name] / RECORDED_IDENT_MS[period_ms]:.2f}"
                 if fig.ok(name) else "")
        print(f"  period {period_ms} ms: {fig.show(name, '{:6.2f} ms')} | recorded before "
              f"{RECORDED_IDENT_MS[period_ms]:g} ms{ratio}")
    ok = all(m is True for m in met)
    fig.put("target_met", None if None in met else ok)
    fig.report_failures()
    fig.emit(args.json)
    return fig.exit_status(ok)


if __name__ == "__main__":
    sys.exit(main())
