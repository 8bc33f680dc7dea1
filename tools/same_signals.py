"""Are two trees' simulations the same, bit for bit? (development tool, not installed)

Run: .venv/bin/python tools/same_signals.py OLD_TREE [NEW_TREE] [--runs DIR] [--only NAME]

Runs ``hil-gateway simulate`` in each configuration of :data:`CONFIGS` with the package of
``OLD_TREE`` and of ``NEW_TREE`` (default: this repository) on ``PYTHONPATH`` (the figures
are drawn but not compared), and compares every column of ``signals.csv``: ``equal`` when
the files are identical byte for byte (floats are written with ``repr``, so that is bit for
bit), otherwise the largest relative difference per column. ``summary.json`` is compared
too, without its wall time. Then the sampled-data controllers alone, in configurations a
simulation does not reach (:data:`CONTROLLERS`: missed cycles, withheld commands, a delay
of 2, an initial angle and speed): every command of each, step by step, hashed in each tree.
The old tree's runs are kept in ``--runs`` (default /tmp/same-signals) and reused when
present: make the old tree with ``git archive <base commit> | tar -x -C /tmp/perf-old``.
Exit status 0 when everything is equal, 1 otherwise.
"""

from __future__ import annotations

import argparse
import csv
import json
import math
import os
import subprocess
import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]

#: name → the command line's words after ``simulate``
CONFIGS: dict[str, list[str]] = {
    "default": [],
    "flux-true": ["--flux", "true"],
    "full-order-voltage": ["--law", "full-order", "--drive-mode", "voltage"],
    "full-order-true": ["--law", "full-order", "--drive-mode", "voltage", "--flux", "true"],
    "period-2ms": ["--period", "2ms"],
    "period-250us": ["--period", "250us"],
    "current-loop": ["--drive-mode", "current-loop"],
    "setpoints-ab": ["--setpoint-frame", "ab"],
    "delay-0": ["--delay", "0"],
    "plant-rs+10": ["--plant", "rs+10"],
    "drift-free": ["--estimator", "drift-free"],
    "rs-adaptive": ["--estimator", "rs-adaptive"],
    "load-untold": ["--load", "untold"],
    "controller-ifoc": ["--controller", "ifoc"],
    "identify": ["--identify"],
    "load-observed": ["--load", "observed"],
    "euler": ["--discretisation", "euler"],
    "full-order-euler": ["--law", "full-order", "--drive-mode", "voltage",
                         "--discretisation", "euler"],
    "continuous": ["--period", "continuous", "--flux", "true", "--duration", "0.5"],
}


def simulate(tree: Path, words: list[str], out: Path) -> None:
    env = {**os.environ, "PYTHONPATH": str(tree)}
    cmd = [sys.executable, "-m", "gateway", "simulate", *words, "--out", str(out), "--force"]
    done = subprocess.run(cmd, env=env, cwd=tree, capture_output=True, text=True)
    if not (out / "signals.csv").is_file():
        raise RuntimeError(f"{' '.join(cmd)} wrote no signals.csv (exit {done.returncode}):\n"
                           f"{done.stderr[-2000:]}")


def _columns(path: Path) -> dict[str, list[float]]:
    with path.open(newline="") as f:
        rows = list(csv.reader(f))
    return {name: [float(r[j]) for r in rows[1:]] for j, name in enumerate(rows[0])}


def differences(old: Path, new: Path) -> dict[str, float]:
    """Column → largest relative difference (inf: a column or row count differs)."""
    a, b = _columns(old), _columns(new)
    out: dict[str, float] = {}
    for name in sorted(set(a) | set(b)):
        x, y = a.get(name), b.get(name)
        if x is None or y is None or len(x) != len(y):
            out[name] = math.inf
            continue
        worst = 0.0
        for u, v in zip(x, y, strict=True):
            if u == v or (math.isnan(u) and math.isnan(v)):
                continue
            worst = max(worst, abs(u - v) / max(abs(u), abs(v), 1e-300))
        if worst:
            out[name] = worst
    return out


#: The controllers stepped alone (:data:`STEPPER`): law, delay, setpoint frame, current lag
#: (s), estimator, flux source, identify, initial ε0 and ω̂, period (s).
CONTROLLERS = [
    (law, *rest)
    for law in ("current-fed", "full-order")
    for rest in (
        (1, "dq", 0.0, "open-loop", "estimated", False, 0.0, 0.0, 1e-3),
        (0, "dq", 0.0, "open-loop", "estimated", False, 0.0, 0.0, 1e-3),
        (1, "ab", 0.0, "drift-free", "estimated", False, 0.7, 3.0, 1e-3),
        (1, "dq", 1 / 2000, "rs-adaptive", "estimated", False, -2.9, 0.0, 1e-3),
        (1, "dq", 0.0, "open-loop", "true", False, 3.0, 1.0, 1e-3),
        (1, "dq", 0.0, "drift-free", "estimated", True, 0.0, 0.0, 1e-3),
        (2, "dq", 0.0, "open-loop", "estimated", False, 1.0, 0.0, 1e-3),
        (1, "dq", 0.0, "open-loop", "estimated", False, 0.0, 0.0, 2.5e-4),
    )
]

#: Run in each tree: the samples of the paper scenario's simulation (this tree's own,
#: compared with the signals above), then every command of each controller of CONTROLLERS,
#: a missed cycle every 37th and a withheld command every 53rd, hashed.
STEPPER = """
import hashlib, json, sys
from dbc.modes import SetpointFrame
from dbc.motor import MotorParams
from dbc.timing import Sampling
from gateway.control.controller import ControllerConfig, Sample
from gateway.control.sampled import make_controller
from gateway.reference import paper_profile
from gateway.session import run
from gateway.spec import RunSpec

prof = paper_profile()
samples = {}
for law, drive in (("current-fed", "ideal"), ("full-order", "voltage")):
    sig = run(RunSpec(law=law, drive_mode=drive, identify=False), prof,
              MotorParams.paper()).sig
    samples[law] = [Sample(complex(sig["i_sa"][k], sig["i_sb"][k]),
                           complex(sig["u_sa"][k], sig["u_sb"][k]),
                           complex(sig["psi_r_mod"][k], 0.0)) for k in range(len(sig["t"]))]
out = {}
for case in json.loads(sys.argv[1]):
    law, delay, frame, lag, est, flux, ident, eps0, w0, period = case
    sampling = Sampling(period, min(delay, 1), frame)
    if delay > 1:  # beyond the command line's choices: set on the frozen object
        object.__setattr__(sampling, "delay", delay)
    cfg = ControllerConfig(law=law, flux=flux, estimator=est, sampling=sampling,
                           discretisation="exact", current_lag=lag, identify=ident)
    ctl = make_controller(MotorParams.paper(), cfg, prof.at, eps_0=eps0, w_hat=w0)
    h = hashlib.sha256(type(ctl).__name__.encode())
    for k, s in enumerate(samples[law]):
        if k % 37 == 36:
            ctl.coast()
            h.update(repr((ctl.w_hat, ctl.eps_0)).encode())
            continue
        h.update(repr((ctl.step(prof.at(k * period), s), ctl.w_hat, ctl.eps_0)).encode())
        if k % 53 == 52:
            ctl.withhold()
    out[json.dumps(case)] = h.hexdigest()
print(json.dumps(out))
"""


def controller_hashes(tree: Path) -> dict[str, str]:
    """Each controller of :data:`CONTROLLERS`'s hash in ``tree``."""
    env = {**os.environ, "PYTHONPATH": str(tree)}
    done = subprocess.run([sys.executable, "-c", STEPPER, json.dumps(CONTROLLERS)], env=env,
                          cwd=tree, capture_output=True, text=True)
    if done.returncode:
        raise RuntimeError(f"stepping the controllers in {tree} failed:\n"
                           f"{done.stderr[-2000:]}")
    return json.loads(done.stdout.strip().splitlines()[-1])


def _summary(path: Path) -> dict:
    s = json.loads(path.read_text())
    s.pop("wall_time_s", None)
    return s


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("old", type=Path)
    ap.add_argument("new", type=Path, nargs="?", default=ROOT)
    ap.add_argument("--runs", type=Path, default=Path("/tmp/same-signals"))
    ap.add_argument("--only", action="append", help="a configuration's name (repeatable)")
    ap.add_argument("--no-controllers", action="store_true",
                    help="skip the controllers stepped alone")
    args = ap.parse_args(argv)
    names = args.only or list(CONFIGS)
    all_equal = True
    for name in names:
        words = CONFIGS[name]
        old_out = args.runs / "old" / name
        new_out = args.runs / "new" / name
        if not (old_out / "signals.csv").is_file():
            simulate(args.old.resolve(), words, old_out)
        simulate(args.new.resolve(), words, new_out)
        same_csv = ((old_out / "signals.csv").read_bytes()
                    == (new_out / "signals.csv").read_bytes())
        same_summary = _summary(old_out / "summary.json") == _summary(new_out / "summary.json")
        if same_csv and same_summary:
            verdict = "equal bit for bit (signals.csv, summary.json)"
        else:
            all_equal = False
            diff = differences(old_out / "signals.csv", new_out / "signals.csv")
            worst = max(diff.values(), default=0.0)
            verdict = (f"DIFFERS: max relative {worst:.3g} in "
                       f"{', '.join(f'{k} {v:.2g}' for k, v in diff.items())}"
                       f"{'' if same_summary else '; summary.json differs'}")
        print(f"{name:20s} {' '.join(words) or '(paper profile)':60s} {verdict}", flush=True)
    if not args.no_controllers:
        old, new = controller_hashes(args.old.resolve()), controller_hashes(args.new.resolve())
        for case in CONTROLLERS:
            key = json.dumps(case)
            equal = old.get(key) == new.get(key)
            all_equal &= equal
            law, delay, frame, lag, est, flux, ident, eps0, w0, period = case
            label = (f"{law}, delay {delay}, {frame}, lag {lag:g} s, {est}, {flux} flux"
                     f"{', identify' if ident else ''}, eps_0 {eps0:g}, w_hat {w0:g}, "
                     f"T {period:g} s")
            print(f"controller  {label:82s} "
                  f"{'every command equal bit for bit' if equal else 'DIFFERS'}", flush=True)
    return 0 if all_equal else 1


if __name__ == "__main__":
    sys.exit(main())
