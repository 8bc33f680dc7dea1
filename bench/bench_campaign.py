"""Campaign throughput: points per second in this process and on a local Dask cluster of 1
and 2 workers, the campaign's overhead per point against calling the simulation directly,
and the scaling of 2 workers against 1.

    .venv/bin/python bench/bench_campaign.py            # 400 points of 150 ms, 3 repeats
    .venv/bin/python bench/bench_campaign.py --quick    # 100 points, 1 repeat

The points: the quick profile for 150 ms, a Monte Carlo of R_s (±5 %) and J (±20 %),
the R_s-adaptive estimator. Baseline: the same points' simulations called directly
(:func:`gateway.session.run` on a RunSpec made beforehand), in the same invocation,
interleaved with the campaign in this process; and the points as the command line runs
one (its inputs built from the options, :func:`gateway.cli.simulate_inputs`, then the same
call), which is what a point runs.

Overhead per point (the target, < 5 %): the campaign's time in this process less the time
its points spent in :func:`gateway.session.run` (each call timed), against that time: what
the campaign adds to calling the simulation, measured in one pass, so that a shared
machine's load drifting between passes (two passes of the same direct loop differ by up to
20 % here) does not enter it. Beside it, as checks: the simulation inside the campaign
against the same point's direct call (median over points of the ratio: the campaign must
not make the run itself slower), and the whole pass against the direct pass (the older
figure; it carries the drift). Rates are over the points' running (the runner's loop, the
table written per batch), the cluster's start-up apart. Scaling = rate of 2 workers / rate
of 1 in each repeat (the two measured back to back), median of the repeats (target ≥ 1.8×;
on a shared 2-core machine the second worker competes with everything else). Medians of
the repeats.

A campaign that fails (a point not 'ok', the cluster not starting) is a failed
measurement (bench/_common.py). ``--json [FILE]`` keys: ``points``, ``repeats``,
``direct_s``, ``cli_s``, ``in_process_s``, ``overhead_per_point_pct``,
``run_in_campaign_pct``, ``overhead_vs_direct_pct``, ``overhead_vs_cli_pct``,
``rate_direct``, ``rate_in_process``, ``rate_1_worker``, ``rate_2_workers``,
``cluster_start_s``, ``scaling_2_vs_1``, ``scaling_2_vs_1_runs`` (points per second,
seconds),
``failed``.
"""

from __future__ import annotations

import argparse
import statistics
import sys
import tempfile
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from _common import Figures, RunError, add_json_option, the_run  # noqa: E402

CAMPAIGN = """
[campaign]
name = "bench"
[base]
profile = "{root}/profiles/quick.toml"
duration = "{duration}"
estimator = "rs-adaptive"
[random]
n = {n}
seed = {seed}
"plant.motor.Rs" = {{dist = "uniform", low = 0.95, high = 1.05}}
"plant.motor.J" = {{dist = "uniform", low = 0.8, high = 1.2}}
"""


def points(n: int, seed: int, duration: str = "150ms"):
    from gateway.campaign.model import parse_campaign
    from gateway.campaign.options import command_options
    from gateway.campaign.points import plan

    campaign = parse_campaign(CAMPAIGN.format(root=ROOT, n=n, seed=seed, duration=duration),
                              "<bench>",
                              command_options)
    return campaign, plan(campaign, ROOT)[0]


def direct(pts, each: list[float] | None = None) -> float:
    """The points' simulations called directly: their RunSpecs made first (not timed);
    ``each``: each point's time appended."""
    from gateway.campaign.options import build_parser, parse_args
    from gateway.cli import simulate_inputs
    from gateway.session import run
    from gateway.sim import scenario_from_text

    parser = build_parser()
    inputs = [simulate_inputs(parse_args(parser, p.command, p.argv),
                              scenario_from_text(*p.plant)) for p in pts]
    t0 = time.perf_counter()
    for i in inputs:
        t = time.perf_counter()
        result = run(i.spec, i.profile, i.motor, windows=i.windows)
        if each is not None:
            each.append(time.perf_counter() - t)
        if result.exit_status:
            raise RunError(f"a direct run stopped: {result.summary['run']['stop_reason']}")
    return time.perf_counter() - t0


def direct_cli(pts) -> float:
    """The points as the command line runs one: its inputs from the options
    (:func:`gateway.cli.simulate_inputs`, timed), then :func:`gateway.session.run`."""
    from gateway.campaign.options import build_parser, parse_args
    from gateway.cli import simulate_inputs
    from gateway.session import run
    from gateway.sim import scenario_from_text

    parser = build_parser()
    t0 = time.perf_counter()
    for p in pts:
        i = simulate_inputs(parse_args(parser, p.command, p.argv), scenario_from_text(*p.plant))
        if run(i.spec, i.profile, i.motor, windows=i.windows).exit_status:
            raise RunError("a direct run stopped")
    return time.perf_counter() - t0


class RunTimer:
    """:func:`gateway.session.run` timed, call by call, while in use (a point imports it
    when it runs: the module's attribute is what it calls)."""

    def __init__(self) -> None:
        self.each: list[float] = []

    def __enter__(self) -> RunTimer:
        import gateway.session as session

        self._session, self._run = session, session.run

        def timed(*args, **kwargs):
            t0 = time.perf_counter()
            try:
                return self._run(*args, **kwargs)
            finally:
                self.each.append(time.perf_counter() - t0)

        session.run = timed
        return self

    def __exit__(self, *exc) -> None:
        self._session.run = self._run


def campaign_run(campaign, pts, engine, timer: RunTimer | None = None) -> float:
    """The points through the campaign's runner on ``engine`` into a new table
    (``timer``: its calls of the simulation timed, in this process)."""
    import contextlib

    from gateway.campaign import runner
    from gateway.campaign.runpoint import Limits

    with tempfile.TemporaryDirectory(prefix="bench-campaign-") as d:
        table, _ = runner.prepare(Path(d), campaign, False)
        with timer or contextlib.nullcontext():
            t0 = time.perf_counter()
            rows = runner.run(engine, pts, table, Limits(runs_dir=d), lambda rows: None)
            seconds = time.perf_counter() - t0
        bad = [r for r in rows if r["status"] != "ok"]
        if bad or len(rows) != len(pts):
            why = bad[0]["stop_reason"] if bad else f"{len(rows)} rows of {len(pts)}"
            raise RunError(f"the campaign did not run every point: {why}")
        table.compact()
    return seconds


def in_process(campaign, pts, timer: RunTimer | None = None) -> float:
    from gateway.campaign.engine import InProcess

    return campaign_run(campaign, pts, InProcess(), timer)


def on_dask(campaign, pts, workers: int) -> tuple[float, float]:
    """(cluster start-up, running) seconds on a local cluster of ``workers``."""
    from gateway.campaign.engine import DaskEngine
    from gateway.campaign.options import Command

    t0 = time.perf_counter()
    engine = DaskEngine(Command.SIMULATE, workers=workers)
    start = time.perf_counter() - t0
    try:
        # the workers' first points import the gateway: warm them up apart
        campaign_run(campaign, pts[: 2 * workers], engine)
        return start, campaign_run(campaign, pts, engine)
    finally:
        engine.close()


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--quick", action="store_true", help="100 points, one repeat")
    ap.add_argument("--points", type=int, help="points per measurement (default 400)")
    ap.add_argument("--repeats", type=int, help="repeats (default 3)")
    ap.add_argument("--point-duration", default="150ms", metavar="DURATION",
                    help="each point's simulated time (default 150ms: short points, where "
                         "the per-point overhead shows most; the quick profile lasts 1.5 s)")
    add_json_option(ap)
    args = ap.parse_args(argv)
    n = args.points or (100 if args.quick else 400)
    repeats = args.repeats or (1 if args.quick else 3)
    campaign, pts = points(n, 1, args.point_duration)
    warm = points(4, 2)[1]
    fig = Figures(points=n, repeats=repeats)
    here = ("direct_s", "in_process_s", "rate_direct", "rate_in_process",
            "overhead_per_point_pct", "run_in_campaign_pct", "overhead_vs_direct_pct",
            "cli_s", "overhead_vs_cli_pct")
    try:
        with the_run("warm-up"):
            direct(warm)
            in_process(campaign, warm)
        d_s, p_s, c_s, own, slower = [], [], [], [], []
        for _ in range(repeats):  # interleaved: the machine's load falls on all alike
            each: list[float] = []
            with the_run("direct"):
                d_s.append(direct(pts, each))
            with the_run("command line's inputs"):
                c_s.append(direct_cli(pts))
            timer = RunTimer()
            with the_run("in process"):
                p_s.append(in_process(campaign, pts, timer))
            if len(timer.each) != len(each):
                raise RunError(f"the campaign ran the simulation {len(timer.each)} times "
                               f"for {len(each)} points")
            own.append(100.0 * (p_s[-1] - sum(timer.each)) / sum(timer.each))
            slower.append(100.0 * (statistics.median(
                c / d for c, d in zip(timer.each, each, strict=True)) - 1.0))
    except RunError as exc:
        fig.fail(here, str(exc))
    else:
        d, p = statistics.median(d_s), statistics.median(p_s)
        fig.put("direct_s", d)
        fig.put("in_process_s", p)
        fig.put("rate_direct", n / d)
        fig.put("rate_in_process", n / p)
        fig.put("overhead_per_point_pct", statistics.median(own))
        fig.put("run_in_campaign_pct", statistics.median(slower))
        # the whole pass against the baseline pass beside it, then the median: the load
        # drifts between passes, and this figure with it
        fig.put("overhead_vs_direct_pct", statistics.median(
            100.0 * (pi - di) / di for pi, di in zip(p_s, d_s, strict=True)))
        c = statistics.median(c_s)
        fig.put("cli_s", c)
        fig.put("overhead_vs_cli_pct", statistics.median(
            100.0 * (pi - ci) / ci for pi, ci in zip(p_s, c_s, strict=True)))
    rates: dict[int, list[float]] = {1: [], 2: []}
    starts: list[float] = []
    pairs: list[tuple[float, float]] = []
    for _ in range(repeats):
        this: dict[int, float] = {}
        for w in (1, 2):
            try:
                with the_run(f"{w} worker(s)"):
                    start, seconds = on_dask(campaign, pts, w)
            except RunError as exc:
                fig.fail(f"rate_{w}_worker{'s' if w > 1 else ''}", str(exc))
                continue
            starts.append(start)
            rates[w].append(this.setdefault(w, n / seconds))
        if len(this) == 2:
            pairs.append((this[1], this[2]))
    for w, name in ((1, "rate_1_worker"), (2, "rate_2_workers")):
        if rates[w]:
            fig.put(name, statistics.median(rates[w]))
    fig.put("cluster_start_s", statistics.median(starts) if starts else None)
    if pairs:
        # each repeat's 2 workers against its own 1 worker, measured back to back, then the
        # median: the host's load drifts between repeats more than within one
        fig.put("scaling_2_vs_1", statistics.median(r2 / r1 for r1, r2 in pairs))
        fig.put("scaling_2_vs_1_runs", [r2 / r1 for r1, r2 in pairs])
    else:
        fig.fail("scaling_2_vs_1", "a cluster measurement failed")

    print(f"campaign throughput: {n} points (quick profile, {args.point_duration} each), "
          "median of "
          f"{repeats}")
    print(f"{'':34}{'points/s':>10}{'s':>9}   baseline / target")
    print(f"{'direct session.run (baseline)':34}"
          + fig.show("rate_direct", lambda v: f"{v:10.1f}{n / v:9.2f}"))
    print(f"{'inputs from options + session.run':34}"
          + fig.show("cli_s", lambda v: f"{n / v:10.1f}{v:9.2f}   the command line's path"))
    print(f"{'campaign, in this process':34}"
          + fig.show("rate_in_process", lambda v: f"{v:10.1f}{n / v:9.2f}")
          + fig.show("overhead_per_point_pct",
                     lambda v: f"   overhead {v:+.1f} % per point (target < 5 %)"))
    print(f"{'':34}{'':19}   checks: its simulations "
          + fig.show("run_in_campaign_pct", "{:+.1f} %")
          + " against the same points' direct calls (median of the points); the pass "
          + fig.show("overhead_vs_direct_pct", "{:+.1f} %") + " against the direct pass, "
          + fig.show("overhead_vs_cli_pct", "{:+.1f} %")
          + " against the command line's (both carry the load's drift between passes)")
    for w, name in ((1, "rate_1_worker"), (2, "rate_2_workers")):
        label = f"campaign, local cluster, {w} worker{'s' if w > 1 else ''}"
        print(f"{label:34}" + fig.show(name, lambda v: f"{v:10.1f}{n / v:9.2f}"))
    print(f"{'scaling 2 workers / 1':34}" + fig.show(
        "scaling_2_vs_1", lambda v: f"{v:10.2f}×{'':8}   target ≥ 1.8×")
          + (f" (repeats: {', '.join(f'{r:.2f}' for r in fig.values['scaling_2_vs_1_runs'])})"
             if "scaling_2_vs_1_runs" in fig.values else ""))
    print(f"(the local cluster starts in {fig.show('cluster_start_s', '{:.1f}')} s, not in "
          "the rates)")
    fig.report_failures()
    fig.emit(args.json)
    return fig.exit_status()


if __name__ == "__main__":
    sys.exit(main())
