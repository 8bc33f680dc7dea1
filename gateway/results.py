"""The one writer of a run's results: ``signals.csv``, the figures and ``summary.json``.

`simulate`, `sim` and `run` all end here (:func:`gateway.session.run`), each file written
once: the record's columns (with the emulator's full-resolution truth merged in before
anything is written, where a `sim` run has it), the metrics computed once from them, the
figures drawn from the same columns, and the summary last, naming any file that could not
be written (``write_errors``, exit status 1).
"""

from __future__ import annotations

import logging
from collections.abc import Callable, Mapping
from pathlib import Path
from typing import Any, Protocol

import numpy as np

from gateway import report
from gateway.figures import Worker

log = logging.getLogger(__name__)


class TruthColumns(Protocol):
    """The emulator's state at full resolution by cycle (:class:`gateway.sim.TruthRecorder`)."""

    def columns(self, cycles: np.ndarray) -> dict[str, np.ndarray] | None: ...


def merge_truth(sig: dict[str, np.ndarray], truth: TruthColumns | None, period: float,
                lsb: float, on_bus: str = report.TRUTH_TPDO3) -> str:
    """Replace the drive's truth as the bus carried it in ``sig`` (``on_bus`` says how:
    TPDO3's INT16, or a standard drive's velocity actual value) by the emulator's
    full-resolution state of the same cycles, where it has them and they agree with the bus
    within half its LSB ``lsb`` (rad/s) wherever the bus does not saturate; returns what
    the truth rests on."""
    if truth is None or not len(sig["t"]):
        return on_bus
    full = truth.columns(np.rint(sig["t"] / period))
    if full is None:
        return on_bus
    ok = np.abs(sig["w_m"]) < 1000.0
    if not np.all(np.abs(full["w_m"][ok] - sig["w_m"][ok]) <= lsb / 2 + 1e-9):
        log.warning("the emulator's truth does not match the bus's cycle by cycle; the "
                    "summary uses the bus's")
        return on_bus
    sig.update(full)
    return report.TRUTH_FULL


def _try_write(errors: list[str], path: Path, write: Callable[[Path], object], what: str
               ) -> Any:
    try:
        return write(path)
    except OSError as exc:
        errors.append(f"cannot write {what} to {path}: {exc.strerror or exc}")
        return None


def write_results(out: Path, sig: Mapping[str, np.ndarray] | None, summary: dict[str, Any],
                  *, figures: bool, limits: Mapping[str, float] | None = None,
                  delay_s: float = 0.0, errors: list[str] | None = None,
                  worker: Worker | None = None) -> list[Path]:
    """Write ``signals.csv`` (``sig``: the record's columns; None: no cycle ran), the figures
    (``figures``: the run has the truth they need; drawn by ``worker`` where there is one,
    :class:`gateway.drawing.FigureWorker`) and ``summary.json``, once each; the figure
    titles come from ``summary["configuration"]``, the metric windows from its
    ``speed_error``. What cannot be written goes into ``summary["write_errors"]`` with exit
    status 1. Returns the files written, in that order (a file that failed is not among
    them: never a false "wrote")."""
    errors = list(errors or [])
    written: list[Path] = []
    if not out.is_dir():  # deleted or moved while the run went on
        try:
            out.mkdir(parents=True, exist_ok=True)
            errors.append(f"the run directory {out} was deleted or moved during the run: "
                          "made again for the results; what was written into it before "
                          "(the bus log) went with it")
            summary.setdefault("run", {})["bus_log_error"] = "deleted with the run directory"
        except OSError as exc:
            errors.append(f"the run directory {out} was deleted during the run and cannot be "
                          f"made again ({exc.strerror or exc}): nothing could be written")
    if sig is not None:
        n = len(errors)
        _try_write(errors, out / "signals.csv", lambda p: report.write_columns_csv(p, sig),
                   "the per-cycle signals")
        if len(errors) == n:
            written.append(out / "signals.csv")
        run = summary.get("run", {})
        stopped = ("" if run.get("stop") in (None, "END_OF_PROFILE")
                   else f"{run.get('stop')}, see summary.json run.stop_reason")
        if figures and "speed_error" in summary:
            written.extend(_try_write(errors, out, lambda p: report.plot_figures(
                sig, p, report.title_for(summary.get("configuration", {})),
                windows=summary["speed_error"]["windows"], limits=limits,
                delay_s=delay_s, stopped=stopped, worker=worker), "the figures") or [])
    n = len(errors)
    write_summary_noting(out, summary, errors)  # appends to ``errors`` when it fails
    if len(errors) == n:
        written.append(out / "summary.json")
    return written


def write_summary_noting(out: Path, summary: dict[str, Any], errors: list[str]) -> None:
    """summary.json, atomically; write errors (earlier ones in ``errors`` too) go into it,
    and if it cannot be written itself, into the exit status and onto stderr."""
    if errors:
        summary["write_errors"] = list(errors)
        summary.setdefault("run", {})["exit_status"] = 1
    try:
        report.write_summary(out / "summary.json", summary)
    except OSError as exc:
        errors.append(f"cannot write the summary to {out / 'summary.json'}: "
                      f"{exc.strerror or exc}")
        summary["write_errors"] = list(errors)
        summary.setdefault("run", {})["exit_status"] = 1
