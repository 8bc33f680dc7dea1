"""What a drive engineer checks of a run, as assertions: settling time, overshoot,
steady-state error in a window, current peak, no fault.

Each takes a :class:`gateway.drivetest.DriveRun` (the pytest plugin's ``drive_run``
fixture returns one), raises :class:`AssertionError` with a message that says what was
asked, what the run did and when, and which run it was and where its files are; and
returns what it measured, for a test to print or check further. Signals are columns of
signals.csv (docs/outputs.md: ``w_m`` and ``w_ref`` in rad/s by default; ``psi_r_mod``
and ``psi_ref`` for the flux); times in s.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Any

import numpy as np

from gateway.stop import StopReason

#: The settling band when none is given: 2 % of the step.
DEFAULT_BAND = 0.02


@dataclass(frozen=True)
class Step:
    """A reference step seen in a run: from ``initial`` (the reference at ``start``) to
    ``final`` (at ``end``), s."""

    start: float
    end: float
    initial: float
    final: float

    @property
    def size(self) -> float:
        return self.final - self.initial


def _fail(run: Any, text: str) -> AssertionError:
    return AssertionError(f"{text}\n  run: {run.describe()}")


def _span(run: Any, start: float, end: float | None) -> tuple[np.ndarray, float]:
    """The selection of samples start ≤ t ≤ end (None: to the last) and the end used;
    ValueError when the run has no sample there."""
    t = run.column("t")
    stop = float(t[-1]) if end is None else float(end)
    sel = (t >= start) & (t <= stop)
    if not np.any(sel):
        raise ValueError(f"no sample of the run in [{start:g}, {stop:g}] s (it covers "
                         f"{t[0]:g} … {t[-1]:g} s)")
    return sel, stop


def step_of(run: Any, reference: str, start: float, end: float | None = None) -> Step:
    """The step of ``reference`` from ``start`` to ``end`` (None: the run's last sample):
    its value at the first sample from ``start`` and at the last up to ``end``."""
    sel, stop = _span(run, start, end)
    r = run.column(reference)[sel]
    return Step(start, stop, float(r[0]), float(r[-1]))


def settling_time(run: Any, after: float, *, signal: str = "w_m", reference: str = "w_ref",
                  band: float = DEFAULT_BAND, band_abs: float | None = None,
                  until: float | None = None) -> float | None:
    """How long after ``after`` ``signal`` enters, and then stays in, the band around the
    reference's final value (at ``until``, None: the end): ±``band_abs``, or ±``band``
    times the step's size. None when it is outside at the last sample."""
    sel, _ = _span(run, after, until)
    step = step_of(run, reference, after, until)
    width = _band(step, band, band_abs, reference)
    t, y = run.column("t")[sel], run.column(signal)[sel]
    outside = np.flatnonzero(~(np.abs(y - step.final) <= width))  # NaN is outside
    if not outside.size:
        return 0.0
    last = outside[-1]
    return None if last == len(t) - 1 else float(t[last + 1] - after)


def _band(step: Step, band: float, band_abs: float | None, reference: str) -> float:
    if band_abs is not None:
        return float(band_abs)
    if step.size == 0:
        raise ValueError(f"{reference} does not step between {step.start:g} and "
                         f"{step.end:g} s (it stays {step.final:.4g}): give band_abs, the "
                         "band in the signal's unit")
    return abs(band * step.size)


def assert_settles(run: Any, within: float, *, after: float, signal: str = "w_m",
                   reference: str = "w_ref", band: float = DEFAULT_BAND,
                   band_abs: float | None = None, until: float | None = None) -> float:
    """``signal`` settles within ``within`` s of ``after`` (the step's start) into the band
    around the reference's final value and stays there up to ``until`` (None: the end);
    the band is ±``band`` of the step (2 %) or ±``band_abs``. Returns the settling time."""
    ts = settling_time(run, after, signal=signal, reference=reference, band=band,
                       band_abs=band_abs, until=until)
    step = step_of(run, reference, after, until)
    width = _band(step, band, band_abs, reference)
    how = (f"±{width:.4g} ({100 * band:g} % of the {step.size:+.4g} step of {reference})"
           if band_abs is None else f"±{width:.4g}")
    if ts is None:
        y = run.column(signal)[_span(run, after, until)[0]]
        raise _fail(run, f"{signal} never settled after t = {after:g} s: at t = "
                         f"{step.end:g} s it is {y[-1]:.4g}, outside {how} of "
                         f"{step.final:.4g}")
    if ts > within:
        raise _fail(run, f"{signal} settled {ts:.4g} s after t = {after:g} s, not within "
                         f"{within:g} s: it stays within {how} of {step.final:.4g} only from "
                         f"t = {after + ts:.4g} s")
    return ts


def overshoot(run: Any, after: float, *, signal: str = "w_m", reference: str = "w_ref",
              until: float | None = None) -> tuple[float, float]:
    """How far ``signal`` goes beyond the reference's final value in the step's direction
    between ``after`` and ``until``, in per cent of the step (0 when it never does), and
    when its peak is, s."""
    sel, _ = _span(run, after, until)
    step = step_of(run, reference, after, until)
    _band(step, DEFAULT_BAND, None, reference)  # refuses a reference that does not step
    t, y = run.column("t")[sel], run.column(signal)[sel]
    beyond = (y - step.final) * math.copysign(1.0, step.size)
    k = int(np.nanargmax(beyond)) if np.any(np.isfinite(beyond)) else 0
    return max(0.0, 100.0 * float(beyond[k]) / abs(step.size)), float(t[k])


def assert_overshoot_below(run: Any, percent: float, *, after: float, signal: str = "w_m",
                           reference: str = "w_ref", until: float | None = None) -> float:
    """``signal``'s overshoot of the reference's step from ``after`` stays below
    ``percent`` per cent of the step. Returns the overshoot, %."""
    over, at = overshoot(run, after, signal=signal, reference=reference, until=until)
    if not over < percent:
        step = step_of(run, reference, after, until)
        raise _fail(run, f"{signal} overshoots the {step.size:+.4g} step of {reference} "
                         f"(to {step.final:.4g}) by {over:.3g} % at t = {at:.4g} s, not below "
                         f"{percent:g} %")
    return over


@dataclass(frozen=True)
class ErrorStats:
    """``signal`` − ``reference`` over a window: the largest magnitude and when, the mean
    (the offset) and the RMS."""

    max_abs: float
    t_max: float
    mean: float
    rms: float


def steady_state_error(run: Any, window: tuple[float, float], *, signal: str = "w_m",
                       reference: str = "w_ref") -> ErrorStats:
    """The error ``signal`` − ``reference`` over ``window`` (from, to in s, inclusive)."""
    sel, _ = _span(run, window[0], window[1])
    e = run.column(signal)[sel] - run.column(reference)[sel]
    t = run.column("t")[sel]
    k = int(np.argmax(np.where(np.isfinite(e), np.abs(e), np.inf)))
    return ErrorStats(float(abs(e[k])), float(t[k]), float(np.mean(e)),
                      float(np.sqrt(np.mean(e * e))))


def assert_steady_state_error(run: Any, below: float, *, window: tuple[float, float],
                              signal: str = "w_m", reference: str = "w_ref") -> ErrorStats:
    """|``signal`` − ``reference``| stays below ``below`` throughout ``window`` (from, to
    in s). Returns the error's statistics."""
    st = steady_state_error(run, window, signal=signal, reference=reference)
    if not st.max_abs < below:
        raise _fail(run, f"{signal} − {reference} reaches {st.max_abs:.4g} at t = "
                         f"{st.t_max:.4g} s in [{window[0]:g}, {window[1]:g}] s, not below "
                         f"{below:g} (mean {st.mean:+.4g}, rms {st.rms:.4g})")
    return st


def current_peak(run: Any, window: tuple[float, float] | None = None) -> tuple[float, float]:
    """The largest stator current magnitude |i_s| = hypot(i_sa, i_sb), A, and when, s
    (over ``window``, None: the whole run)."""
    sel, _ = _span(run, *(window or (-math.inf, None)))
    t = run.column("t")[sel]
    i = np.hypot(run.column("i_sa")[sel], run.column("i_sb")[sel])
    k = int(np.argmax(np.where(np.isfinite(i), i, np.inf)))
    return float(i[k]), float(t[k])


def assert_current_peak_below(run: Any, amps: float,
                              window: tuple[float, float] | None = None) -> float:
    """|i_s| stays below ``amps`` (over ``window``, None: the whole run). Returns the
    peak, A."""
    peak, at = current_peak(run, window)
    if not peak < amps:
        where = "" if window is None else f" in [{window[0]:g}, {window[1]:g}] s"
        raise _fail(run, f"the stator current |i_s| reaches {peak:.4g} A at t = {at:.4g} s"
                         f"{where}, not below {amps:g} A")
    return peak


def assert_no_fault(run: Any) -> None:
    """The run went to the end of its profile with exit status 0: no stop for a fault, no
    EMCY or fault recorded, the drive confirmed safe where it was shut down, every file
    written."""
    s = run.summary
    problems = []
    if run.stop is not StopReason.END_OF_PROFILE:
        problems.append(f"it stopped early: {run.stop.name} ({run.stop_reason})")
    faults = s.get("faults") or []
    problems += [f"fault at {f.get('time')}: {f.get('kind')} {f.get('text', '')}".rstrip()
                 for f in faults]
    shutdown = s.get("shutdown")
    if shutdown is not None and not shutdown.get("safe", False):
        problems.append(f"the drive was not confirmed safe ({'; '.join(shutdown['steps'])})")
    problems += [f"not written: {e}" for e in s.get("write_errors", [])]
    if run.exit_status != 0 and not problems:
        problems.append(f"exit status {run.exit_status}")
    if problems:
        raise _fail(run, "the run did not go cleanly: " + "; ".join(problems))
