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
import os
import queue
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
    """Run ``points`` one after the other (one parser and one runner thread for the
    batch: a new thread per point made each run about 5 % slower, its first steps on a
    cold thread)."""
    parser = shared_parser()
    result = BatchResult()
    runner = _Runner(limits, parser)
    try:
        for point in points:
            row, abandoned = runner.run(point)
            result.outcomes[point.hash] = row
            if abandoned:
                result.abandoned = True
                break  # this process is no place for more runs: the rest go elsewhere
    finally:
        runner.close()
    return result


class _Runner:
    """The thread a batch's points run in, one at a time; a point past its time limit is
    asked to stop, and if it does not within the grace period, it is left behind with its
    thread (no further point is given to it)."""

    def __init__(self, limits: Limits, parser: argparse.ArgumentParser) -> None:
        self.limits = limits
        self.parser = parser
        self._thread: threading.Thread | None = None
        self._todo: queue.SimpleQueue[tuple[PointConfig, StopSignals, dict[str, Any],
                                            threading.Event] | None] = queue.SimpleQueue()

    def _loop(self) -> None:
        while (job := self._todo.get()) is not None:
            point, signals, box, done = job
            _run(point, self.limits, self.parser, signals, box)
            done.set()

    def run(self, point: PointConfig) -> tuple[dict[str, Any], bool]:
        limits = self.limits
        if self._thread is None:
            self._thread = threading.Thread(target=self._loop, name="campaign points",
                                            daemon=True)
            self._thread.start()
        signals = StopSignals()
        box: dict[str, Any] = {}
        done = threading.Event()
        t0 = time.perf_counter()
        self._todo.put((point, signals, box, done))
        try:
            done.wait(limits.timeout)
        except BaseException:  # Ctrl-C in the in-process engine: the run stops within a cycle
            signals.request("interrupted")
            done.wait(limits.grace)
            raise
        if done.is_set():
            return box["row"], False
        signals.request(f"time limit of {limits.timeout:g} s per point")
        done.wait(limits.grace)
        wall = time.perf_counter() - t0
        if not done.is_set():
            self._thread = None  # left behind with its point; never given another:
            self._todo = queue.SimpleQueue()  # a next point gets a new thread and queue
            return outcome(PointStatus.TIMEOUT, f"past the time limit of {limits.timeout:g} "
                           f"s per point and not stopped {limits.grace:g} s after it (left "
                           "behind; raise --timeout if the point is merely slow)",
                           EXIT_TIMEOUT, wall), True
        row = dict(box["row"])
        row.update(status=PointStatus.TIMEOUT.value, exit_status=EXIT_TIMEOUT,
                   stop_reason=f"past the time limit of {limits.timeout:g} s per point; "
                               f"stopped ({row['stop_reason']})")
        return row, False

    def close(self) -> None:
        """The runner thread ends after its point (if one is left behind, with it)."""
        if self._thread is not None:
            self._todo.put(None)
            self._thread = None


def _run(point: PointConfig, limits: Limits, parser: argparse.ArgumentParser,
         signals: StopSignals, box: dict[str, Any]) -> None:
    t0 = time.perf_counter()
    try:
        box["row"] = _run_checked(point, limits, parser, signals, t0)
    except UserError as exc:
        box["row"] = outcome(PointStatus.ERROR, str(exc), exc.exit_code,
                             time.perf_counter() - t0)
    except Exception as exc:  # a run that fails is a row with the reason, not a lost batch
        box["row"] = outcome(PointStatus.ERROR, f"{type(exc).__name__}: {exc}", 1,
                             time.perf_counter() - t0)


def _run_dir(point: PointConfig, limits: Limits) -> str:
    return str(Path(limits.runs_dir) / f"{point.index:05d}-{point.hash[:8]}")


def _run_checked(point: PointConfig, limits: Limits, parser: argparse.ArgumentParser,
                 signals: StopSignals, t0: float) -> dict[str, Any]:
    from gateway.cli import sim_inputs, simulate_inputs
    from gateway.session import Output, run, save
    from gateway.sim import scenario_from_text

    args = parse_args(parser, point.command, point.argv)
    plant = scenario_from_text(*point.plant) if point.plant else None
    params = dict(point.controller_params) if point.controller_params is not None else None
    keep_dir = _run_dir(point, limits)
    if point.command is Command.SIMULATE:
        inputs = simulate_inputs(args, plant, params)
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
