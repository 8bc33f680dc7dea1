"""One point on a worker: the command line's own parser and inputs, then
:func:`gateway.session.run`, within a time limit; the outcome as the table's columns.

The runs of a batch go on in a thread of their own, one after the other. At the time
limit a run is asked to stop as Ctrl-C would (:meth:`gateway.stop.StopSignals.request`;
the loop stops within a cycle), and given a grace period; a run that still has not
returned is left behind (its thread is a daemon) and the batch says so, so that the engine
can restart that worker. Either way the point becomes a row (status ``timeout``), never a
hung campaign.

A point's run directory is written only on request (``keep_runs``) or when the point
failed (it did not run to the end of its profile): into ``runs_dir``/<index>-<hash>/.
A `sim` point always writes one (its bus log), removed again when it is not to be kept.
"""

from __future__ import annotations

import argparse
import copy
import json
import math
import os
import shutil
import socket
import threading
import time
from collections.abc import Sequence
from dataclasses import dataclass, field
from enum import StrEnum
from pathlib import Path
from typing import Any

from gateway.campaign.metrics import metrics_of
from gateway.campaign.options import Command, parse_args, shared_parser
from gateway.campaign.points import PointConfig
from gateway.errors import UserError
from gateway.stop import StopSignals


class PointStatus(StrEnum):
    """How a point ended (the table's ``status``)."""

    OK = "ok"  #: ran to the end of its profile
    STOPPED = "stopped"  #: the run stopped early by itself (diverged, drive fault, ...)
    ERROR = "error"  #: refused or failed with an error (its reason says which)
    TIMEOUT = "timeout"  #: past its time limit
    WORKER_DIED = "worker-died"  #: the process running it died (again on a retry)

    @property
    def ran(self) -> bool:
        """A result of the point's run itself (kept on a re-run even with --retry-failed)."""
        return self in (PointStatus.OK, PointStatus.STOPPED)


#: The exit status recorded for a point that has no run's: over its time limit (as
#: timeout(1)), its worker killed (128 + SIGKILL).
EXIT_TIMEOUT = 124
EXIT_WORKER_DIED = 137


@dataclass(frozen=True)
class Limits:
    """How points run: ``timeout`` (s per point), ``grace`` (s to stop after it),
    ``keep_runs`` (every point's run directory), ``runs_dir`` (where run directories go,
    absolute)."""

    timeout: float = 300.0
    grace: float = 10.0
    keep_runs: bool = False
    runs_dir: str = ""


@dataclass
class BatchResult:
    """The outcome columns of each point of a batch (by hash), and whether a run was left
    behind in its thread (the worker should be restarted)."""

    outcomes: dict[str, dict[str, Any]] = field(default_factory=dict)
    abandoned: bool = False


def where() -> str:
    """This worker, as the table names it: host:pid."""
    return f"{socket.gethostname()}:{os.getpid()}"


def outcome(status: PointStatus, reason: str, exit_status: int, wall: float,
            stop: str = "", run_dir: str | None = None, **metrics: float) -> dict[str, Any]:
    """A point's outcome columns."""
    return {"status": status.value, "stop": stop, "stop_reason": " ".join(reason.split()),
            "exit_status": exit_status, "wall_time_s": wall, "worker": where(),
            "run_dir": run_dir, **metrics}


def run_batch(points: Sequence[PointConfig], limits: Limits) -> BatchResult:
    """Run ``points`` one after the other in one runner thread, which goes from one point
    to the next by itself while this thread watches each point's time limit (a new thread
    per point made each run about 5 % slower, its first steps on a cold thread; handing
    each point over cost another 0.1 ms)."""
    jobs = [_Job(p) for p in points]
    cancel = threading.Event()  # no further point starts (one left behind, or Ctrl-C)
    finished = threading.Event()  # every job done (the runner thread's last act)
    thread = threading.Thread(target=_work, args=(jobs, limits, _Options(shared_parser()),
                                                  cancel, finished),
                              name="campaign points", daemon=True)
    result = BatchResult()
    thread.start()
    try:
        for job in jobs:
            row, abandoned = _watch(job, limits, thread, cancel, finished)
            result.outcomes[job.point.hash] = row
            if abandoned:
                result.abandoned = True
                break  # this process is no place for more runs: the rest go elsewhere
    finally:
        cancel.set()
    return result


@dataclass
class _Job:
    """One point in the runner thread: its stop ``signals``, when it ``started`` (``t0``,
    perf_counter s), when it is ``done`` and its ``row``."""

    point: PointConfig
    signals: StopSignals = field(default_factory=StopSignals)
    started: threading.Event = field(default_factory=threading.Event)
    done: threading.Event = field(default_factory=threading.Event)
    t0: float = 0.0
    row: dict[str, Any] = field(default_factory=dict)


def _work(jobs: Sequence[_Job], limits: Limits, options: _Options,
          cancel: threading.Event, finished: threading.Event) -> None:
    """The runner thread: the jobs one after the other, until one is cancelled."""
    for job in jobs:
        if cancel.is_set():
            return
        job.t0 = time.perf_counter()
        job.started.set()
        job.row = _run(job.point, limits, options, job.signals)
        job.done.set()
    finished.set()


def _watch(job: _Job, limits: Limits, thread: threading.Thread, cancel: threading.Event,
           finished: threading.Event) -> tuple[dict[str, Any], bool]:
    """``job``'s row once it is done, within its time limit (asked to stop past it, as
    Ctrl-C would); (row, whether its run was left behind in the runner thread). This
    thread sleeps until the batch is finished or the point's time limit, not once per
    point (waking for each took the runner's GIL once more a point)."""
    while not job.started.wait(1.0):  # at once: the previous point is done
        if not thread.is_alive():  # pragma: no cover - _run catches what a run raises
            return outcome(PointStatus.ERROR, "the campaign's runner thread ended before "
                           "the point started", 1, math.nan), True
    try:
        while not job.done.is_set():
            left = job.t0 + limits.timeout - time.perf_counter()
            if left <= 0:
                break
            finished.wait(left)
    except BaseException:  # Ctrl-C in the in-process engine: the run stops within a cycle
        cancel.set()
        job.signals.request("interrupted")
        job.done.wait(limits.grace)
        raise
    if job.done.is_set():
        return job.row, False
    job.signals.request(f"time limit of {limits.timeout:g} s per point")
    job.done.wait(limits.grace)
    if not job.done.is_set():
        cancel.set()  # left behind with its point; never given another
        return outcome(PointStatus.TIMEOUT, f"past the time limit of {limits.timeout:g} "
                       f"s per point and not stopped {limits.grace:g} s after it (left "
                       "behind; raise --timeout if the point is merely slow)",
                       EXIT_TIMEOUT, time.perf_counter() - job.t0), True
    row = dict(job.row)
    row.update(status=PointStatus.TIMEOUT.value, exit_status=EXIT_TIMEOUT,
               stop_reason=f"past the time limit of {limits.timeout:g} s per point; "
                           f"stopped ({row['stop_reason']})")
    return row, False


class _Options:
    """A batch's points' options, parsed by the command line's parser and (`simulate`)
    checked into :class:`gateway.cli.SimulateOptions`, once for the points that share
    them: the points of a campaign that sweeps only plant keys differ in their plant alone
    (the parsing and checking was 4 % of a 150 ms point)."""

    def __init__(self, parser: argparse.ArgumentParser) -> None:
        self.parser = parser
        self._kept: dict[tuple[Any, ...], tuple[argparse.Namespace, Any]] = {}

    def of(self, point: PointConfig) -> tuple[argparse.Namespace, Any]:
        """(the point's parsed options, a copy; its SimulateOptions or None for `sim`)."""
        from gateway.cli import simulate_options

        params = point.controller_params
        key = (point.command, point.argv,
               None if params is None else json.dumps(params, sort_keys=True, default=repr))
        kept = self._kept.get(key)
        if kept is None:
            args = parse_args(self.parser, point.command, point.argv)
            checked = (simulate_options(args, dict(params) if params is not None else None)
                       if point.command is Command.SIMULATE else None)
            kept = self._kept[key] = (args, checked)
        return copy.copy(kept[0]), kept[1]


def _run(point: PointConfig, limits: Limits, options: _Options,
         signals: StopSignals) -> dict[str, Any]:
    """The point's row (a run that fails is a row with the reason, not a lost batch)."""
    t0 = time.perf_counter()
    try:
        return _run_checked(point, limits, options, signals, t0)
    except UserError as exc:
        return outcome(PointStatus.ERROR, str(exc), exc.exit_code, time.perf_counter() - t0)
    except Exception as exc:
        return outcome(PointStatus.ERROR, f"{type(exc).__name__}: {exc}", 1,
                       time.perf_counter() - t0)


def _run_dir(point: PointConfig, limits: Limits) -> str:
    return str(Path(limits.runs_dir) / f"{point.index:05d}-{point.hash[:8]}")


def _run_checked(point: PointConfig, limits: Limits, options: _Options,
                 signals: StopSignals, t0: float) -> dict[str, Any]:
    from gateway.cli import sim_inputs, simulate_inputs
    from gateway.session import Output, run, save
    from gateway.sim import scenario_from_text

    args, checked = options.of(point)
    plant = scenario_from_text(*point.plant) if point.plant else None
    params = dict(point.controller_params) if point.controller_params is not None else None
    keep_dir = _run_dir(point, limits)
    if point.command is Command.SIMULATE:
        inputs = simulate_inputs(args, plant, params, checked)
        output = Output(keep_dir, "simulate", force=True) if limits.keep_runs else None
        result = run(inputs.spec, inputs.profile, inputs.motor, output=output,
                     windows=inputs.windows, signals=signals)
        if output is None and _failed(result.summary) and not signals.requested.is_set():
            result = save(result, inputs.spec, Output(keep_dir, "simulate", force=True))
    else:
        inputs = sim_inputs(args, plant, params)
        result = run(inputs.spec, inputs.profile, inputs.motor, target=inputs.target,
                     output=Output(keep_dir, "sim", force=True), windows=inputs.windows,
                     signals=signals)
        if not limits.keep_runs and not _failed(result.summary):
            shutil.rmtree(keep_dir, ignore_errors=True)
            result.out = None
    wall = time.perf_counter() - t0
    run_info = result.summary["run"]
    stop = str(run_info["stop"])
    if stop == "END_OF_PROFILE" and result.exit_status == 0:
        status = PointStatus.OK
    elif stop == "END_OF_PROFILE":  # ran, but a file could not be written
        status = PointStatus.ERROR
    else:
        status = PointStatus.STOPPED
    reason = str(run_info.get("stop_reason") or stop)
    if result.write_errors:
        reason += "; " + "; ".join(result.write_errors)
    return outcome(status, reason, result.exit_status, wall, stop,
                   str(result.out) if result.out is not None else None,
                   **metrics_of(result.summary))


def _failed(summary: dict[str, Any]) -> bool:
    run_info = summary["run"]
    return run_info["stop"] != "END_OF_PROFILE" or int(run_info["exit_status"]) != 0
