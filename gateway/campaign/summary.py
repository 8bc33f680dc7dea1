"""What a campaign's table says: how its points ended, how many passed each criterion of
[pass], and the worst points with the command that reproduces each alone.

A point passes when it ran to the end of its profile (status ``ok``) and every criterion
holds on its metrics; a criterion on a metric the point has no value for (it failed
before) does not hold.
"""

from __future__ import annotations

import math
from collections import Counter
from collections.abc import Mapping, Sequence
from pathlib import Path
from typing import Any

from gateway.campaign.model import Criterion, Op
from gateway.campaign.points import reproduce

DEFAULT_METRIC = "speed_rms"
WORST = 5


def criteria_of(meta: Mapping[str, Any]) -> list[Criterion]:
    return [Criterion(c["metric"], Op(c["op"]), float(c["threshold"]))
            for c in meta.get("criteria", [])]


def primary_metric(meta: Mapping[str, Any], given: str | None = None) -> str:
    """The metric the figures and the worst points show: ``given``, else the first
    criterion's, else the speed error's RMS."""
    if given:
        return given
    crit = criteria_of(meta)
    return crit[0].metric if crit else DEFAULT_METRIC


def passes(row: Mapping[str, Any], criteria: Sequence[Criterion]) -> bool:
    return row.get("status") == "ok" and all(c.passes(row.get(c.metric)) for c in criteria)


def _value(row: Mapping[str, Any], metric: str) -> float:
    v = row.get(metric)
    try:
        x = float(v)
    except (TypeError, ValueError):
        return math.inf
    return x if math.isfinite(x) else math.inf


def worst(rows: Sequence[Mapping[str, Any]], criteria: Sequence[Criterion], metric: str,
          k: int = WORST) -> list[Mapping[str, Any]]:
    """The ``k`` worst points: those that did not pass first, then by ``metric``, largest
    (or missing) first."""
    return sorted(rows, key=lambda r: (passes(r, criteria), -_value(r, metric),
                                       r.get("point", 0)))[:k]


def _fmt(x: Any) -> str:
    if isinstance(x, float):
        return f"{x:.4g}"
    return str(x)


def params_text(row: Mapping[str, Any], axes: Sequence[str]) -> str:
    return ", ".join(f"{a}={_fmt(row.get(a))}" for a in axes if a in row)


def status_line(rows: Sequence[Mapping[str, Any]]) -> str:
    counts = Counter(str(r.get("status")) for r in rows)
    stops = Counter(str(r.get("stop")).lower().replace("_", " ") for r in rows
                    if r.get("status") == "stopped")
    parts = []
    for status in ("ok", "stopped", "error", "timeout", "worker-died"):
        if counts.get(status):
            extra = (f" ({', '.join(f'{n} {s}' for s, n in stops.most_common())})"
                     if status == "stopped" else "")
            parts.append(f"{counts[status]} {status}{extra}")
    return "status: " + ", ".join(parts)


def text(rows: Sequence[Mapping[str, Any]], meta: Mapping[str, Any], metric: str,
         repro_dir: Path, k: int = WORST) -> str:
    """The summary: statuses, criteria, the worst points and how to reproduce each."""
    criteria = criteria_of(meta)
    axes = [a["key"] for a in meta.get("axes", [])]
    lines = [status_line(rows)]
    n = len(rows)
    if criteria:
        ok = sum(passes(r, criteria) for r in rows)
        lines.append(f"pass: {ok} of {n} points passed every criterion (and ran to the end)")
        width = max(len(str(c)) for c in criteria)
        for c in criteria:
            good, bad, without = criterion_counts(rows, c)
            lines.append(f"  {c!s:<{width}}  {good} passed, {bad} failed"
                         + (f", {without} without a value" if without else ""))
    else:
        lines.append("pass: no [pass] criteria; a point passes when it ran to the end")
    bad = worst(rows, criteria, metric, k)
    if bad:
        lines.append(f"worst {len(bad)} by {metric} (those that did not pass first):")
        for r in bad:
            v = r.get(metric)
            status = r.get("status")
            why = ("" if status == "ok" else
                   f"  {status}: {str(r.get('stop_reason', ''))[:120]}")
            lines.append(f"  #{r.get('point')} {metric} {_fmt(v) if v is not None else '—'}"
                         f"  {params_text(r, axes)}{why}")
            lines.append(f"    {reproduce(r, repro_dir)}")
    return "\n".join(lines)


def criterion_counts(rows: Sequence[Mapping[str, Any]], criterion: Criterion
                     ) -> tuple[int, int, int]:
    """How many points pass ``criterion``, fail it, and have no value for its metric."""
    has = [v for v in (r.get(criterion.metric) for r in rows)
           if v is not None and not _is_nan(v)]
    good = sum(criterion.passes(v) for v in has)
    return good, len(has) - good, len(rows) - len(has)


def _is_nan(v: Any) -> bool:
    return isinstance(v, float) and math.isnan(v)


def all_passed(rows: Sequence[Mapping[str, Any]], meta: Mapping[str, Any]) -> bool:
    criteria = criteria_of(meta)
    return all(passes(r, criteria) for r in rows)
