"""The regression gate: each run's metrics against a baseline run's, within the limits of
a tolerance file (:mod:`gateway.tolerance`).

One :class:`Check` per run × metric: passed, failed (moved beyond its limit, or not a
number in the run), or in error (the metric cannot be compared: missing in a summary, or
not a number in the baseline, or not a number at all such as a table or a text — the
tolerance file or the runs need fixing). :func:`exit_status` is 0 when every check
passed, 1 when one failed, 2 when one is in error.
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from enum import StrEnum
from typing import Any

from gateway.dotted import DottedKeyError, lookup
from gateway.tolerance import Direction, Limit


class Verdict(StrEnum):
    """A check's outcome."""

    PASS = "pass"
    FAIL = "FAIL"
    ERROR = "ERROR"


@dataclass(frozen=True)
class Check:
    """One metric of one run (``run``: its label) against the baseline's: the values (None:
    absent or not a number), the verdict, and what went wrong ("" when it passed)."""

    run: str
    limit: Limit
    baseline: float | None
    value: float | None
    verdict: Verdict
    message: str = ""

    @property
    def change(self) -> float | None:
        """value − baseline, when both are numbers."""
        if self.baseline is None or self.value is None:
            return None
        return self.value - self.baseline


def evaluate(baseline: Mapping[str, Any], runs: Sequence[tuple[str, Mapping[str, Any]]],
             limits: Sequence[Limit]) -> list[Check]:
    """Every run (label, summary) × every limit, run by run, in the tolerance file's order."""
    base = {lim.key: _number(baseline, lim.key, "the baseline") for lim in limits}
    out: list[Check] = []
    for label, summary in runs:
        for lim in limits:
            out.append(_check(label, lim, base[lim.key], _number(summary, lim.key, label)))
    return out


def exit_status(checks: Sequence[Check]) -> int:
    """2 when a check is in error, else 1 when one failed, else 0."""
    verdicts = {c.verdict for c in checks}
    return 2 if Verdict.ERROR in verdicts else 1 if Verdict.FAIL in verdicts else 0


def errors(checks: Sequence[Check]) -> list[str]:
    """The distinct messages of the checks in error, in order."""
    return list(dict.fromkeys(c.message for c in checks if c.verdict is Verdict.ERROR))


@dataclass(frozen=True)
class _Metric:
    """A metric read from a summary: its value (None: null, i.e. NaN or infinite), or why
    it cannot be compared (``problem``)."""

    value: float | None = None
    problem: str = ""
    null: bool = False


def _number(summary: Mapping[str, Any], key: str, whose: str) -> _Metric:
    try:
        x = lookup(summary, key)
    except DottedKeyError as exc:
        return _Metric(problem=f"{whose} has {exc}")
    if x is None:  # summary.json writes NaN and ±inf as null
        return _Metric(null=True)
    if isinstance(x, int | float) and not isinstance(x, bool):
        return _Metric(float(x))
    return _Metric(problem=f"{key!r} is {_what(key, x)} in {whose}, not a number: name a "
                           "number of summary.json in the tolerance file")


def _what(key: str, x: Any) -> str:
    if isinstance(x, Mapping):
        keys = ", ".join(f"{key}.{k}" for k in list(x)[:4])
        return f"a table ({keys}{', …' if len(x) > 4 else ''})"
    if isinstance(x, list | tuple):
        return f"a list of {len(x)} (its elements are {key}.0 …)" if x else "an empty list"
    return f"{type(x).__name__} {x!r}"


def _check(label: str, lim: Limit, base: _Metric, run: _Metric) -> Check:
    if base.problem or run.problem:
        return Check(label, lim, base.value, run.value, Verdict.ERROR,
                     base.problem or run.problem)
    if base.null:
        return Check(label, lim, None, run.value, Verdict.ERROR,
                     f"{lim.key!r} is null in the baseline (NaN or infinite): there is nothing "
                     "to compare with; choose another baseline run or metric")
    assert base.value is not None
    if run.null:
        return Check(label, lim, base.value, None, Verdict.FAIL,
                     f"{lim.key} is not a number in {label} (null in summary.json: NaN or "
                     f"infinite); the baseline's is {base.value:.4g}")
    assert run.value is not None
    if not lim.exceeded(base.value, run.value):
        return Check(label, lim, base.value, run.value, Verdict.PASS)
    change = run.value - base.value
    verb = "grew" if change > 0 else "fell"
    return Check(label, lim, base.value, run.value, Verdict.FAIL,
                 f"{lim.key} {verb} from {base.value:.4g} to {run.value:.4g} "
                 f"({_change_text(change, base.value, ', ')}), more than the "
                 f"{lim.allowed(base.value):.4g} allowed ({lim.describe()}) in {label}")


def _change_text(change: float, base: float, sep: str = " ") -> str:
    """``+4.01`` and, against a baseline other than 0, the change in per cent of it."""
    return f"{change:+.4g}" + (f"{sep}{100 * change / abs(base):+.3g} %" if base else "")


def table(checks: Sequence[Check]) -> str:
    """The checks as a plain-text table: run, metric, baseline, value, change, limit,
    result; then one line with the outcome."""
    heads = ["run", "metric", "baseline", "value", "change", "limit", "result"]
    rows = [heads]
    for c in checks:
        change = c.change
        rows.append([
            c.run, c.limit.key, _num(c.baseline), _num(c.value),
            "—" if change is None or c.baseline is None else _change_text(change, c.baseline),
            "—" if c.baseline is None else _limit_text(c.limit, c.baseline),
            c.verdict.value])
    widths = [max(len(r[j]) for r in rows) for j in range(len(heads))]
    lines = ["  ".join(cell.ljust(widths[j]) if j < 2 else cell.rjust(widths[j])
                       for j, cell in enumerate(r)).rstrip() for r in rows]
    return "\n".join(lines) + "\n" + outcome(checks)


def outcome(checks: Sequence[Check]) -> str:
    """One line: passed, or how many checks failed or could not be made, and which."""
    failed = [c for c in checks if c.verdict is Verdict.FAIL]
    broken = [c for c in checks if c.verdict is Verdict.ERROR]
    if not failed and not broken:
        return f"regression gate: passed, {len(checks)} checks within tolerance"
    parts = []
    if failed:
        parts.append(f"{len(failed)} of {len(checks)} checks failed ("
                     + ", ".join(f"{c.run}: {c.limit.key}" for c in failed) + ")")
    if broken:
        parts.append(f"{len(broken)} could not be made (errors below)")
    return "regression gate: FAILED, " + "; ".join(parts)


def _num(x: float | None) -> str:
    return "—" if x is None else f"{x:.4g}"


def _limit_text(lim: Limit, base: float) -> str:
    allowed = lim.allowed(base)
    return {Direction.UP: f"≤ +{allowed:.3g}", Direction.DOWN: f"≥ -{allowed:.3g}",
            Direction.BOTH: f"± {allowed:.3g}"}[lim.direction]
