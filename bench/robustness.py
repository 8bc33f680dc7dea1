"""The robustness table of the sensorless loop against plants that differ from the
controller's model (plant scenarios, ``plant/scenarios/``), with `hil-gateway simulate`'s
Python API (sampled 1 ms, one period of SYNC delay, (d, q) setpoints, INT16 PDOs).

    .venv/bin/python bench/robustness.py                  # the table on stdout, PNG in runs/
    .venv/bin/python bench/robustness.py --markdown       # Markdown for README/BENCHMARKS.md
    .venv/bin/python bench/robustness.py --only paper     # one block: paper, zero-speed,
                                                          #   slow-reversal, exact,
                                                          #   full-order, load, identify

Columns are speed errors ω − ω* in rad/s: RMS over the run, max |·|, and the final value
(last sample). "runaway" marks max |ω − ω*| > 50 rad/s. The PNG (``--png``, default
``runs/robustness.png``) shows |ω − ω*| over time per case. Nothing here is fixed in
advance: every figure is simulated when the script runs (a few minutes on one core).

A run that ends in a numerical error (a runaway) is "diverged", a result. A run that fails
otherwise (another exception from the simulation) is a failed measurement: ``FAILED:
<reason>`` in its cell, the other cases go on, exit status 1 (bench/_common.py).
``--json [FILE]`` keys: ``"<block>: <row> / <controller>"`` for every case, each
``{"rms", "max", "final", "runaway"}`` (speed error, rad/s; non-finite as "inf"/"nan") or
null; ``runs``, ``seconds``, ``png`` (the figure written, or null); ``failed``.
"""

from __future__ import annotations

import argparse
import math
import sys
import time
from dataclasses import dataclass
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from _common import Figures, RunError, add_json_option, failed_text, the_run  # noqa: E402

from dbc.motor import MotorParams  # noqa: E402
from gateway.reference import load_profile, paper_profile  # noqa: E402
from gateway.session import run  # noqa: E402
from gateway.spec import RunSpec  # noqa: E402
from plant.scenario import resolve_scenario  # noqa: E402

RUNAWAY = 50.0  # rad/s

#: (label, RunSpec keywords) of the controller columns
CONTROLLERS = {
    "true flux": {"flux": "true"},
    "open-loop": {"estimator": "open-loop"},
    "drift-free": {"estimator": "drift-free"},
    "rs-adaptive": {"estimator": "rs-adaptive"},
}


@dataclass
class Case:
    block: str
    profile: str
    scenario: str
    controller: str
    kw: dict
    rms: float = math.nan
    max: float = math.nan
    final: float = math.nan
    t: np.ndarray | None = None
    e: np.ndarray | None = None
    row: str = ""  # the table row, default the scenario
    failed: str = ""  # why the run failed (not a divergence: an error), "" if it did not

    @property
    def runaway(self) -> bool:
        return not self.failed and not self.max <= RUNAWAY

    @property
    def name(self) -> str:
        """The case's figure name: block, row, controller."""
        return f"{self.block}: {self.row or self.scenario} / {self.controller}"


def blocks() -> dict[str, list[Case]]:
    """The cases, by block."""
    out: dict[str, list[Case]] = {}
    paper = ["nominal", "continuous-load", "offset10mA", "rs+5", "rs-5", "rs+10", "rs-10",
             "offset10mA-rs+5", "offset10mA-rs+10", "offset10mA-rs-10", "rr+20", "rr-20"]
    out["paper"] = [Case("paper", "paper", s, c, kw) for s in paper
                    for c, kw in CONTROLLERS.items()]
    for prof in ("zero-speed", "slow-reversal"):
        out[prof] = [Case(prof, prof, s, c, kw) for s in ("nominal", "rs+10", "rs-10")
                     for c, kw in CONTROLLERS.items()]
    exact = {"discretisation": "exact"}
    out["exact"] = [Case("exact", prof, s, c, {**exact, **kw}, row=f"{prof}, {s}")
                    for prof, scns in (("paper", ("nominal", "rs+10", "rs-10",
                                                  "offset10mA-rs+10", "offset10mA-rs-10",
                                                  "rr+20", "rr-20")),
                                       ("zero-speed", ("rs+10", "rs-10")),
                                       ("slow-reversal", ("rs+10", "rs-10")))
                    for s in scns
                    for c, kw in CONTROLLERS.items() if c != "open-loop"]
    fo = {"law": "full-order", "drive": "voltage"}
    out["full-order"] = [Case("full-order", "paper", s, c, {**fo, **kw})
                         for s in ("nominal", "rs+5", "rs-5")
                         for c, kw in (("true flux", {"flux": "true"}),
                                       ("open-loop", {}),
                                       ("drift-free", {"estimator": "drift-free"}),
                                       ("rs-adaptive", {"estimator": "rs-adaptive"}))]
    out["load"] = [Case("load", "paper", "continuous-load", f"T_L {load}",
                        {**kw, "load": load, "drive": drive},
                        row=f"{c}, {drive} drive")
                   for drive in ("ideal", "current-loop")
                   for c, kw in (("drift-free", {"estimator": "drift-free"}),
                                 ("rs-adaptive", {"estimator": "rs-adaptive"}))
                   for load in ("known", "observed")]
    # the observed load against plant errors (rs-adaptive estimator, ideal drive)
    out["load"] += [Case("load", "paper", s, f"T_L {load}",
                         {"estimator": "rs-adaptive", "load": load},
                         row=f"rs-adaptive, ideal drive, {s}")
                    for s in ("offset10mA", "noise5mA", "rs+10", "rr+20", "real-drive")
                    for load in ("known", "observed")]
    # the standstill identification of R_s and R_r (--identify, docs/robustness.md §5)
    ident = [("paper", s) for s in ("nominal", "rs+10", "rs-10", "offset10mA-rs+10",
                                     "offset10mA-rs-10", "rr+20", "rr-20", "real-drive")]
    ident += [(p, s) for p in ("zero-speed", "slow-reversal")
              for s in ("rs+10", "rs-10", "rr+20", "rr-20")]
    out["identify"] = [Case("identify", prof, s, f"{est}{' + identify' if on else ''}",
                            {"discretisation": "exact", "estimator": est, "load": "known",
                             "identify": on}, row=f"{prof}, {s}")
                       for prof, s in ident
                       for est in ("drift-free", "rs-adaptive") for on in (False, True)]
    return out


def sim_config(drive: str | None = None, **kw) -> RunSpec:
    """RunSpec of a case: sampled 1 ms, delay 1, (d, q) setpoints, the Euler design unless
    the case says otherwise (the load observer exists in it only; block "exact" has the
    sampled-data design). Not imported from tests/: a third-party package (eds-utils)
    installs a top-level ``tests`` package that shadows the project's."""
    kw.setdefault("discretisation", "euler")
    return RunSpec.from_words(1e-3, 1, "dq", drive, **kw)


def simulate(case: Case) -> Case:
    prof = paper_profile() if case.profile == "paper" else load_profile(
        ROOT / "gateway" / "profiles" / f"{case.profile}.toml")
    cfg = sim_config(plant=resolve_scenario(case.scenario), **case.kw)
    try:
        with the_run():
            try:
                rec = run(cfg, prof, MotorParams()).sig
            except (ValueError, OverflowError) as exc:  # a runaway may end in a numerical error
                print(f"  {case.block}/{case.scenario}/{case.controller}: {exc}",
                      file=sys.stderr)
                return case
    except RunError as exc:  # any other error: the run failed, not the controller
        case.failed = str(exc)
        print(f"  {case.block}/{case.scenario}/{case.controller}: {failed_text(case.failed)}",
              file=sys.stderr)
        return case
    e = rec["w_m"] - rec["w_ref"]
    finite = np.isfinite(e)
    case.t, case.e = rec["t"], e
    case.rms = float(np.sqrt(np.mean(e[finite] ** 2))) if finite.all() else math.inf
    case.max = float(np.max(np.abs(e))) if finite.all() else math.inf
    case.final = float(e[-1])
    return case


def fmt(x: float) -> str:
    if not math.isfinite(x):
        return "diverged"
    return f"{x:.3g}"


def table(cases: list[Case], markdown: bool) -> str:
    """One row per scenario, one column group per controller."""
    ctls = list(dict.fromkeys(c.controller for c in cases))
    scns = list(dict.fromkeys(c.row or c.scenario for c in cases))
    by = {(c.row or c.scenario, c.controller): c for c in cases}
    head = ["plant"] + [f"{k}: RMS / max / final" for k in ctls]
    rows = []
    for s in scns:
        row = [s]
        for k in ctls:
            c = by.get((s, k))
            if c is None:
                row.append("")
                continue
            if c.failed:
                row.append(failed_text(c.failed))
                continue
            cell = f"{fmt(c.rms)} / {fmt(c.max)} / {fmt(c.final)}"
            row.append(cell + (" runaway" if c.runaway else ""))
        rows.append(row)
    if markdown:
        lines = ["| " + " | ".join(head) + " |", "|" + "---|" * len(head)]
        lines += ["| " + " | ".join(r) + " |" for r in rows]
        return "\n".join(lines)
    widths = [max(len(r[i]) for r in [head, *rows]) for i in range(len(head))]
    return "\n".join("  ".join(x.ljust(w) for x, w in zip(r, widths, strict=True))
                     for r in [head, *rows])


TITLES = {
    "paper": "paper scenario, current-fed law, ideal drive",
    "zero-speed": "zero speed under ±5.8 N·m, then zero stator frequency "
                  "(profiles/zero-speed.toml)",
    "slow-reversal": "slow reversal ±30 rad/s at 2 N·m (profiles/slow-reversal.toml)",
    "exact": "the sampled-data design (--discretisation exact, the CLI's default), "
             "current-fed law, ideal drive",
    "full-order": "paper scenario, full-order law, voltage drive",
    "load": "paper scenario, load applied within the period, known or observed",
    "identify": "R_s and R_r identified at standstill (--identify), sampled-data design, "
                "load known",
}


PAPER_PLOT = ("rs+10", "rs-10", "offset10mA-rs+10", "offset10mA-rs-10", "rr+20", "rr-20")


def plot(all_cases: dict[str, list[Case]], path: Path) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    names = [b for b in all_cases if any(c.e is not None for c in all_cases[b])]
    fig, axes = plt.subplots(len(names), 1, figsize=(11, 3.2 * len(names)),
                             layout="constrained", squeeze=False)
    for ax, b in zip(axes[:, 0], names, strict=True):
        k = 0
        for c in all_cases[b]:
            if c.e is None or c.controller in ("true flux", "open-loop"):
                continue  # before (drift-free, dotted) and after (solid)
            if b == "paper" and c.scenario not in PAPER_PLOT:
                continue
            if b == "identify" and not c.controller.startswith("drift-free"):
                continue  # before and after the identification, one estimator
            after = ("identify" in c.controller if b == "identify" else
                     "rs-adaptive" in c.controller or "observed" in c.controller)
            ax.semilogy(c.t, np.abs(c.e) + 1e-4, lw=0.8 if after else 0.6,
                        ls="-" if after else ":", color=f"C{k // 2 % 10}",
                        label=f"{c.row or c.scenario}, {c.controller}")
            k += 1
        ax.set_title(TITLES[b], fontsize="medium")
        ax.set_ylabel("|ω − ω*| [rad/s]")
        ax.set_ylim(1e-3, 1e3)
        ax.grid(True, alpha=0.3)
        ax.legend(fontsize="x-small", ncol=3, loc="upper left")
    axes[-1, 0].set_xlabel("time [s]")
    path.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(path, dpi=100)
    plt.close(fig)


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--markdown", action="store_true", help="Markdown tables")
    ap.add_argument("--only", action="append", choices=list(TITLES),
                    help="run only this block (repeatable)")
    ap.add_argument("--png", default=str(ROOT / "runs" / "robustness.png"),
                    help="figure of |ω − ω*| per case (default runs/robustness.png)")
    add_json_option(ap)
    args = ap.parse_args(argv)
    all_cases = {b: cs for b, cs in blocks().items() if not args.only or b in args.only}
    fig = Figures()
    t0 = time.perf_counter()
    for b, cases in all_cases.items():
        for c in cases:
            simulate(c)
            if c.failed:
                fig.fail(c.name, c.failed)
            else:
                fig.put(c.name, {"rms": c.rms, "max": c.max, "final": c.final,
                                 "runaway": c.runaway})
        title = TITLES[b]
        print(f"\n**{title}**\n" if args.markdown else f"\n{title}")
        print(table(cases, args.markdown), flush=True)
    runs, seconds = sum(len(c) for c in all_cases.values()), time.perf_counter() - t0
    fig.put("runs", runs)
    fig.put("seconds", seconds)
    print(f"\n({runs} runs, {seconds:.0f} s; speed errors ω − ω* in rad/s; sampled 1 ms, "
          f"delay 1, (d, q) setpoints; 'runaway': max > {RUNAWAY:g} rad/s"
          f"{f'; {len(fig.failed)} FAILED' if fig.failed else ''})")
    fig.put("png", None)
    try:
        plot(all_cases, Path(args.png))
        print(f"wrote {args.png}")
        fig.put("png", args.png)
    except ImportError:
        print("(install matplotlib for the figure)")
    except OSError as exc:
        print(f"cannot write the figure to {args.png}: {exc.strerror or exc}")
    fig.report_failures()
    fig.emit(args.json)
    return fig.exit_status()


if __name__ == "__main__":
    sys.exit(main())
