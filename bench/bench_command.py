"""The command a user waits for: `hil-gateway simulate` of the paper scenario, end to end.

Run: .venv/bin/python bench/bench_command.py [--repeats 7] [--baseline DIR] [--sim]

Wall seconds from starting the command to its exit, in a subprocess of this tree's code
(``PYTHONPATH`` = the repository), warm: bytecode cached (``PYTHONDONTWRITEBYTECODE`` is
dropped from the environment) and one run of each command first, not counted. Median of
``--repeats`` runs, the commands interleaved within each repeat: `simulate` with its figures
(the default), `simulate --no-figures`, and `simulate --help` (start-up and imports); with
``--sim`` also `sim --profile profiles/paper.toml` (what scripts/demo runs after its
bootstrap) and `scripts/demo` itself (this tree only: it runs the tree's own bootstrap and
``.venv``; target ≤ 2 s warm). Beside each: the CPU seconds of the command and the processes
it waited for (its figure worker), and the baseline — ``--baseline DIR``: the same commands
from another tree (the code before: ``git archive <commit> | tar -x -C DIR``), interleaved
with this one; without it, the figure recorded before (BENCHMARKS.md). Target: `simulate`
with its figures in ≤ 1 s. The machine's load decides much of a wall figure: the CPU figure
says what the command needed.

A run that fails (exit status, no summary, a stop before the profile's end, a file missing)
is a failed measurement: ``FAILED: <reason>`` in place of its figure (bench/_common.py).
``--json [FILE]`` keys: ``python``, ``repeats``, per command ``<command>_s`` (median wall)
and ``<command>_cpu_s``, with a baseline ``baseline_<command>_s`` and
``<command>_vs_baseline`` (wall ratio), without one ``recorded_<command>_s`` where a figure
was recorded; commands ``simulate``, ``simulate_no_figures``, ``help``, ``sim``, ``demo``;
``target_s``, ``target_met`` (null when `simulate` failed), with ``--sim``
``demo_target_s`` and ``demo_target_met``, ``failed``.
"""

from __future__ import annotations

import argparse
import statistics
import sys
import tempfile
from pathlib import Path

from _common import (
    Figures,
    RunError,
    add_json_option,
    read_summary,
    require_completed,
    run_command,
    warm_env,
)

ROOT = Path(__file__).resolve().parents[1]
TARGET_S = 1.0
#: scripts/demo, warm (its bootstrap finds the tree's .venv up to date).
DEMO_TARGET_S = 2.0
#: Recorded before the figure worker and the lighter start-up (BENCHMARKS.md, "The command
#: a user waits for": the tree before, median s, 2026-11-26).
RECORDED_S = {"simulate": 2.16, "help": 0.24, "sim": 2.82}
FIGURES = ("fig1_references.png", "fig2_errors.png", "fig3_currents_voltages.png")


#: The commands that a baseline tree from before this benchmark does not have, or that
#: run only this tree (scripts/demo bootstraps the tree's own .venv).
NEW_COMMANDS = frozenset({"simulate_no_figures", "demo"})
#: The first word of a command run as a script of the tree instead of ``python -m gateway``.
DEMO = "scripts/demo"



def commands(sim: bool) -> dict[str, tuple[list[str], tuple[str, ...]]]:
    """name → (the words after ``python -m gateway``, the files its run must write)."""
    out = {
        "simulate": (["simulate"], ("signals.csv", "summary.json", *FIGURES)),
        "simulate_no_figures": (["simulate", "--no-figures"], ("signals.csv", "summary.json")),
        "help": (["simulate", "--help"], ()),
    }
    if sim:
        out["sim"] = (["sim", "--profile", str(ROOT / "profiles" / "paper.toml")],
                      ("signals.csv", "summary.json", *FIGURES))
        out["demo"] = ([DEMO], ("signals.csv", "summary.json", *FIGURES))
    return out


def run_once(tree: Path, words: list[str], files: tuple[str, ...], out: Path
             ) -> tuple[float, float]:
    """(wall s, CPU s of the command and what it waited for); RunError when it failed."""
    cmd = ([str(tree / DEMO), *words[1:]] if words[0] == DEMO
           else [sys.executable, "-m", "gateway", *words])
    if words[-1] != "--help":
        cmd += ["--out", str(out), "--force"]
    wall, cpu = run_command(cmd, tree, warm_env(PYTHONPATH=str(tree)), timeout=300)
    if files:
        summary = read_summary(out)
        require_completed(summary, out, files)
    return wall, cpu


def measure(trees: dict[str, Path], cmds: dict, repeats: int, work: Path
            ) -> dict[tuple[str, str], tuple[list[float], list[float]] | str]:
    """(tree, command) → (walls, CPUs) of ``repeats`` runs after one not counted, or the
    reason it failed; commands and trees interleaved."""
    results: dict = {}
    for r in range(repeats + 1):
        for name, (words, files) in cmds.items():
            for label, tree in trees.items():
                key = (label, name)
                if isinstance(results.get(key), str) or (label != "this"
                                                         and name in NEW_COMMANDS):
                    continue
                try:
                    wall, cpu = run_once(tree, words, files, work / f"{label}-{name}")
                except RunError as exc:
                    results[key] = str(exc)
                    continue
                if r:  # the first run of each only warms the caches
                    walls, cpus = results.setdefault(key, ([], []))
                    walls.append(wall)
                    cpus.append(cpu)
    return results


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--repeats", type=int, default=7, help="timed runs of each (default 7)")
    ap.add_argument("--baseline", type=Path, metavar="DIR",
                    help="another tree of the code (e.g. the commit before) to run beside")
    ap.add_argument("--sim", action="store_true",
                    help="also `sim --profile profiles/paper.toml` and scripts/demo itself "
                         "(warm, target 2 s)")
    add_json_option(ap)
    args = ap.parse_args(argv)
    trees = {"this": ROOT}
    if args.baseline is not None:
        trees["baseline"] = args.baseline.resolve()
    cmds = commands(args.sim)
    python = sys.version.split()[0]
    fig = Figures(python=python, repeats=args.repeats, target_s=TARGET_S)
    print(f"Python {python}; wall s from start to exit, median of {args.repeats} warm runs "
          "(CPU s of the command and its workers)")
    with tempfile.TemporaryDirectory(prefix="bench-command-") as tmp:
        results = measure(trees, cmds, args.repeats, Path(tmp))
    for name in cmds:
        got = results.get(("this", name))
        if isinstance(got, str):
            fig.fail([f"{name}_s", f"{name}_cpu_s"], got)
        elif got is not None:
            fig.put(f"{name}_s", statistics.median(got[0]))
            fig.put(f"{name}_cpu_s", statistics.median(got[1]))
        line = f"{name:20s} {fig.show(f'{name}_s', '{:6.2f} s')}"
        if fig.ok(f"{name}_s"):
            line += f" (CPU {fig.values[f'{name}_cpu_s']:.2f} s)"
        if "baseline" in trees and name in NEW_COMMANDS:
            line += " | (no such command in the baseline)"
        elif "baseline" in trees:
            base = results.get(("baseline", name))
            if isinstance(base, str):
                fig.fail(f"baseline_{name}_s", base)
            elif base is not None:
                fig.put(f"baseline_{name}_s", statistics.median(base[0]))
                if fig.ok(f"{name}_s"):
                    fig.put(f"{name}_vs_baseline",
                            fig.values[f"{name}_s"] / fig.values[f"baseline_{name}_s"])
            line += f" | baseline {fig.show(f'baseline_{name}_s', '{:6.2f} s')}"
            if f"{name}_vs_baseline" in fig.values:
                line += f", ratio {fig.values[f'{name}_vs_baseline']:.2f}"
        elif name in RECORDED_S:
            fig.put(f"recorded_{name}_s", RECORDED_S[name])
            line += f" | recorded before {RECORDED_S[name]:g} s"
        print(line)
    ok = fig.ok("simulate_s") and fig.values.get("simulate_s") is not None
    met = ok and fig.values["simulate_s"] <= TARGET_S
    fig.put("target_met", met if ok else None)
    print(f"simulate with its figures: {'meets' if met else 'MISSES'} the {TARGET_S:g} s "
          "target" if ok else "simulate: not measured")
    demo_met = True
    if "demo" in cmds:
        fig.put("demo_target_s", DEMO_TARGET_S)
        if fig.ok("demo_s") and fig.values.get("demo_s") is not None:
            demo_met = fig.values["demo_s"] <= DEMO_TARGET_S
            fig.put("demo_target_met", demo_met)
            print(f"scripts/demo, warm: {'meets' if demo_met else 'MISSES'} the "
                  f"{DEMO_TARGET_S:g} s target")
        else:
            fig.put("demo_target_met", None)
    fig.report_failures()
    fig.emit(args.json)
    return fig.exit_status(bool(met) and demo_met)


if __name__ == "__main__":
    sys.exit(main())
