"""One self-contained HTML page of a run, or of several runs side by side.

`hil-gateway report RUN_DIR` renders what a run directory holds: its configuration, the
outcome (stop, reason, exit status, shutdown), the commissioning (identification), the
metrics overall and per window, the figures (embedded as base64 PNG: the page opens
offline, with no other file), the bus's timing and counters, the faults, and every other
section ``summary.json`` has, shown generically as tables (a key this module does not know
yet still appears). Several run directories make one comparison page: their outcomes and
metrics side by side, the configuration keys that differ, the errors overlaid, and each
run's own page folded below. Rendering only: the CLI writes the file
(:func:`write_report`, complete or not at all).
"""

from __future__ import annotations

import base64
import html
import json
import math
import tempfile
from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from gateway import report
from gateway.atomicfile import write_text_atomic
from gateway.dotted import flatten
from gateway.errors import UserError
from gateway.rundir import RUN_FILES, RUNNING_MARKER, run_labels

#: The default file of a comparison of several runs (in the current directory).
COMPARISON_NAME = "compare.html"
#: What a report may be written as.
HTML_SUFFIXES = (".html", ".htm")
#: The run's figures, in the order a report shows them.
FIGURES = tuple(name for name in RUN_FILES if name.endswith(".png"))

_METRICS = (("speed error ω−ω*", "speed_error", "rad/s"),
            ("flux error |ψr|−ψ*", "flux_error", "Wb"),
            ("estimation error ω̂−ω", "estimation_error", "rad/s"))
#: Top-level summary keys with a section of their own; every other key gets a generic one.
_KNOWN = frozenset({
    "speed_error", "flux_error", "estimation_error", "peak_current", "peak_voltage",
    "truth", "quantisation", "configuration", "configuration_notes", "identification",
    "run", "timing", "shutdown", "faults", "stopped_early", "wall_time_s", "write_errors",
    "bus_faults"})
#: Keys of ``run`` the bus section shows (the outcome section shows the stop).
_BUS_COUNTERS = ("cycles", "missed_cycles", "late_rpdo", "rpdo_after_sync",
                 "last_good_cycle", "stop_cycle", "bus_log", "bus_frames_logged",
                 "bus_frames_dropped", "bus_log_error")
_OUTCOME_KEYS = frozenset({"status", "stop", "stop_reason", "exit_status", "cycles",
                           "wall_time_s", "tpdo_events", "frames_before_stop",
                           *_BUS_COUNTERS})

_CSS = """
body{font-family:system-ui,sans-serif;margin:1.5em auto;max-width:75em;color:#222;
line-height:1.35;padding:0 1em}
h1{font-size:1.5em;margin-bottom:.2em}h2{font-size:1.2em;border-bottom:1px solid #ccc;
margin-top:1.6em}h3{font-size:1.05em}
table{border-collapse:collapse;margin:.5em 0 1em}td,th{border:1px solid #ccc;
padding:.2em .55em;vertical-align:top;text-align:left}th{background:#f2f2f2}
td.num{text-align:right;font-variant-numeric:tabular-nums}
.status{padding:.5em .8em;border-radius:4px;font-weight:600;margin:.6em 0}
.ok{background:#e3f4e1;color:#1d5e1a}.bad{background:#fbe3e1;color:#8a1c12}
.warn{background:#fff4d6;color:#6b4d00}
.config{color:#555}figure{margin:1em 0}img{max-width:100%;border:1px solid #ddd}
figcaption{color:#555;font-size:.9em}nav a{margin-right:.8em}
details{margin:.6em 0;border:1px solid #ddd;padding:.3em .8em}
summary{cursor:pointer;font-weight:600}code{background:#f5f5f5;padding:0 .2em}
"""


@dataclass
class ReportRun:
    """A run directory as a report reads it: ``summary`` from ``summary.json`` or, for a
    run that never wrote one (still running, or its process died), from its
    ``running.json`` marker (``finished`` False); the figures it holds; its signals only
    when a comparison needs them (:meth:`signals`)."""

    path: Path
    summary: dict[str, Any]
    finished: bool
    figures: list[Path] = field(default_factory=list)

    @property
    def name(self) -> str:
        return self.path.name or str(self.path)

    def signals(self) -> tuple[dict[str, Any], str]:
        """The columns of ``signals.csv`` and "" — or {} and why there are none."""
        path = self.path / "signals.csv"
        if not path.is_file():
            return {}, "no signals.csv"
        try:
            return report.read_csv(path), ""
        except (OSError, ValueError, StopIteration) as exc:
            return {}, f"signals.csv cannot be read ({exc})"


def load(path: Path) -> ReportRun:
    """Read a run directory for a report; :class:`UserError` (what, where, what to give)
    when it is not one or its summary cannot be read."""
    if not path.is_dir():
        raise UserError(f"{str(path)!r} is not a directory: give run directories written "
                        "by simulate, sim or run")
    finished = (path / "summary.json").is_file()
    source = path / ("summary.json" if finished else RUNNING_MARKER)
    if not source.is_file():
        raise UserError(f"{str(path)!r} is not a run directory (no summary.json, no "
                        f"{RUNNING_MARKER}): give directories written by simulate, sim or run")
    try:
        summary = json.loads(source.read_text(encoding="utf-8"))
    except (OSError, ValueError) as exc:
        raise UserError(f"{str(source)!r} cannot be read ({exc}): a damaged run directory; "
                        "run it again") from exc
    if not isinstance(summary, dict):
        raise UserError(f"{str(source)!r} is not a run's summary (a JSON table is expected)")
    figures = [path / name for name in FIGURES if (path / name).is_file()]
    return ReportRun(path, summary, finished, figures)


# ------------------------------------------------------------------------------ pages


def render_run(run: ReportRun) -> str:
    """The whole page of one run."""
    body = _run_body(run, "")
    return page(f"run {run.name}", f"<h1>Run {escape(run.name)}</h1>\n{body}")


def render_comparison(runs: Sequence[ReportRun]) -> str:
    """The page of several runs: outcomes and metrics side by side, the configuration
    keys that differ, the errors overlaid, then each run's own page folded."""
    names = run_labels([r.path for r in runs])
    parts = [f"<h1>Comparison of {len(runs)} runs</h1>",
             "<nav>" + "".join(f'<a href="#r{j}">{escape(n)}</a>' for j, n in enumerate(names))
             + "</nav>",
             "<h2>Outcome</h2>", _comparison_outcome(runs, names),
             "<h2>Metrics</h2>", _comparison_metrics(runs, names),
             "<h2>Configuration</h2>", _comparison_config(runs, names),
             "<h2>Errors overlaid</h2>", _comparison_figure(runs, names)]
    for j, (run, name) in enumerate(zip(runs, names, strict=True)):
        parts.append(f'<details id="r{j}"><summary>{escape(name)} — {escape(_stop_text(run))}'
                     f"</summary>\n{_run_body(run, f'r{j}-')}</details>")
    return page(f"comparison of {len(runs)} runs", "\n".join(parts))


def check_output(out: Path) -> Path:
    """``out`` when it names an HTML file (by its suffix); else :class:`UserError`."""
    if out.suffix.lower() not in HTML_SUFFIXES:
        raise UserError(f"-o {str(out)!r}: a report is written as "
                        f"{' or '.join(HTML_SUFFIXES)} (by the suffix); e.g. -o "
                        f"{out.with_suffix('.html')}")
    return out


def write_report(runs: Sequence[ReportRun], out: Path) -> Path:
    """Render ``runs`` (one: its page; several: the comparison) and write ``out`` complete
    or not at all; :class:`UserError` when it cannot be written."""
    check_output(out)
    text = render_run(runs[0]) if len(runs) == 1 else render_comparison(runs)
    try:
        return write_text_atomic(out, text)
    except OSError as exc:
        raise UserError(f"cannot write the report to {str(out)!r}: {exc.strerror or exc}; "
                        "choose a writable place with -o FILE.html") from exc


def page(title: str, body: str) -> str:
    return ("<!DOCTYPE html>\n<html lang=\"en\">\n<head>\n<meta charset=\"utf-8\">\n"
            f"<title>{escape(title)}</title>\n<style>{_CSS}</style>\n</head>\n<body>\n{body}\n"
            "</body>\n</html>\n")


# ------------------------------------------------------------------------- one run


def _run_body(run: ReportRun, ids: str) -> str:
    """The sections of one run; ``ids`` prefixes the section anchors (unique on a page)."""
    s = run.summary
    sections: list[tuple[str, str, str | None]] = [
        ("outcome", "Outcome", _outcome(run)),
        ("configuration", "Configuration", _configuration(s)),
        ("identification", "Commissioning: identification at standstill",
         _identification(s.get("identification"))),
        ("metrics", "Metrics", _metrics(s)),
        ("figures", "Figures", _figures(run)),
        ("bus", "Bus: timing and counters", _bus(s)),
        ("faults", "Faults", _faults(s)),
        ("injected", "Injected bus faults and the reaction", _injected(s)),
    ]
    sections += [(f"x-{key}", _title(key), _value(s[key])) for key in s if key not in _KNOWN]
    shown = [(f"{ids}{a}", t, h) for a, t, h in sections if h is not None]
    conf = s.get("configuration") or {}
    head = [f'<p class="config">{escape(report.title_for(conf))}</p>' if conf else "",
            _status(run),
            "<nav>" + "".join(f'<a href="#{a}">{escape(t)}</a>' for a, t, _ in shown) + "</nav>"]
    body = [f'<section id="{a}"><h2>{escape(t)}</h2>\n{h}</section>' for a, t, h in shown]
    return "\n".join(head + body)


def _stop_text(run: ReportRun) -> str:
    r = run.summary.get("run") or {}
    if not run.finished:
        return "did not finish"
    return f"{r.get('stop', '?')}, exit status {r.get('exit_status', '?')}"


def _status(run: ReportRun) -> str:
    """The banner: how the run ended and its exit status."""
    r = run.summary.get("run") or {}
    if not run.finished:
        return ('<div class="status warn">Did not finish: the directory has only '
                f"{RUNNING_MARKER} (the run is still going, or its process was killed); what it "
                "configured is below, its results were never written.</div>")
    stop, status = r.get("stop"), r.get("exit_status")
    good = stop == "END_OF_PROFILE" and status == 0
    text = (f"Stopped: {stop} — {r.get('stop_reason', '')} · exit status {status}"
            if stop else f"exit status {status}")
    return f'<div class="status {"ok" if good else "bad"}">{escape(text)}</div>'


def _outcome(run: ReportRun) -> str:
    s = run.summary
    r = s.get("run") or {}
    rows: list[tuple[str, Any]] = [("run directory", str(run.path))]
    rows += [(k, r[k]) for k in ("status", "stop", "stop_reason", "exit_status", "cycles")
             if k in r]
    if "stopped_early" in s:
        rows.append(("stopped early", s["stopped_early"]))
    wall = r.get("wall_time_s", s.get("wall_time_s"))
    if wall is not None:
        rows.append(("wall time, s", wall))
    rows += [(f"run.{k}", r[k]) for k in r if k not in _OUTCOME_KEYS]
    out = kv_table(rows)
    if s.get("write_errors"):
        out += "<h3>Files that could not be written</h3>" + bullet_list(s["write_errors"])
    if s.get("shutdown"):
        out += "<h3>Shutdown</h3>" + _value(s["shutdown"])
    return out


def _configuration(s: Mapping[str, Any]) -> str | None:
    conf = s.get("configuration")
    if not conf and not s.get("configuration_notes"):
        return None
    out = _value(conf) if conf else ""
    if s.get("configuration_notes"):
        out += "<h3>Configuration notes</h3>" + bullet_list(s["configuration_notes"])
    return out


def _identification(ident: Any) -> str | None:
    if not ident:
        return None
    line = report.identification_line(ident) if isinstance(ident, Mapping) else ""
    return (f"<p>{escape(line)}</p>" if line else "") + _value(ident)


def _metrics(s: Mapping[str, Any]) -> str | None:
    if not any(key in s for _, key, _ in _METRICS):
        truth = "the drive sends no truth (ω, |ψr|), so there are no tracking errors"
        return f"<p>{escape(truth)}.</p>" if s.get("run") and s.get("timing") else None
    heads = ["", "max", "rms", "final"]
    rows = [[label, *(_si(s[key].get(k), unit) for k in ("max", "rms", "final"))]
            for label, key, unit in _METRICS if isinstance(s.get(key), Mapping)]
    out = table(heads, rows)
    windows = _windows(s)
    if windows:
        out += "<h3>Per window</h3>" + windows
    peaks = [(name, _si(s.get(key), unit)) for name, key, unit in
             (("peak current", "peak_current", "A"), ("peak voltage", "peak_voltage", "V"))
             if key in s]
    if "truth" in s:
        peaks.append(("truth (ω, |ψr|)", s["truth"]))
    out += kv_table(peaks)
    q = s.get("quantisation")
    if isinstance(q, Mapping):
        applied = "applied" if q.get("applied") else f"not applied ({q.get('reason', '')})"
        out += (f"<h3>Bus resolution</h3><p>{escape(applied)}, from "
                f"{escape(q.get('source', ''))}</p>")
        sig = q.get("signals")
        if isinstance(sig, Mapping) and sig:
            out += _records_table([{"signal": k, **v} for k, v in sig.items()
                                   if isinstance(v, Mapping)])
    return out


def _windows(s: Mapping[str, Any]) -> str:
    """One row per metric window: its span and label, each error's max and RMS."""
    present = [(label, key, unit) for label, key, unit in _METRICS
               if isinstance(s.get(key), Mapping) and s[key].get("windows")]
    if not present:
        return ""
    heads = ["window", "from, s", "to, s"]
    for label, _, _ in present:
        heads += [f"{label} max", "rms"]
    rows = []
    for j, w in enumerate(s[present[0][1]]["windows"]):
        row: list[Any] = [w.get("label", f"window {j}"), w.get("from"), w.get("to")]
        for _, key, unit in present:
            ws = s[key]["windows"]
            other = ws[j] if j < len(ws) else {}
            row += [_si(other.get("max"), unit), _si(other.get("rms"), unit)]
        rows.append(row)
    return table(heads, rows)


def _figures(run: ReportRun) -> str:
    if not run.figures:
        why = ("the run's results were never written" if not run.finished else
               "no truth from the drive, so no figures" if "truth" not in run.summary
               else "none in the run directory (matplotlib was not installed?)")
        return f"<p>No figures: {escape(why)}.</p>"
    return "\n".join(png_figure(p.read_bytes(), p.name) for p in run.figures)


def _bus(s: Mapping[str, Any]) -> str | None:
    r = s.get("run") or {}
    timing = s.get("timing")
    if not timing and "missed_cycles" not in r:
        return None  # a simulation: no bus
    out = ""
    if isinstance(timing, Mapping) and timing:
        rows = [[name, *(_us(v.get(k)) for k in ("median", "p99", "max", "min"))]
                for name, v in timing.items() if isinstance(v, Mapping)]
        out += table(["per cycle", "median, µs", "p99, µs", "max, µs", "min, µs"], rows)
    out += kv_table([(k, r[k]) for k in _BUS_COUNTERS if k in r])
    events = r.get("tpdo_events")
    if events is not None:
        out += "<h3>TPDO events</h3>" + (_value(events) if events else
                                         "<p>none (every TPDO on time)</p>")
    if r.get("frames_before_stop"):
        out += "<h3>The last frames before the stop</h3>" + _value(r["frames_before_stop"])
    return out


def _faults(s: Mapping[str, Any]) -> str | None:
    if "faults" not in s:
        return None
    return _value(s["faults"]) if s["faults"] else "<p>none</p>"


def _injected(s: Mapping[str, Any]) -> str | None:
    """The faults a plant scenario injected on the bus (``bus_faults``: each, and how often
    it acted), then what the run did: its stop, the TPDO events it counted."""
    if not s.get("bus_faults"):
        return None
    r = s.get("run") or {}
    reaction = [("stop", r.get("stop")), ("stop reason", r.get("stop_reason")),
                ("exit status", r.get("exit_status"))]
    reaction += [(k, r[k]) for k in ("tpdo_events", "max_consecutive_missed", "skipped_syncs",
                                         "error_frames")
                 if k in r]
    return _value(s["bus_faults"]) + "<h3>Reaction</h3>" + kv_table(reaction)


# ---------------------------------------------------------------------- comparison


def _comparison_outcome(runs: Sequence[ReportRun], names: list[str]) -> str:
    rows = []
    for run, name in zip(runs, names, strict=True):
        conf = run.summary.get("configuration") or {}
        r = run.summary.get("run") or {}
        rows.append([name, conf.get("command", ""),
                     report.profile_name(conf.get("profile")) or "—",
                     r.get("stop") if run.finished else "did not finish",
                     r.get("exit_status"), r.get("cycles")])
    return table(["run", "command", "profile", "stop", "exit status", "cycles"], rows)


def _comparison_metrics(runs: Sequence[ReportRun], names: list[str]) -> str:
    rows = []
    for label, unit, key, sub in report.COMPARED_METRICS:
        cells: list[Any] = [label]
        for run in runs:
            v: Any = run.summary.get(key)
            for k in sub:
                v = v.get(k) if isinstance(v, Mapping) else None
            cells.append(_si(v, unit))
        rows.append(cells)
    return table(["", *names], rows)


def _comparison_config(runs: Sequence[ReportRun], names: list[str]) -> str:
    as_runs = [report.Run(r.path, r.summary, {}) for r in runs]
    diffs = report.config_differences(as_runs)
    out = (table(["configuration key", *names], [[k, *v] for k, v in diffs.items()])
           if diffs else "<p>the same configuration</p>")
    some = report.config_only_in_some(as_runs)
    if some:
        out += f"<p>Not compared (only in some runs): {escape(', '.join(some))}</p>"
    return out


def _comparison_figure(runs: Sequence[ReportRun], names: list[str]) -> str:
    """The speed and flux errors of every run that has them, overlaid
    (:func:`gateway.report.plot_compare`)."""
    loaded, notes = [], []
    for run, name in zip(runs, names, strict=True):
        sig, why = run.signals()
        if why:
            notes.append(f"{name}: {why}")
        loaded.append(report.Run(Path(name), run.summary, sig))
    with tempfile.TemporaryDirectory(prefix="hil-report-") as tmp:
        png = report.plot_compare(loaded, Path(tmp) / "compare.png")
        figure = (png_figure(png.read_bytes(), "speed and flux errors of every run")
                  if png is not None else "<p>No figure: matplotlib is not installed.</p>")
    return figure + (bullet_list(notes) if notes else "")


# -------------------------------------------------------------------------- pieces


def escape(x: Any) -> str:
    return html.escape(str(x), quote=True)


def _title(key: str) -> str:
    words = key.replace("_", " ")
    return words[:1].upper() + words[1:]


def png_figure(data: bytes, caption: str) -> str:
    b64 = base64.b64encode(data).decode("ascii")
    return (f'<figure><img alt="{escape(caption)}" src="data:image/png;base64,{b64}">'
            f"<figcaption>{escape(caption)}</figcaption></figure>")


def _si(x: Any, unit: str) -> str:
    if x is None:
        return "—"
    if isinstance(x, bool) or not isinstance(x, int | float):
        return str(x)
    return report.format_si(float(x), unit)


def _us(x: Any) -> str:
    return "—" if not isinstance(x, int | float) else f"{1e6 * x:.1f}"


def _scalar(x: Any) -> str:
    """A leaf value as text: null as "—", floats with 6 significant digits."""
    if x is None:
        return "—"
    if isinstance(x, bool):
        return "yes" if x else "no"
    if isinstance(x, float):
        return f"{x:.6g}" if math.isfinite(x) else str(x)
    return str(x)


def _cell(x: Any) -> str:
    if isinstance(x, Mapping):
        return f"<td>{_value(x) if x else 'none'}</td>"
    if isinstance(x, list | tuple) and x and not _all_scalar(x):
        return f"<td>{_value(x)}</td>"
    if isinstance(x, list | tuple):
        return f"<td>{escape(', '.join(_scalar(v) for v in x))}</td>"
    num = isinstance(x, int | float) and not isinstance(x, bool)
    return f'<td class="num">{escape(_scalar(x))}</td>' if num else f"<td>{escape(_scalar(x))}</td>"


def _all_scalar(x: Any) -> bool:
    values = x.values() if isinstance(x, Mapping) else x
    return not any(isinstance(v, Mapping | list | tuple) for v in values)


def table(heads: Sequence[str], rows: Sequence[Sequence[Any]]) -> str:
    head = "".join(f"<th>{escape(h)}</th>" for h in heads)
    body = "".join("<tr>" + "".join(_cell(c) for c in row) + "</tr>\n" for row in rows)
    return f"<table>\n<tr>{head}</tr>\n{body}</table>\n"


def kv_table(rows: Sequence[tuple[str, Any]]) -> str:
    """Rows of a name and its value, without a header."""
    body = "".join(f"<tr><th>{escape(k)}</th>{_cell(v)}</tr>\n" for k, v in rows)
    return f"<table>\n{body}</table>\n" if rows else ""


def _records_table(records: Sequence[Mapping[str, Any]]) -> str:
    """A list of tables as one table: a column per (dotted) key any of them has."""
    flat = [flatten(r) for r in records]
    heads = list(dict.fromkeys(k for f in flat for k in f))
    return table(heads, [[f.get(k) for k in heads] for f in flat])


def bullet_list(items: Sequence[Any]) -> str:
    return "<ul>" + "".join(f"<li>{escape(_scalar(i))}</li>" for i in items) + "</ul>\n"


def _value(x: Any) -> str:
    """Any summary value as HTML: a table as rows of dotted keys, a list of tables as one
    table, a list of values as a list, a value as text."""
    if isinstance(x, Mapping):
        return kv_table(list(flatten(x).items())) if x else "<p>empty</p>"
    if isinstance(x, list | tuple) and x and all(isinstance(v, Mapping) for v in x):
        return _records_table(x)
    if isinstance(x, list | tuple):
        return bullet_list(x) if x else "<p>none</p>"
    return f"<p>{escape(_scalar(x))}</p>"
