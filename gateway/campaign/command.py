"""`hil-gateway campaign CAMPAIGN.toml` and `hil-gateway campaign show TABLE`."""

from __future__ import annotations

import argparse
import math
import sys
import time
from collections.abc import Sequence
from pathlib import Path
from typing import Any

from gateway.campaign import figures, summary
from gateway.campaign.model import Campaign, load_campaign
from gateway.campaign.points import PointConfig, plan
from gateway.campaign.progress import CampaignProgress, clock
from gateway.campaign.runpoint import Limits
from gateway.errors import UserError
from gateway.scope import live_scope
from gateway.units import parse_duration

PROG = "hil-gateway"
SHOW = "campaign-show"  # `campaign show` as parsed (see :func:`rewrite`)

DESCRIPTION = """\
Run a campaign: the base run of a campaign file (the options of `simulate`, or of `sim`
against the emulator) at every point of its axes (a grid of values, random draws with a
seed, or both crossed), each point one run through the same entry as the command line.
The results go into one table in DIR (results.parquet, a row per point: the point's
values, a hash of its configuration, the metrics, the stop reason, the exit status, the
wall time); a second run of the same command runs only the points the table does not have
(after Ctrl-C, a crash or a lost worker: nothing is lost and nothing runs twice). At the
end: how many points passed each criterion of [pass], the worst points with the command
that reproduces each alone, and figures in DIR/figures. `hil-gateway campaign show TABLE`
redraws them from the table.

The points run on Dask: by default a local cluster of one worker process per core (one
thread each) whose dashboard address is printed; --scheduler runs them on a cluster you
started (dask scheduler, dask worker ADDRESS --nthreads 1); --in-process runs them here,
one after the other (for debugging). Shipped campaigns: campaigns/*.toml; the file format
is below and in the README.

Exit status: 0 when every point ran to its end and passed every criterion, 1 when some did
not, 130 when interrupted (run the command again to go on), 2 for bad input."""

EPILOG = """\
campaign file:
  [campaign]  name = "rs-sweep", command = "simulate" (or "sim")
  [base]      the command's options without dashes: profile = "profiles/paper.toml",
              period = "1ms", estimator = "drift-free", identify = true, ...
  [grid]      axes, every combination: period = ["500us", "1ms"], "plant.motor.Rs" =
              [0.9, 1.1], variant = [{label = "a", flux = "true"}, ...]; several [[grid]]
              tables are run one after the other
  [random]    n = 1000, seed = 1, "plant.motor.J" = {dist = "uniform", low = 0.8, high =
              1.2} (uniform, loguniform, normal: mean/std, integers, choice: values)
  [pass]      criteria on the table's metrics: speed_rms = "< 0.05", exit_status = "== 0"
  An axis is an option, a plant scenario key plant.<motor|sensors|inverter|load>.<key>
  (plant/scenario.py; set in the scenario the plant option names, or the nominal one), a
  controller parameter controller.<name>, a bus fault key bus.<key> (set in every
  [[bus.fault]] of the point's scenario; simulate, sampled, or sim), or a table of settings
  per value.

examples:
  hil-gateway campaign campaigns/motor-population.toml          local cluster, all cores
  hil-gateway campaign campaigns/period-delay.toml --workers 1 --csv
  hil-gateway campaign campaigns/robustness.toml --scheduler tcp://127.0.0.1:8786
  hil-gateway campaign show runs/campaign-motor-population
"""


def rewrite(argv: Sequence[str]) -> list[str]:
    """``campaign show ...`` → ``campaign-show ...``: one command word for argparse, which
    cannot have both a file and a sub-action in one place."""
    out = list(argv)
    for i, word in enumerate(out):
        if word.startswith("-"):
            continue
        if word == "campaign" and i + 1 < len(out) and out[i + 1] == "show":
            out[i:i + 2] = [SHOW]
        break
    return out


def add_parser(sub: Any) -> None:
    p = sub.add_parser("campaign", help="thousands of runs across mismatch, timing and "
                       "settings, on Dask; `campaign show TABLE` redraws the results",
                       description=DESCRIPTION, epilog=EPILOG,
                       formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("campaign", metavar="CAMPAIGN.toml", help="the campaign file")
    p.add_argument("--out", metavar="DIR",
                   help="the campaign's directory: its table, figures and kept runs "
                        "(default runs/campaign-<name>); a second run goes on where the "
                        "first stopped")
    where = p.add_mutually_exclusive_group()
    where.add_argument("--scheduler", metavar="tcp://HOST:PORT",
                       help="run on this Dask scheduler's workers (started with dask "
                            "scheduler and dask worker ADDRESS --nthreads 1); the files the "
                            "campaign names must be at the same paths for them")
    where.add_argument("--workers", type=int, metavar="N",
                       help="the local cluster's worker processes (default: one per core)")
    where.add_argument("--in-process", action="store_true",
                       help="run the points here, one after the other, without Dask "
                            "(for debugging)")
    p.add_argument("--dashboard", metavar="[HOST:]PORT", default="127.0.0.1:0",
                   help="the local cluster's dashboard (default 127.0.0.1, any free port; "
                        "the address is printed)")
    p.add_argument("--timeout", default="300s", metavar="DURATION",
                   help="time limit of one point (default 300s): it is then stopped, and "
                        "recorded as 'timeout'")
    p.add_argument("--keep-runs", action="store_true",
                   help="keep every point's run directory (DIR/runs/<point>-<hash>/); "
                        "by default only those of points that did not run to their end")
    p.add_argument("--retry-failed", action="store_true",
                   help="run again the points recorded with an error, a timeout or a dead "
                        "worker (those that ran keep their rows)")
    p.add_argument("--csv", action="store_true", help="also write DIR/results.csv")
    p.add_argument("--scope", metavar="[HOST:]PORT",
                   help="serve the running table live at http://HOST:PORT/ (the live scope's "
                        "page: each point's numeric results against its number, as points "
                        "come back; HOST 127.0.0.1 by default, PORT 0: any free port)")
    _add_view_options(p)
    p.set_defaults(func=cmd_campaign)

    s = sub.add_parser(SHOW, prog=f"{PROG} campaign show",
                       description="Show a campaign's table again: the statuses, the pass "
                                   "criteria, the worst points with the command that "
                                   "reproduces each, and the figures (redrawn).")
    s.add_argument("table", metavar="TABLE",
                   help="the campaign's directory (its --out DIR) or its results.parquet")
    s.add_argument("--figures", metavar="DIR",
                   help="where the figures go (default TABLE's directory/figures)")
    _add_view_options(s)
    s.set_defaults(func=cmd_show)


def _add_view_options(p: argparse.ArgumentParser) -> None:
    p.add_argument("--metric", metavar="NAME",
                   help="the metric of the figures and the worst points (default: the first "
                        "criterion's, else speed_rms)")
    p.add_argument("--map", metavar="A,B",
                   help="the two axes of the map (default: the first two grid axes)")
    p.add_argument("--worst", type=int, default=summary.WORST, metavar="K",
                   help=f"how many of the worst points to list (default {summary.WORST})")


def _validate(campaign: Campaign, points: Sequence[PointConfig]) -> None:
    """Every input checked before anything runs: each distinct plant scenario parsed, each
    distinct set of options turned into a run (no run started)."""
    from gateway.campaign.options import Command as Cmd
    from gateway.campaign.options import build_parser, parse_args
    from gateway.cli import sim_inputs, simulate_inputs
    from gateway.sim import scenario_from_text

    parser = build_parser()
    plants: dict[tuple[str, str], Any] = {}
    checked: set[tuple[Any, ...]] = set()
    for p in points:
        try:
            plant = None
            if p.plant is not None:
                if p.plant not in plants:
                    plants[p.plant] = scenario_from_text(*p.plant)
                plant = plants[p.plant]
            key = (p.argv, repr(sorted((p.controller_params or {}).items())),
                   p.plant is None)
            if key in checked:
                continue
            checked.add(key)
            args = parse_args(parser, p.command, p.argv)
            params = dict(p.controller_params) if p.controller_params is not None else None
            (simulate_inputs if p.command is Cmd.SIMULATE else sim_inputs)(args, plant, params)
        except UserError as exc:
            values = ", ".join(f"{k}={v}" for k, v in p.values.items())
            raise UserError(f"{campaign.source}, point #{p.index}"
                            f"{f' ({values})' if values else ''}: {exc}") from exc


def _engine(args: argparse.Namespace, campaign: Campaign) -> Any:
    from gateway.campaign.engine import DaskEngine, InProcess

    if args.in_process:
        return InProcess()
    if args.workers is not None and args.workers < 1:
        raise UserError(f"--workers {args.workers}: give at least 1")
    return DaskEngine(campaign.command, args.scheduler, args.workers, args.dashboard)


def _view(args: argparse.Namespace) -> tuple[str | None, list[str] | None]:
    keys = None
    if args.map:
        keys = [k.strip() for k in args.map.split(",")]
        if len(keys) != 2 or not all(keys):
            raise UserError(f"--map {args.map!r}: give two axes, e.g. --map period,delay")
    if args.metric:
        from gateway.campaign.metrics import check_metric

        check_metric(args.metric, "--metric")
    if args.worst < 0:
        raise UserError(f"--worst {args.worst}: give 0 or more")
    return args.metric, keys


def _report(rows: list[dict[str, Any]], meta: dict[str, Any], d: Path, fig_dir: Path,
            args: argparse.Namespace) -> None:
    metric, keys = _view(args)
    metric = summary.primary_metric(meta, metric)
    if keys is not None:
        axes = {a["key"] for a in meta.get("axes", [])}
        for k in keys:
            if k not in axes:
                raise UserError(f"--map: {k!r} is not an axis of the campaign; its axes: "
                                f"{', '.join(sorted(axes))}")
    print(summary.text(rows, meta, metric, d / "repro", args.worst))
    drawn = figures.draw(rows, meta, metric, fig_dir, keys)
    if drawn is None:
        print("(install matplotlib for the figures)")
    elif drawn:
        print(f"figures: {', '.join(str(p) for p in drawn)}")


def cmd_campaign(args: argparse.Namespace) -> int:
    from gateway.campaign import runner

    timeout = parse_duration(args.timeout, "--timeout")
    if not timeout > 0:
        raise UserError(f"--timeout {args.timeout}: give a positive duration, e.g. 300s")
    _view(args)
    campaign = load_campaign(args.campaign)
    points, same = plan(campaign)
    _validate(campaign, points)
    out = Path(args.out or f"runs/campaign-{campaign.name}")
    runner.check_out(out, campaign)
    with runner.lock(out):
        table, done = runner.prepare(out, campaign, args.retry_failed)
        todo = [p for p in points if p.hash not in done]
        before = len(points) - len(todo)
        print(f"{PROG} campaign {campaign.name}: {len(points)} points of `{campaign.command}`"
              + (f" ({same} identical to others, run once)" if same else "")
              + f"; {before} already in {out}, {len(todo)} to run")
        for ax in campaign.axes:
            print(f"  {ax.describe()}")
        interrupted = False
        t0 = time.perf_counter()
        if todo:
            limits = Limits(timeout=timeout, keep_runs=args.keep_runs,
                            runs_dir=str((out / "runs").resolve()))
            engine = _engine(args, campaign)
            print(f"running on {engine.description}"
                  + (f"; dashboard: {engine.dashboard}" if engine.dashboard else ""),
                  flush=True)
            progress = CampaignProgress(campaign.name, len(todo), before)
            try:
                with runner.interrupts(), live_scope(args.scope,
                                                     f"campaign {campaign.name}") as feed:
                    table_view = PointRows(feed)

                    def on_rows(rows: list[dict[str, Any]]) -> None:
                        progress.advance(len(rows), sum(r["status"] != "ok" for r in rows))
                        table_view.add(rows)

                    runner.run(engine, todo, table, limits, on_rows)
                    table_view.finish()
            except KeyboardInterrupt:
                interrupted = True
            finally:
                progress.close()
                engine.close()
        final = table.compact()
        wanted = {p.hash for p in points}
        rows = [r for r in (final.to_pylist() if final is not None else [])
                if r["hash"] in wanted]
        if interrupted:
            print(f"{PROG} campaign: interrupted after {clock(time.perf_counter() - t0)}: "
                  f"{len(rows)} of {len(points)} points are in {out / 'results.parquet'}; run "
                  "the same command again to run the others", file=sys.stderr)
            return 130
        if args.csv and final is not None:
            print(f"wrote {table.write_csv(final)}")
        print(f"{len(rows)} points in {out / 'results.parquet'}")
        _report(rows, table.meta, out, out / "figures", args)
        return 0 if summary.all_passed(rows, table.meta) else 1


class PointRows:
    """The campaign's running table for the live scope (``--scope``): one row per point
    as it comes back, its number as the x axis and its numeric results as signals."""

    def __init__(self, feed: Any) -> None:
        self.feed = feed
        self.columns: tuple[str, ...] = ()
        self._rows: list[tuple[float, ...]] = []

    def add(self, rows: list[dict[str, Any]]) -> None:
        if self.feed is None or not rows:
            return
        if not self.columns:  # the first batch names the columns; the feed starts then
            self.columns = ("t", *(k for k, v in rows[0].items() if _numeric(v)))
            self.feed.attach(self)
        for r in rows:
            values = [r.get(k) for k in self.columns[1:]]
            self._rows.append((float(len(self._rows) + 1),
                               *(float(v) if _numeric(v) else math.nan for v in values)))

    def finish(self) -> None:
        if self.feed is not None:
            self.feed.finish({"run": {"stop": "CAMPAIGN_DONE",
                                      "stop_reason": f"{len(self._rows)} points run"}})


def _numeric(v: Any) -> bool:
    return isinstance(v, int | float) and not isinstance(v, bool)


def cmd_show(args: argparse.Namespace) -> int:
    from gateway.campaign.table import open_table

    _view(args)
    table, meta, d = open_table(args.table)
    rows = table.to_pylist()
    print(f"campaign {meta.get('name', '?')}: {len(rows)} points in {d}")
    _report(rows, meta, d, Path(args.figures) if args.figures else d / "figures", args)
    return 0
