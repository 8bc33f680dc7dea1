"""A campaign's table as one self-contained HTML page (`hil-gateway report CAMPAIGN_DIR`).

The page holds what `campaign show` prints and draws: the campaign (its file, command,
axes), how its points ended, how many passed each criterion of [pass], the worst points
with the command that reproduces each alone, the figures (embedded as base64 PNG: the page
opens offline), and the points themselves as a table, worst first (at most
:data:`MAX_ROWS`; the whole table is ``results.parquet``). Rendering only: the CLI writes
the file.
"""

from __future__ import annotations

import tempfile
from collections.abc import Mapping, Sequence
from pathlib import Path
from typing import Any

from gateway.campaign import figures, summary
from gateway.campaign.points import reproduce
from gateway.htmlreport import bullet_list, escape, kv_table, page, png_figure, table

#: Points shown in the page's table (worst first); the rest are in results.parquet.
MAX_ROWS = 500


def render(rows: Sequence[Mapping[str, Any]], meta: Mapping[str, Any], where: Path,
           metric: str | None = None, worst: int = summary.WORST) -> str:
    """The page of the campaign whose table ``rows`` and metadata ``meta`` are in
    ``where`` (the commands that reproduce points write their files into
    ``where/repro``); ``metric``: the figures' and the worst points' (default: the first
    criterion's)."""
    metric = summary.primary_metric(meta, metric)
    criteria = summary.criteria_of(meta)
    axes = [a["key"] for a in meta.get("axes", [])]
    name = str(meta.get("name", where.name))
    n_pass = sum(summary.passes(r, criteria) for r in rows)
    all_ok = bool(rows) and n_pass == len(rows)
    status = (f"{n_pass} of {len(rows)} points passed"
              + (" every criterion" if criteria else "") + " (and ran to the end)")
    parts = [f"<h1>Campaign {escape(name)}</h1>",
             f'<div class="status {"ok" if all_ok else "bad"}">{escape(status)}</div>',
             f"<p>{escape(summary.status_line(rows))}</p>",
             "<h2>Campaign</h2>", _campaign(meta, where, len(rows)),
             "<h2>Criteria</h2>", _criteria(rows, criteria),
             f"<h2>Worst points by {escape(metric)}</h2>",
             _worst(rows, criteria, metric, axes, where, worst),
             "<h2>Figures</h2>", _figures(rows, meta, metric),
             f"<h2>Points ({len(rows)})</h2>", _points(rows, criteria, metric, axes)]
    return page(f"campaign {name}", "\n".join(parts))


def _campaign(meta: Mapping[str, Any], where: Path, n: int) -> str:
    axes = [f"{a['key']}: " + (", ".join(a.get("values", [])) if a.get("grid")
                               else f"random ({a.get('kind', '')})")
            for a in meta.get("axes", [])]
    rows: list[tuple[str, Any]] = [
        ("file", meta.get("source", "—")), ("command", meta.get("command", "—")),
        ("directory", str(where)), ("points in the table", n),
        ("random draws", meta.get("random_n", "—"))]
    if meta.get("description"):
        rows.insert(0, ("description", meta["description"]))
    out = kv_table(rows) + ("<h3>Axes</h3>" + bullet_list(axes) if axes else "")
    text = meta.get("text")
    if text:
        out += ("<details><summary>The campaign file</summary><pre>"
                f"{escape(text)}</pre></details>\n")
    return out


def _criteria(rows: Sequence[Mapping[str, Any]], criteria: Sequence[Any]) -> str:
    if not criteria:
        return "<p>No [pass] criteria: a point passes when it ran to the end.</p>"
    body = [[str(c), *summary.criterion_counts(rows, c)] for c in criteria]
    return table(["criterion", "passed", "failed", "without a value"], body)


def _worst(rows: Sequence[Mapping[str, Any]], criteria: Sequence[Any], metric: str,
           axes: Sequence[str], where: Path, k: int) -> str:
    bad = summary.worst(rows, criteria, metric, k)
    if not bad:
        return "<p>No points.</p>"
    items = []
    for r in bad:
        passed = summary.passes(r, criteria)
        why = "" if r.get("status") == "ok" else f" — {r.get('status')}: {r.get('stop_reason', '')}"
        items.append(
            f"<li><b>#{escape(r.get('point'))}</b> {escape(metric)} = "
            f"{escape(_fmt(r.get(metric)))} {'(passed)' if passed else '(did not pass)'}"
            f"{escape(why)}<br>{escape(summary.params_text(r, axes))}<br>"
            f"<code>{escape(reproduce(r, where / 'repro'))}</code></li>")
    return "<ol>" + "\n".join(items) + "</ol>\n"


def _figures(rows: Sequence[Mapping[str, Any]], meta: Mapping[str, Any], metric: str) -> str:
    with tempfile.TemporaryDirectory(prefix="hil-campaign-report-") as tmp:
        drawn = figures.draw(rows, meta, metric, Path(tmp))
        if drawn is None:
            return "<p>No figures: matplotlib is not installed.</p>"
        if not drawn:
            return "<p>No figures: the table has no points.</p>"
        return "\n".join(png_figure(p.read_bytes(), p.stem.replace("_", " ")) for p in drawn)


def _points(rows: Sequence[Mapping[str, Any]], criteria: Sequence[Any], metric: str,
            axes: Sequence[str]) -> str:
    metrics = list(dict.fromkeys([metric, *(c.metric for c in criteria)]))
    heads = ["point", "passed", "status", *axes, *metrics, "wall time, s", "stop reason"]
    ordered = summary.worst(rows, criteria, metric, len(rows))
    body = [[r.get("point"), "yes" if summary.passes(r, criteria) else "no", r.get("status"),
             *(r.get(a) for a in axes), *(r.get(m) for m in metrics), r.get("wall_time_s"),
             r.get("stop_reason") or ""] for r in ordered[:MAX_ROWS]]
    note = (f"<p>The {MAX_ROWS} worst of {len(rows)} points; the whole table is "
            "results.parquet (<code>hil-gateway campaign show</code>).</p>"
            if len(rows) > MAX_ROWS else "")
    return note + table(heads, body)


def _fmt(x: Any) -> str:
    if isinstance(x, float):
        return f"{x:.4g}"
    return "—" if x is None else str(x)

