"""Benchmark of the emulated drive (plant.drive.Drive): simulated seconds per wall second.

    .venv/bin/python bench/bench_plant.py            # 0.2 s simulated per run, 7 runs
    .venv/bin/python bench/bench_plant.py --quick    # 0.05 s, 3 runs

For each mode the drive runs a field-oriented operating point (dq setpoints 4 + 2j A,
frame at 100 rad/s, rated-ish load, voltage feedforward) in periods of T = 1 ms at
f_pwm = 10 kHz. Printed: the median over the runs of simulated s per wall s (the ratio to
real time) and µs per internal step. Target: >= 10x real time with the current loop, i.e.
<= 10 µs per internal step in CPython. ``--check`` exits with status 1 below the target.

A mode whose run fails (an exception from the drive model, the operating point lost) is a
failed measurement: ``FAILED: <reason>`` in its row, exit status 1 (bench/_common.py).
``--json [FILE]`` keys: ``python``, ``t_sim_s``, ``repeats``, per mode ``<mode>_x_real_time``
and ``<mode>_us_per_step`` (modes ``ideal``, ``current-loop``, ``voltage``), ``target_met``
(null when the current loop failed), ``failed``.
"""

from __future__ import annotations

import argparse
import cmath
import statistics
import sys
import time

from _common import Figures, RunError, add_json_option, the_run

from dbc.modes import DriveMode
from dbc.motor import MotorParams
from plant.drive import Drive, MotorState, Setpoints
from plant.params import DriveParams

TARGET_X_REAL_TIME = 10.0


def operating_point(motor: MotorParams) -> tuple[MotorState, Setpoints, float]:
    """Steady state under i_dq = 4 + 2j A with the frame at 100 rad/s (slip relation (11))."""
    i_dq, w_0 = 4.0 + 2.0j, 100.0
    psi_rd = motor.M * i_dq.real
    w_m = w_0 - motor.alpha * motor.M * i_dq.imag / psi_rd
    T_L = motor.J * motor.mu * psi_rd * i_dq.imag
    psi_s_dq = motor.sigma * i_dq + motor.M / motor.L_r * psi_rd
    u_dq = motor.R_s * i_dq + 1j * w_0 * psi_s_dq
    state = MotorState(w_m, psi_rd + 0j, i_dq)
    return state, Setpoints("dq", i_dq, u_dq, 0.0, w_0), T_L


def run_once(mode: str, T: float, f_pwm: float, t_sim: float) -> float:
    """Wall seconds to simulate t_sim seconds in periods of T; RunError when the drive
    model raises or loses the operating point."""
    motor = MotorParams()
    state, sp, T_L = operating_point(motor)
    n = round(t_sim / T)
    w_0 = sp.w_0
    with the_run():
        drive = Drive(motor, DriveParams(mode=mode, f_pwm=f_pwm), state)  # type: ignore[arg-type]
        drive.enable(True)
        t0 = time.perf_counter()
        for k in range(n):
            drive.set_setpoints(Setpoints("dq", sp.i_s_ref, sp.u_s_ref, w_0 * k * T, w_0))
            drive.advance(T, T_L)
        wall = time.perf_counter() - t0
        i_s_ab = drive.state.i_s_ab
    # sanity: the operating point was held (a broken drive would be meaningless to time)
    i_dq = i_s_ab * cmath.exp(-1j * w_0 * n * T)
    if not abs(i_dq - sp.i_s_ref) <= 0.05 * abs(sp.i_s_ref) and mode != "voltage":
        raise RunError(f"{mode}: the drive lost the operating point (i_dq = {i_dq:.4g})")
    return wall


def median_wall(mode: str, T: float, f_pwm: float, t_sim: float, repeats: int) -> float:
    run_once(mode, T, f_pwm, min(t_sim, 0.01))  # warm-up
    return statistics.median(run_once(mode, T, f_pwm, t_sim) for _ in range(repeats))


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--quick", action="store_true", help="short run (0.05 s, 3 repeats)")
    ap.add_argument("--T", type=float, default=1e-3, help="period per advance(), s")
    ap.add_argument("--f-pwm", type=float, default=10e3, help="internal rate, Hz")
    ap.add_argument("--check", action="store_true", help="exit 1 below the target")
    add_json_option(ap)
    args = ap.parse_args(argv)
    t_sim, repeats = (0.05, 3) if args.quick else (0.2, 7)
    steps = round(t_sim * args.f_pwm)
    python = sys.version.split()[0]
    print(f"plant.drive.Drive: T = {args.T * 1e3:g} ms, f_pwm = {args.f_pwm / 1e3:g} kHz, "
          f"{t_sim:g} s simulated per run, median of {repeats} runs (Python {python})")
    print(f"{'mode':<14}{'sim s / wall s':>16}{'us / step':>12}{'x real time':>13}")
    fig = Figures(python=python, t_sim_s=t_sim, repeats=repeats)

    def measure(mode: str) -> dict[str, float]:
        wall = median_wall(mode, args.T, args.f_pwm, t_sim, repeats)
        return {f"{mode}_x_real_time": t_sim / wall, f"{mode}_us_per_step": wall / steps * 1e6}

    for mode in (m for m in DriveMode if not m.standard):  # the model's current sources
        ratio_key, step_key = f"{mode}_x_real_time", f"{mode}_us_per_step"
        if fig.measure_all([ratio_key, step_key], measure, mode) is None:
            print(f"{mode:<14}{fig.show(ratio_key)}")
            continue
        ratio, us = fig.values[ratio_key], fig.values[step_key]
        print(f"{mode:<14}{ratio:>16.1f}{us:>12.2f}{ratio:>12.1f}x")
    ratio = fig.values["current-loop_x_real_time"]
    ok = ratio is not None and ratio >= TARGET_X_REAL_TIME
    fig.put("target_met", None if ratio is None else ok)
    print(f"target: >= {TARGET_X_REAL_TIME:g}x real time with the current loop "
          f"(<= {1e6 / (TARGET_X_REAL_TIME * args.f_pwm):g} us per internal step): "
          f"{'not measured' if ratio is None else 'met' if ok else 'NOT met'}")
    fig.report_failures()
    fig.emit(args.json)
    return fig.exit_status(ok or not args.check)


if __name__ == "__main__":
    raise SystemExit(main())
