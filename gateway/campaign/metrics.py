"""A run's summary (summary.json, :func:`gateway.report.metrics`) → the metric columns of a
campaign's table, and the names [pass] criteria may use.

For each error of the summary (speed ω − ω*, flux |ψr| − ψ*, estimation ω̂ − ω):
``<error>_rms``, ``<error>_max`` (of |·|), ``<error>_final``, and per metric window k (the
reference profile's segments, docs/outputs.md) ``<error>_max_w<k>`` and ``<error>_rms_w<k>``;
``peak_current`` (A), ``peak_voltage`` (V), ``cycles``; a bus run (``sim``) also
``missed_cycles``. Besides them the outcome columns ``exit_status`` and ``wall_time_s``
(:data:`OUTCOME`) may be used in criteria.
"""

from __future__ import annotations

import math
import re
from collections.abc import Mapping
from typing import Any

from gateway.errors import UserError

#: summary key → the metric columns' prefix
ERRORS = {"speed_error": "speed", "flux_error": "flux", "estimation_error": "estimation"}
STATS = ("rms", "max", "final")
SCALARS = ("peak_current", "peak_voltage")
RUN_COUNTS = ("cycles", "missed_cycles")
#: Outcome columns a criterion may use too.
OUTCOME = ("exit_status", "wall_time_s")
#: The fixed metric columns, in the table's order.
FIXED = tuple(f"{p}_{s}" for p in ERRORS.values() for s in STATS) + SCALARS + RUN_COUNTS
_WINDOW = re.compile(r"^(speed|flux|estimation)_(max|rms)_w(\d+)$")


def _num(x: Any) -> float:
    return math.nan if x is None else float(x)


def metrics_of(summary: Mapping[str, Any]) -> dict[str, float]:
    """The metric columns of one run's summary (absent metrics are left out)."""
    out: dict[str, float] = {}
    for key, prefix in ERRORS.items():
        m = summary.get(key)
        if not m:
            continue
        for stat in STATS:
            out[f"{prefix}_{stat}"] = _num(m.get(stat))
        for k, w in enumerate(m.get("windows", [])):
            out[f"{prefix}_max_w{k}"] = _num(w.get("max"))
            out[f"{prefix}_rms_w{k}"] = _num(w.get("rms"))
    for key in SCALARS:
        if key in summary:
            out[key] = _num(summary[key])
    run = summary.get("run", {})
    for key in RUN_COUNTS:
        if run.get(key) is not None:
            out[key] = float(run[key])
    return out


def is_metric(name: str) -> bool:
    """Whether ``name`` is a metric column (or an outcome a criterion may use)."""
    return name in FIXED or name in OUTCOME or _WINDOW.match(name) is not None


def check_metric(name: str, where: str) -> None:
    if not is_metric(name):
        raise UserError(f"{where}: {name!r} is not a metric of the table; use one of "
                        f"{', '.join(FIXED + OUTCOME)}, or a window's "
                        "<speed|flux|estimation>_<max|rms>_w<k> (k from 0, the profile's "
                        "segments)")


def window_sort_key(name: str) -> tuple[int, str]:
    """Metric columns in a stable order: the fixed ones first, then by window."""
    if name in FIXED:
        return (FIXED.index(name), "")
    m = _WINDOW.match(name)
    if m is None:
        return (10_000, name)
    prefixes = list(ERRORS.values())
    return (len(FIXED) + 6 * int(m.group(3)) + 2 * prefixes.index(m.group(1))
            + ("max", "rms").index(m.group(2)), name)
