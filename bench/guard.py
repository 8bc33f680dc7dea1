"""The divergence guard without a speed sensor: how often it stops a run that was
under control, how early it stops one that was not, and what it does with a load the laws
are not told.

    .venv/bin/python bench/guard.py               # both tables
    .venv/bin/python bench/guard.py --markdown    # Markdown for BENCHMARKS.md

Every run is simulated (sampled 1 ms, delay 1, (d, q), ideal drive) with no guard, and the
guard of ``gateway/guard.py`` (:class:`DivergenceWatch` on the profile's envelope) is then
replayed on the record *blind*: the truth columns (ω, |ψ_r|, T_e) removed, as from a real
drive that reports no speed. Table 1 counts, over the robustness cases (both designs; the
open-loop, drift-free and rs-adaptive estimators and the true flux; the paper, zero-speed
and slow-reversal profiles; nine plants), the runs that stayed within 20 rad/s of ω* and
were stopped anyway (false stops, by which check), and the runaways (max |ω − ω*| > 50 rad/s)
that were not stopped. Table 2 replays the untold loads: the rated and smaller torques
added from 1.2 s (the paper profile, scenario ``untold-load`` and variants) and the paper's
load shape (a step at 0.5 s, 0.5 N·m from 1 s) on the paper profile without its load, none
of it told. Nothing is fixed in advance: every figure is computed when the script runs
(about 3.5 minutes on one core).

A run that fails (an exception from the simulation or the guard's replay) is a failed
measurement: named with its reason (``FAILED: <reason>``), left out of the counts, the other
runs go on, exit status 1 (bench/_common.py). ``--json [FILE]`` keys: ``counts``
({"bounded" | "in between" | "runaway": {"stopped", "ran on"}}), ``runs`` (counted),
``false_stops``, ``runaways_not_stopped`` (lists of runs), ``runaways_stopped``,
``runaways_stopped_early``; ``"case: <run>"`` (null) for a run that failed;
``"untold: <load> / <design>"`` ({"max_error", "stopped_at_s", "by", "error_then",
"estimate_error_until_then"}, the last four null when not stopped) or null; ``seconds``;
``failed``.
"""

from __future__ import annotations

import argparse
import math
import sys
import time
from collections import Counter
from dataclasses import replace
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from _common import Figures, RunError, add_json_option, failed_text, the_run  # noqa: E402

from bench.robustness import RUNAWAY, sim_config  # noqa: E402
from dbc.motor import MotorParams  # noqa: E402
from gateway.cycle import CycleRow  # noqa: E402
from gateway.guard import DivergenceWatch, profile_envelope  # noqa: E402
from gateway.reference import Signal, load_profile, paper_profile  # noqa: E402
from gateway.session import run  # noqa: E402
from plant.scenario import parse_scenario, resolve_scenario  # noqa: E402

BOUNDED = 20.0  # rad/s: a run under control stays within this of ω*
MOTOR = MotorParams()
PLANTS = ("nominal", "rs+10", "rs-10", "offset10mA-rs+10", "offset10mA-rs-10", "rr+20",
          "rr-20", "real-drive", "noise5mA")
CONTROLLERS = {"open-loop": {"estimator": "open-loop"},
               "drift-free": {"estimator": "drift-free"},
               "rs-adaptive": {"estimator": "rs-adaptive"},
               "true flux": {"flux": "true"}}
UNTOLD = (ROOT / "plant" / "scenarios" / "untold-load.toml").read_text()


def blind_stop(sig: dict[str, np.ndarray], profile) -> tuple[int | None, str]:
    """The cycle index at which the guard stops the record without its truth, and why."""
    watch = DivergenceWatch(profile_envelope(profile, MOTOR, 20.0))
    for k in range(len(sig["t"])):
        row = CycleRow(**{f: float(sig[f][k]) for f in CycleRow._fields})
        if watch.check(row._replace(w_m=math.nan, psi_r_mod=math.nan, T_e=math.nan), k + 1):
            return k, watch.reason or ""
    return None, ""


def check_name(reason: str) -> str:
    """The guard's check that fired, from its reason."""
    if "field orientation lost" in reason:
        return "orientation"
    if "flux estimate below" in reason:
        return "flux deficit"
    return reason.split(": ", 1)[1].split(" = ")[0] if ": " in reason else reason


def simulate(profile, plant, **kw) -> dict[str, np.ndarray]:
    return run(sim_config(plant=plant, **kw), profile, MOTOR).sig


def simulate_and_replay(profile, plant, **kw) -> tuple[dict[str, np.ndarray], int | None, str]:
    """The record and the guard's blind stop on it; RunError when either fails."""
    with the_run():
        sig = simulate(profile, plant, **kw)
        return (sig, *blind_stop(sig, profile))


def cases_table(markdown: bool, fig: Figures | None = None) -> str:
    profiles = {"paper": paper_profile(),
                "zero-speed": load_profile(ROOT / "gateway" / "profiles" / "zero-speed.toml"),
                "slow-reversal": load_profile(ROOT / "gateway" / "profiles" /
                                              "slow-reversal.toml")}
    counts: Counter[tuple[str, str]] = Counter()
    false_stops: list[str] = []
    missed: list[str] = []
    early = []  # runaways: how long before |ω − ω*| > 20 rad/s the guard stopped them
    fig = fig if fig is not None else Figures()
    failed: list[str] = []
    for disc in ("exact", "euler"):
        for pname, prof in profiles.items():
            for plant in PLANTS:
                for cname, kw in CONTROLLERS.items():
                    run_name = f"{disc}, {pname}, {plant}, {cname}"
                    try:
                        sig, k, why = simulate_and_replay(prof, resolve_scenario(plant),
                                                          discretisation=disc, **kw)
                    except RunError as exc:
                        fig.fail(f"case: {run_name}", str(exc))
                        failed.append(f"{run_name}: {failed_text(str(exc))}")
                        continue
                    e = np.abs(sig["w_m"] - sig["w_ref"])
                    worst = float(e.max()) if np.isfinite(e).all() else math.inf
                    kind = ("bounded" if worst <= BOUNDED else
                            "runaway" if worst > RUNAWAY else "in between")
                    counts[(kind, "stopped" if k is not None else "ran on")] += 1
                    label = f"{run_name} (max {worst:.3g} rad/s)"
                    if kind == "bounded" and k is not None:
                        false_stops.append(f"{label}: {check_name(why)} at "
                                           f"{sig['t'][k]:.3f} s")
                    if kind == "runaway":
                        if k is None:
                            missed.append(label)
                        else:
                            t20 = sig["t"][np.argmax(e > BOUNDED)]
                            early.append(t20 - sig["t"][k])
    rows = [("within 20 rad/s of ω*", "bounded"), ("20–50 rad/s", "in between"),
            ("runaway (> 50 rad/s)", "runaway")]
    lines = ["| runs | stopped by the guard, blind | ran to the end |", "|---|---|---|"]
    for title, kind in rows:
        lines.append(f"| {title} | {counts[(kind, 'stopped')]} | {counts[(kind, 'ran on')]} |")
    text = "\n".join(lines if markdown else [ln.replace("|", " ") for ln in lines])
    n = sum(counts.values())
    text += (f"\n\n{n} runs. Stopped although within 20 rad/s: "
             + ("; ".join(false_stops) if false_stops else "none"))
    text += "\nRunaways not stopped: " + ("; ".join(missed) if missed else "none")
    lead = np.array(early) * 1e3
    if early:
        text += (f"\nRunaways stopped: {int(np.sum(lead > 0))} of {len(lead)} before their speed "
                 f"error passed {BOUNDED:g} rad/s (by up to {lead.max():.0f} ms), the others "
                 f"after it (median {np.median(-lead[lead <= 0]):.0f} ms, at most "
                 f"{-lead.min():.0f} ms)")
    if failed:
        text += f"\nRuns FAILED (not counted above): {len(failed)}: " + "; ".join(failed)
    fig.put("counts", {kind: {"stopped": counts[(kind, "stopped")],
                              "ran on": counts[(kind, "ran on")]} for _, kind in rows})
    fig.put("runs", n)
    fig.put("false_stops", false_stops)
    fig.put("runaways_not_stopped", missed)
    fig.put("runaways_stopped", len(early))
    fig.put("runaways_stopped_early", int(np.sum(lead > 0)))
    return text


def untold_table(markdown: bool, fig: Figures | None = None) -> str:
    paper = paper_profile()
    free = replace(paper, load=Signal(0.0))
    cases = []
    for extra in (1.0, 2.0, 3.0, 5.8):
        text = UNTOLD.replace("value = 5.8", f"value = {extra:g}")
        cases.append((f"{extra:g} N·m from 1.2 s", paper,
                      parse_scenario(text, f"untold {extra:g} N·m")))
    for extra in (1.0, 3.0, 5.8):  # the paper's load shape, untold: X at 0.5 s, 0.5 at 1 s
        text = (f"[load]\ntorque = \"none\"\nsteps = [{{ t = 0.5, value = {extra:g}, "
                "ramp = 0.01 }, { t = 1.0, value = 0.5, ramp = 0.01 }]\n")
        cases.append((f"{extra:g} N·m at 0.5–1 s, then 0.5 N·m, none told", free,
                      parse_scenario(text, f"untold step {extra:g}")))
    head = ("| untold load | design | max \\|ω − ω*\\| | stopped at | by | ω − ω* then | "
            "max \\|ω̂ − ω*\\| until then |")
    lines = [head, "|---|---|---|---|---|---|---|"]
    fig = fig if fig is not None else Figures()
    for title, prof, plant in cases:
        for disc in ("exact", "euler"):
            name = f"untold: {title} / {disc}"
            try:
                sig, k, why = simulate_and_replay(prof, plant, discretisation=disc,
                                                  estimator="rs-adaptive")
            except RunError as exc:
                fig.fail(name, str(exc))
                lines.append(f"| {title} | {disc} | {failed_text(str(exc))} | | | | |")
                continue
            e = sig["w_m"] - sig["w_ref"]
            if k is None:
                fig.put(name, {"max_error": np.abs(e).max(), "stopped_at_s": None, "by": None,
                               "error_then": None, "estimate_error_until_then": None})
                lines.append(f"| {title} | {disc} | {np.abs(e).max():.3g} | not stopped | "
                             "| | |")
                continue
            eh = np.abs(sig["w_hat"] - sig["w_ref"])[:k + 1].max()
            fig.put(name, {"max_error": np.abs(e).max(), "stopped_at_s": sig["t"][k],
                           "by": check_name(why), "error_then": e[k],
                           "estimate_error_until_then": eh})
            lines.append(f"| {title} | {disc} | {np.abs(e).max():.3g} | {sig['t'][k]:.3f} s "
                         f"| {check_name(why)} | {e[k]:.3g} | {eh:.3g} |")
    return "\n".join(lines if markdown else [ln.replace("|", " ") for ln in lines])


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--markdown", action="store_true", help="Markdown tables")
    add_json_option(ap)
    args = ap.parse_args(argv)
    fig = Figures()
    t0 = time.perf_counter()
    print("\nThe guard, blind, on the robustness cases\n")
    print(cases_table(args.markdown, fig), flush=True)
    print("\nLoads the laws are not told (rs-adaptive estimator; rad/s)\n")
    print(untold_table(args.markdown, fig))
    seconds = fig.put("seconds", time.perf_counter() - t0)
    print(f"\n({seconds:.0f} s)")
    fig.report_failures()
    fig.emit(args.json)
    return fig.exit_status()


if __name__ == "__main__":
    sys.exit(main())
