"""The robustness table of the sensorless loop against plants that differ from the
controller's model (plant scenarios, ``plant/scenarios/``): the campaign
``campaigns/robustness.toml`` (`hil-gateway campaign`, a local Dask cluster by default),
printed as one table per block (sampled 1 ms, one period of SYNC delay, (d, q) setpoints,
INT16 PDOs).

    .venv/bin/python bench/robustness.py                  # the tables on stdout
    .venv/bin/python bench/robustness.py --markdown       # Markdown for README/BENCHMARKS.md
    .venv/bin/python bench/robustness.py --only paper     # one block: paper, zero-speed,
                                                          #   slow-reversal, exact,
                                                          #   full-order, load, identify
    .venv/bin/python bench/robustness.py --png runs/robustness.png   # and the figure

Columns are speed errors ω − ω* in rad/s: RMS over the run, max |·|, and the final value
(last sample). "runaway" marks max |ω − ω*| > 50 rad/s, "(diverged)" a run the divergence
guard stopped (the figures are up to there). ``--png FILE`` draws |ω − ω*| over
time per case (it keeps every run's directory for its signals: slower). Nothing here is
fixed in advance: every figure is simulated when the script runs (the campaign's table is
in ``--out DIR``, default a new runs/bench-robustness-<time>; its summary goes to stderr).

A run that ends in a numerical error or diverges is a result. A point that fails
otherwise (an error, a time limit, a dead worker) is a failed measurement: ``FAILED:
<reason>`` in its cell, the other cases go on, exit status 1 (bench/_common.py).
``--json [FILE]`` keys: ``"<block>: <row> / <controller>"`` for every case, each
``{"rms", "max", "final", "runaway"}`` (speed error, rad/s; non-finite as "inf"/"nan") or
null; ``runs``, ``seconds``, ``png`` (the figure written, or null); ``failed``.
"""

from __future__ import annotations

import argparse
import contextlib
import math
import sys
import time
import tomllib
from dataclasses import dataclass
from datetime import datetime
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from _common import Figures, add_json_option, failed_text  # noqa: E402

from gateway.campaign import tomltext  # noqa: E402
from gateway.campaign.model import load_campaign  # noqa: E402
from gateway.campaign.points import every_point  # noqa: E402
from gateway.cli import main as hil_gateway  # noqa: E402
from gateway.report import read_csv  # noqa: E402
from gateway.spec import RunSpec  # noqa: E402

CAMPAIGN = ROOT / "campaigns" / "robustness.toml"
RUNAWAY = 50.0  # rad/s

@dataclass
class Case:
    block: str
    row: str
    controller: str
    rms: float = math.nan
    max: float = math.nan
    final: float = math.nan
    t: np.ndarray | None = None
    e: np.ndarray | None = None
    failed: str = ""  # why the point failed (not a divergence: an error), "" if it did not
    run_dir: str | None = None
    stopped: str = ""  # why the run stopped before the profile's end ("diverged"), or ""

    @property
    def runaway(self) -> bool:
        return not self.failed and not self.max <= RUNAWAY

    @property
    def scenario(self) -> str:
        return self.row.rsplit(", ", 1)[-1]

    @property
    def name(self) -> str:
        """The case's figure name: block, row, controller."""
        return f"{self.block}: {self.row} / {self.controller}"


def sim_config(drive: str | None = None, **kw) -> RunSpec:
    """RunSpec of a robustness case as bench/guard.py replays it: sampled 1 ms, delay 1,
    (d, q) setpoints, the Euler design unless the case says otherwise (the campaign's
    [base]). Not imported from tests/: a third-party package (eds-utils) installs a
    top-level ``tests`` package that shadows the project's."""
    kw.setdefault("discretisation", "euler")
    kw.setdefault("identify", False)  # as the campaign's [base]
    return RunSpec.from_words(1e-3, 1, "dq", drive, **kw)


def labels(values: dict) -> tuple[str, str, str]:
    """A case's block, table row and column, from its point's axis values: the block's
    label ("exact/paper": block "exact", rows prefixed "paper"), the plant and the drive
    in the row, the controller's settings in the column (the load block: the estimator in
    the row, the load in the column)."""
    block, _, prefix = str(values["block"]).partition("/")
    row = [prefix] if prefix else []
    col = []
    for key, v in values.items():
        if key == "block":
            continue
        if key == "plant":
            row.append(str(v))
        elif key == "drive-mode":
            row.append(f"{v} drive")
        elif key == "variant" and block == "load":
            row.insert(0, str(v))
        elif key == "load":
            col.append(f"T_L {v}")
        elif key == "identify":
            col.append("+ identify" if v else "")
        else:
            col.append(str(v))
    if block == "load" and "variant" not in values:
        row.insert(0, "rs-adaptive, ideal drive")
    return block, ", ".join(row), " ".join(c for c in col if c)


def only(blocks: list[str], out: Path, campaign: Path = CAMPAIGN) -> Path:
    """``campaign`` with only the grids of ``blocks`` (a block's label, or its part before
    "/"), written beside ``out``."""
    data = tomllib.loads(campaign.read_text(encoding="utf-8"))
    data["grid"] = [g for g in data["grid"]
                    if g["block"][0]["label"].partition("/")[0] in blocks
                    or g["block"][0]["label"] in blocks]
    return campaign_beside(data, out, "campaign")


def campaign_beside(data: dict, out: Path, tag: str) -> Path:
    """The campaign ``data`` (a parsed campaign file, changed) written beside ``out`` as
    ``<out>-<tag>.toml``, for the campaign command to run."""
    path = out.with_name(f"{out.name}-{tag}.toml")
    out.parent.mkdir(parents=True, exist_ok=True)
    path.write_text(tomltext.dumps(data), encoding="utf-8")
    return path


def run_campaign(args: argparse.Namespace, out: Path, campaign: Path = CAMPAIGN,
                 keep_runs: bool = False) -> tuple[Path, int]:
    """``campaign`` (its summary to stderr) where ``args`` say (``--only``, ``--in-process``,
    ``--scheduler``, ``--workers``), its runs' directories kept with ``keep_runs``; the
    campaign file run and its exit status."""
    path = only(args.only, out, campaign) if args.only else campaign
    words = ["campaign", str(path), "--out", str(out), "--worst", "0"]
    if args.in_process:
        words.append("--in-process")
    elif args.scheduler:
        words += ["--scheduler", args.scheduler]
    elif args.workers:
        words += ["--workers", str(args.workers)]
    if keep_runs:
        words.append("--keep-runs")
    with contextlib.redirect_stdout(sys.stderr):
        status = hil_gateway(words)
    return path, status


def cases_of(path: Path, out: Path, with_signals: bool) -> dict[str, list[Case]]:
    """Every case of the campaign, by block, with its row of the table (a case two blocks
    share is one point, in both)."""
    import pyarrow.parquet as pq

    rows = {r["hash"]: r for r in pq.read_table(out / "results.parquet").to_pylist()}
    blocks: dict[str, list[Case]] = {}
    for point in every_point(load_campaign(path), ROOT):
        block, row, col = labels(dict(point.values))
        case = Case(block, row, col)
        r = rows.get(point.hash)
        if r is None or r["status"] not in ("ok", "stopped") or r["speed_rms"] is None:
            case.failed = "not run" if r is None else f"{r['status']}: {r['stop_reason']}"
        else:
            case.rms, case.max, case.final = r["speed_rms"], r["speed_max"], r["speed_final"]
            case.run_dir = r["run_dir"]
            if r["stop"] != "END_OF_PROFILE":
                case.stopped = str(r["stop"]).lower().replace("_", " ")
            if with_signals and case.run_dir:
                sig = read_csv(Path(case.run_dir) / "signals.csv")
                case.t, case.e = sig["t"], sig["w_m"] - sig["w_ref"]
        blocks.setdefault(block, []).append(case)
    return blocks


def fmt(x: float) -> str:
    if not math.isfinite(x):
        return "diverged"
    return f"{x:.3g}"


def table(cases: list[Case], markdown: bool) -> str:
    """One row per scenario, one column group per controller."""
    ctls = list(dict.fromkeys(c.controller for c in cases))
    scns = list(dict.fromkeys(c.row for c in cases))
    by = {(c.row, c.controller): c for c in cases}
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
            row.append(cell + (" runaway" if c.runaway else "")
                       + (f" ({c.stopped})" if c.stopped else ""))
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
                        label=f"{c.row}, {c.controller}")
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
    ap.add_argument("--png", metavar="FILE",
                    help="also draw |ω − ω*| per case into FILE (keeps the runs: slower)")
    ap.add_argument("--out", metavar="DIR",
                    help="the campaign's directory (default runs/bench-robustness-<time>)")
    where = ap.add_mutually_exclusive_group()
    where.add_argument("--workers", type=int, help="local Dask workers (default: all cores)")
    where.add_argument("--scheduler", metavar="tcp://HOST:PORT", help="a Dask scheduler")
    where.add_argument("--in-process", action="store_true", help="no Dask: one after another")
    add_json_option(ap)
    args = ap.parse_args(argv)
    out = Path(args.out) if args.out else ROOT / "runs" / (
        f"bench-robustness-{datetime.now():%Y%m%d-%H%M%S}")
    fig = Figures()
    t0 = time.perf_counter()
    path, status = run_campaign(args, out, keep_runs=bool(args.png))
    if not (out / "results.parquet").exists():
        print(f"the campaign did not run (exit status {status}); see above", file=sys.stderr)
        return 1
    all_cases = cases_of(path, out, bool(args.png))
    for b, cases in all_cases.items():
        for c in cases:
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
          f"delay 1, (d, q) setpoints; 'runaway': max > {RUNAWAY:g} rad/s; table: "
          f"{out / 'results.parquet'}"
          f"{f'; {len(fig.failed)} FAILED' if fig.failed else ''})")
    fig.put("png", None)
    if args.png:
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
