"""Benchmark of the emulated drive (plant.drive.Drive): simulated seconds per wall second.

    .venv/bin/python bench/bench_plant.py            # 0.2 s simulated per run, 7 runs
    .venv/bin/python bench/bench_plant.py --quick    # 0.05 s, 3 runs

For each mode the drive runs a field-oriented operating point (dq setpoints 4 + 2j A,
frame at 100 rad/s, rated-ish load, voltage feedforward) in periods of T = 1 ms at
f_pwm = 10 kHz. Printed: the median over the runs of simulated s per wall s (the ratio to
real time) and µs per internal step. Target: >= 10x real time with the current loop, i.e.
<= 10 µs per internal step in CPython. ``--check`` exits with status 1 below the target.
"""

from __future__ import annotations

import argparse
import cmath
import statistics
import sys
import time

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
    """Wall seconds to simulate t_sim seconds in periods of T."""
    motor = MotorParams()
    state, sp, T_L = operating_point(motor)
    drive = Drive(motor, DriveParams(mode=mode, f_pwm=f_pwm), state)  # type: ignore[arg-type]
    drive.enable(True)
    n = round(t_sim / T)
    w_0 = sp.w_0
    t0 = time.perf_counter()
    for k in range(n):
        drive.set_setpoints(Setpoints("dq", sp.i_s_ref, sp.u_s_ref, w_0 * k * T, w_0))
        drive.advance(T, T_L)
    wall = time.perf_counter() - t0
    # sanity: the operating point was held (a broken drive would be meaningless to time)
    i_dq = drive.state.i_s_ab * cmath.exp(-1j * w_0 * n * T)
    if abs(i_dq - sp.i_s_ref) > 0.05 * abs(sp.i_s_ref) and mode != "voltage":
        raise SystemExit(f"bench: {mode}: the drive lost the operating point (i_dq = {i_dq})")
    return wall


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--quick", action="store_true", help="short run (0.05 s, 3 repeats)")
    ap.add_argument("--T", type=float, default=1e-3, help="period per advance(), s")
    ap.add_argument("--f-pwm", type=float, default=10e3, help="internal rate, Hz")
    ap.add_argument("--check", action="store_true", help="exit 1 below the target")
    args = ap.parse_args(argv)
    t_sim, repeats = (0.05, 3) if args.quick else (0.2, 7)
    steps = round(t_sim * args.f_pwm)
    print(f"plant.drive.Drive: T = {args.T * 1e3:g} ms, f_pwm = {args.f_pwm / 1e3:g} kHz, "
          f"{t_sim:g} s simulated per run, median of {repeats} runs "
          f"(Python {sys.version.split()[0]})")
    print(f"{'mode':<14}{'sim s / wall s':>16}{'us / step':>12}{'x real time':>13}")
    ratios: dict[str, float] = {}
    for mode in DriveMode:
        run_once(mode, args.T, args.f_pwm, min(t_sim, 0.01))  # warm-up
        walls = [run_once(mode, args.T, args.f_pwm, t_sim) for _ in range(repeats)]
        wall = statistics.median(walls)
        ratios[mode] = t_sim / wall
        print(f"{mode:<14}{t_sim / wall:>16.1f}{wall / steps * 1e6:>12.2f}{t_sim / wall:>12.1f}x")
    ok = ratios["current-loop"] >= TARGET_X_REAL_TIME
    print(f"target: >= {TARGET_X_REAL_TIME:g}x real time with the current loop "
          f"(<= {1e6 / (TARGET_X_REAL_TIME * args.f_pwm):g} us per internal step): "
          f"{'met' if ok else 'NOT met'}")
    return 0 if ok or not args.check else 1


if __name__ == "__main__":
    raise SystemExit(main())
