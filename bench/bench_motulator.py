"""Baseline: plant.drive.Drive against motulator on the same induction-motor drive, side by side.

    .venv/bin/pip install -e '.[bench]'                   # the baseline, motulator (an extra)
    .venv/bin/python bench/bench_motulator.py             # 0.5 s simulated per run, 5 runs
    .venv/bin/python bench/bench_motulator.py --quick     # 0.1 s, 3 runs
    .venv/bin/python bench/bench_motulator.py --T-s 125e-6 --carrier   # one motulator config

Both sides simulate the paper's 0.6 kW motor (R_s = 5.3 Ω, R_r = 3.3 Ω, L_s = 0.365 H,
L_r = 0.375 H, M = 0.34 H, J = 0.0075 kg·m², one pole pair) under current-vector control,
held at the operating point of bench_plant.py (i_dq = 4 + 2j A in rotor-flux coordinates,
frame at 100 rad/s, load torque balancing the motor torque, u_dc = 560 V), starting from
that steady state, for the same simulated time, alternately, each repeated. Printed: the
median of simulated s per wall s for each side and the ratio ours / motulator.

What each side computes (so the ratio is read honestly):

* ours (plant.drive.Drive, mode "current-loop"): model (1), states ω, ψ_r (complex),
  i_s (complex); a discrete PI current loop (+ voltage feedforward, limit, anti-windup) at
  f_pwm = 10 kHz; the voltage held over each 100 µs step (PWM average, no switching); one
  fixed-step classical RK4 step per 100 µs, written out on Python complex scalars; advance()
  called in T = 1 ms periods (what the HIL loop does), the dq setpoint frame turned by
  the drive. No data are stored.
* motulator (motulator.drive, its torque-mode current-vector control): the Γ model of
  the same machine (states ψ_s, ψ_r complex), a stiff mechanical system (ω_M, rotor
  angle), a stiff-DC-bus converter; its own discrete-time control system every T_s (default
  250 µs): a reduced-order flux observer (sensored mode here, the speed is measured like
  ours), a 2DOF complex-vector PI current controller (bandwidth 2π·200 rad/s),
  space-vector PWM duty ratios with one sampling period of computational delay. Per
  sampling period scipy.integrate.solve_ivp (RK45, adaptive step, default tolerances) is
  called once with the duty ratios held (zero-order hold: the average inverter model, its
  default), or, with carrier comparison, once per switching-state interval (up to 4 per
  period: the switching ripple simulated). All solver points are stored and post-processed
  into arrays at the end, as sim.simulate() does. Two configurations are run by default:
  its defaults (T_s = 250 µs, ZOH) and carrier comparison at T_s = 125 µs (the setting
  behind the "about 0.25x real time at 125 µs" figure); --T-s [--carrier] runs one.

Equivalences: motulator's space vectors are peak-scaled (torque 1.5·n_p·Im(i_s ψ_s*)), ours
are the two-phase model (1) (torque (M/L_r)·(ψ_r × i_s)); the same parameters give the
same electrical dynamics, and motulator is given J and T_L times 1.5 so that the
mechanical dynamics are the same too. The T-model parameters become motulator's
inverse-Γ ones (L_σ = L_s − M²/L_r, L_M = M²/L_r, R_R = R_r·(M/L_r)²) and its Γ ones.
Not the same: the control laws (rates, bandwidths, observer) differ, as named above; the
work per simulated second is what is compared, both sides holding the same operating
point (each run checks it at the end).

A run that fails (an exception from either simulator, the operating point lost) is a failed
measurement for its side: ``FAILED: <reason>`` in its row, the other sides go on, exit
status 1 (bench/_common.py). motulator not installed is not a failure (ours only).
``--json [FILE]`` keys: ``python``, ``t_sim_s``, ``repeats``, ``motulator`` (its version or
null), ``motulator_note`` (why not, or ""), ``ours_internal_rate_hz`` (--f-pwm: ours' inner
step rate), ``ours_x_real_time`` (median sim s / wall s),
``ours_x_real_time_runs``; per motulator configuration ``<c>`` (``motulator_250us_ZOH``,
``motulator_125us_PWM``) ``<c>_x_real_time``, ``<c>_x_real_time_runs``, ``<c>_ours_over_it``,
``<c>_points_per_sim_s``; ``ratio``, the headline: ``<c>_ours_over_it`` of the first
configuration (motulator's default, 250 µs ZOH, or ``--T-s``'s; null without motulator);
and ``failed``.
"""

from __future__ import annotations

import argparse
import cmath
import importlib.metadata
import statistics
import sys
import textwrap
import time
from typing import Any

from _common import Figures, RunError, add_json_option, failed_text, the_run
from bench_plant import operating_point, run_once

from dbc.motor import MotorParams
from plant.params import DriveParams

INSTALL_HINT = ".venv/bin/pip install -e '.[bench]'"  # motulator, the baseline
TORQUE_SCALE = 1.5  # motulator's peak-scaled torque over ours, same currents and fluxes


# ---- ours ----------------------------------------------------------------------------------
def run_ours(t_sim: float, T: float, f_pwm: float) -> tuple[float, float]:
    """(wall s, simulated s) for plant.drive.Drive in current-loop mode over t_sim
    (bench_plant's timed run: it also checks that the operating point was held)."""
    return run_once("current-loop", T, f_pwm, t_sim), round(t_sim / T) * T


# ---- motulator -----------------------------------------------------------------------------
def build_motulator(T_s: float, carrier: bool) -> tuple[Any, dict[str, float]]:
    """A motulator Simulation of our motor, started at bench_plant's operating point."""
    from motulator.drive import model
    from motulator.drive import utils as mutils
    from motulator.drive.control import im as control

    motor = MotorParams()
    state, sp, T_L = operating_point(motor)
    k_r = motor.M / motor.L_r
    inv_gamma = mutils.InductionMachineInvGammaPars(
        n_p=1, R_s=motor.R_s, R_R=motor.R_r * k_r**2, L_sgm=motor.sigma, L_M=motor.M * k_r
    )
    gamma = mutils.InductionMachinePars.from_inv_gamma_model_pars(inv_gamma)
    u_dc = DriveParams().u_dc

    machine = model.InductionMachine(gamma)
    mechanics = model.StiffMechanicalSystem(
        J=TORQUE_SCALE * motor.J, tau_L=lambda t: TORQUE_SCALE * T_L + 0 * t
    )
    converter = model.VoltageSourceConverter(u_dc=u_dc)
    mdl = model.Drive(converter, machine, mechanics)
    if carrier:
        mdl.pwm = model.CarrierComparison()

    # steady state at angle 0 (rotor flux on the a axis), as bench_plant's MotorState
    i_s = state.i_s_ab
    psi_R = inv_gamma.L_M * i_s.real  # inverse-Γ rotor flux = (M/L_r)·ψ_r
    psi_s = inv_gamma.L_sgm * i_s + psi_R
    machine.state.psi_ss = complex(psi_s)
    machine.state.psi_rs = complex(psi_s + gamma.L_ell * (psi_s / gamma.L_s - i_s))
    mechanics.state.w_M = state.w_m
    mechanics.state.exp_j_theta_M = complex(1)

    cfg = control.CurrentReferenceCfg(inv_gamma, max_i_s=2.0 * abs(i_s), nom_psi_R=psi_R)
    ctrl = control.CurrentVectorControl(inv_gamma, cfg, J=None, T_s=T_s, sensorless=False)
    tau_ref = 1.5 * inv_gamma.n_p * psi_R * i_s.imag  # gives i_sq = 2 A
    ctrl.ref.tau_M = lambda t: tau_ref + 0 * t
    # controller states at the same steady state: observer, integrator, PWM, delay
    u_dq = complex(sp.u_s_ref)
    ctrl.observer.est.psi_R = psi_R
    ctrl.observer.est.theta_s = 0.0
    ctrl.observer._work.old_i_s = i_s
    pi_ctrl = ctrl.current_ctrl
    pi_ctrl.u_i = u_dq + (pi_ctrl.k_p - pi_ctrl.k_t) * i_s
    u_ab0 = u_dq * cmath.exp(0.5j * sp.w_0 * T_s)  # ZOH over the first period
    ctrl.pwm.realized_voltage = u_ab0
    ctrl.pwm._old_u_cs = u_ab0
    mdl.delay.data = [list(ctrl.pwm.duty_ratios(u_ab0, u_dc))]

    sim = model.Simulation(mdl, ctrl)
    return sim, {"i_abs": abs(i_s), "w_m": state.w_m}


def run_motulator(t_sim: float, T_s: float, carrier: bool) -> tuple[float, float, int]:
    """(wall s, simulated s, solver points stored) for one motulator run over t_sim."""
    import numpy as np

    with the_run("motulator"):
        sim, expect = build_motulator(T_s, carrier)
        t0 = time.perf_counter()
        sim.simulate(t_stop=t_sim)
        wall = time.perf_counter() - t0
        mdl = sim.mdl
        t_done = float(mdl.t0)  # its loop runs while t0 <= t_stop: slightly past t_sim
        i_end = complex(mdl.machine.i_ss)
        w_end = float(np.real(mdl.mechanics.state.w_M))
        points = len(mdl.sol_t)
    if not (t_done >= 0.99 * t_sim and abs(abs(i_end) - expect["i_abs"]) <= 0.05 * expect["i_abs"]
            and abs(w_end - expect["w_m"]) <= 0.05 * abs(expect["w_m"])):
        raise RunError(
            f"motulator lost the operating point (t = {t_done:.4f} s, "
            f"|i_s| = {abs(i_end):.3f} A, w_m = {w_end:.2f} rad/s)"
        )
    return wall, t_done, points


# ---- main ----------------------------------------------------------------------------------
OURS_WHAT = (
    "ours: plant.drive.Drive current-loop: model (1), states w, psi_r, i_s; PI current loop "
    "+ feedforward at {f:g} kHz; fixed-step RK4, one step per {h:g} us, voltage held (PWM "
    "average); advance(T = {T:g} ms); nothing stored"
)
MOTULATOR_WHAT = (
    "motulator {ver} (scipy {scipy}): Gamma model (psi_s, psi_r) + stiff mechanics (w_M, "
    "angle); current-vector control (sensored flux observer, 2DOF PI 2pi*200 rad/s, SVPWM, "
    "1-period delay) every T_s; scipy solve_ivp RK45 (adaptive, default tolerances) once per "
    "{per}; every solver point stored"
)


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--quick", action="store_true", help="short run (0.1 s, 3 repeats)")
    ap.add_argument("--t-sim", type=float, default=None, help="simulated s per run (0.5)")
    ap.add_argument("--repeats", type=int, default=None, help="runs per side (5)")
    ap.add_argument("--T", type=float, default=1e-3, help="ours: period per advance(), s")
    ap.add_argument("--f-pwm", type=float, default=10e3, help="ours: internal rate, Hz")
    ap.add_argument("--T-s", type=float, default=None,
                    help="motulator: only this sampling period, s (default: both configs)")
    ap.add_argument("--carrier", action="store_true",
                    help="motulator: with --T-s, carrier comparison instead of its default ZOH")
    add_json_option(ap)
    args = ap.parse_args(argv)
    t_sim, repeats = (0.1, 3) if args.quick else (0.5, 5)
    t_sim = args.t_sim if args.t_sim is not None else t_sim
    repeats = args.repeats if args.repeats is not None else repeats
    if args.T_s is not None:
        configs = [(args.T_s, args.carrier)]
    else:
        # its defaults (T_s = 250 us, ZOH of the duty ratios), and the configuration behind
        # the "about 0.25x real time at 125 us sampling" (switching simulated)
        configs = [(250e-6, False), (125e-6, True)]

    why = f"not installed; install it with `{INSTALL_HINT}`"
    try:
        mver: str | None = importlib.metadata.version("motulator")
        from motulator.drive.control import im

        if not hasattr(im, "CurrentVectorControl"):  # the API this script is written for
            why = f"{mver} installed, but this script is written for the 0.5 API"
            mver = None
    except (importlib.metadata.PackageNotFoundError, ImportError):
        mver = None

    wrap = textwrap.TextWrapper(width=100, subsequent_indent="  ").fill
    python = sys.version.split()[0]
    print(f"{t_sim:g} s simulated per run, median of {repeats} runs per side, the sides "
          f"run alternately (Python {python})")
    print(wrap("operating point (both): paper's 0.6 kW motor, i_dq = 4+2j A, frame 100 rad/s, "
               "load balancing, u_dc = 560 V, started in steady state, checked at the end"))
    print(wrap(OURS_WHAT.format(f=args.f_pwm / 1e3, h=1e6 / args.f_pwm, T=args.T * 1e3)))
    fig = Figures(python=python, t_sim_s=t_sim, repeats=repeats, motulator=mver,
                  motulator_note="" if mver else why, ours_internal_rate_hz=args.f_pwm)
    if mver is None:
        print(f"motulator: {why} for the side-by-side comparison (ours only below)")
        configs = []
    else:
        import scipy

        print(wrap(MOTULATOR_WHAT.format(
            ver=mver, scipy=scipy.__version__,
            per="sampling period, duty ratios held (ZOH, its default) [ZOH], or once per "
                "switching-state interval, up to 4 per period (carrier comparison) [PWM]")))

    def label(T_s: float, carrier: bool) -> str:
        return f"motulator {T_s * 1e6:g}us {'PWM' if carrier else 'ZOH'}"

    def key(c: tuple[float, bool]) -> str:
        return label(*c).replace(" ", "_")

    def fail(side: str, why: str) -> None:
        """The side (``ours`` or a configuration's key) failed: its figures with it."""
        names = [f"{side}_x_real_time", f"{side}_x_real_time_runs"]
        if side != "ours":
            names += [f"{side}_ours_over_it", f"{side}_points_per_sim_s"]
        fig.fail(names, why)

    def warm_up(side: str, fn, *a) -> bool:
        try:
            fn(*a)
        except RunError as exc:
            fail(side, f"warm-up: {exc}")
            return False
        return True

    ours_ok = warm_up("ours", run_ours, min(t_sim, 0.01), args.T, args.f_pwm)
    theirs: dict[tuple[float, bool], list[float]] = {
        c: [] for c in configs if warm_up(key(c), run_motulator, min(t_sim, 0.01), *c)}
    ours: list[float] = []
    points: dict[tuple[float, bool], int] = {}
    for r in range(repeats):
        if ours_ok:
            try:
                wall, sim_t = run_ours(t_sim, args.T, args.f_pwm)
                ours.append(sim_t / wall)
            except RunError as exc:
                fail("ours", f"run {r + 1} of {repeats}: {exc}")
                ours_ok = False
        for c in list(theirs):
            try:
                wall, sim_t, points[c] = run_motulator(t_sim, *c)
            except RunError as exc:
                fail(key(c), f"run {r + 1} of {repeats}: {exc}")
                del theirs[c]
                continue
            theirs[c].append(sim_t / wall)

    m_ours = statistics.median(ours) if ours_ok else None
    print(f"{'side':<24}{'sim s/wall s (median)':>22}{'min':>8}{'max':>8}"
          f"{'ours/it':>9}{'points/sim s':>14}")
    if m_ours is None:
        print(f"{'ours':<24}  {failed_text(fig.failed['ours_x_real_time'])}")
    else:
        fig.put("ours_x_real_time", m_ours)
        fig.put("ours_x_real_time_runs", ours)
        print(f"{'ours':<24}{m_ours:>22.3f}{min(ours):>8.3f}{max(ours):>8.3f}{'':>9}{'':>14}")
    for c in configs:
        k = key(c)
        if c not in theirs:
            print(f"{label(*c):<24}  {failed_text(fig.failed[f'{k}_x_real_time'])}")
            continue
        xs = theirs[c]
        m = statistics.median(xs)
        fig.put(f"{k}_x_real_time", m)
        fig.put(f"{k}_x_real_time_runs", xs)
        if m_ours is None:
            fig.fail(f"{k}_ours_over_it", f"ours: {fig.failed['ours_x_real_time']}")
        else:
            fig.put(f"{k}_ours_over_it", m_ours / m)
        fig.put(f"{k}_points_per_sim_s", points[c] / t_sim)
        ratio = "" if m_ours is None else f"{m_ours / m:>8.1f}x"
        print(f"{label(*c):<24}{m:>22.3f}{min(xs):>8.3f}{max(xs):>8.3f}"
              f"{ratio:>9}{points[c] / t_sim:>14.0f}")
    # the headline: ours over motulator in its default configuration (or --T-s's)
    head = f"{key(configs[0])}_ours_over_it" if configs else None
    if head is None:
        fig.put("ratio", None)  # motulator not installed: motulator_note says why
    elif head in fig.failed:
        fig.fail("ratio", fig.failed[head])
    else:
        fig.put("ratio", fig.values[head])
        print(f"ratio ours / {label(*configs[0])}: {fig.values[head]:.1f}x (target >= 40x)")
    fig.report_failures()
    fig.emit(args.json)
    return fig.exit_status()


if __name__ == "__main__":
    raise SystemExit(main())
