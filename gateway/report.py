"""Run records: per-cycle signals, the metrics summary, the summary table and the figures.

The same record serves `hil-gateway simulate` and the CAN runs, so their files compare
column for column. Signals are SI; columns are named like the code (``w_m``, ``psi_ref``).
"""

from __future__ import annotations

import csv
import json
import math
import os
from collections.abc import Iterable, Mapping
from pathlib import Path
from typing import Any

import numpy as np

#: Metric windows of the paper scenario, s: start-up and first load, load steps, field weakening.
DEFAULT_WINDOWS: tuple[tuple[float, float], ...] = ((0.0, 0.5), (0.5, 1.5), (1.5, math.inf))

class Record:
    """Per-cycle signals, appended row by row, read back as numpy columns.

    ``row_type`` is a :class:`typing.NamedTuple` class (e.g. :class:`gateway.cycle.CycleRow`):
    its fields are the columns, and :meth:`append` takes only rows of that type.
    """

    def __init__(self, row_type: type[tuple]) -> None:
        fields = getattr(row_type, "_fields", None)
        if not fields:
            raise TypeError(f"{row_type!r} is not a NamedTuple class")
        self.row_type = row_type
        self.columns: tuple[str, ...] = tuple(fields)
        self._rows: list[tuple[float, ...]] = []

    def append(self, row: tuple) -> None:
        """Add one row; a row of another type (other columns) raises TypeError."""
        if type(row) is not self.row_type:
            raise TypeError(f"a {type(row).__name__} row in a record of "
                            f"{self.row_type.__name__} rows")
        self._rows.append(row)

    def __len__(self) -> int:
        return len(self._rows)

    def arrays(self) -> dict[str, np.ndarray]:
        """The columns as float arrays."""
        data = np.asarray(self._rows, dtype=float).reshape(len(self._rows), len(self.columns))
        return {name: data[:, j] for j, name in enumerate(self.columns)}

    def write_csv(self, path: Path) -> None:
        """Write the signals as CSV with a header row; floats with full precision (repr)."""
        with path.open("w", newline="") as f:
            w = csv.writer(f)
            w.writerow(self.columns)
            for row in self._rows:
                w.writerow([repr(float(x)) for x in row])


def read_csv(path: Path) -> dict[str, np.ndarray]:
    """Read a record written by :meth:`Record.write_csv`."""
    with path.open(newline="") as f:
        r = csv.reader(f)
        header = next(r)
        rows = [[float(x) for x in row] for row in r]
    data = np.asarray(rows, dtype=float).reshape(len(rows), len(header))
    return {name: data[:, j] for j, name in enumerate(header)}


def _error_stats(
    t: np.ndarray, e: np.ndarray, windows: Iterable[tuple[float, float]]
) -> dict[str, Any]:
    """max |e|, RMS, final value, and the same per window."""
    out: dict[str, Any] = {
        "max": float(np.max(np.abs(e))) if e.size else math.nan,
        "rms": float(np.sqrt(np.mean(e * e))) if e.size else math.nan,
        "final": float(e[-1]) if e.size else math.nan,
        "windows": [],
    }
    for lo, hi in windows:
        sel = (t >= lo) & (t < hi)
        if not np.any(sel):
            continue
        ew = e[sel]
        out["windows"].append({
            "from": lo,
            "to": float(t[sel][-1]) if math.isinf(hi) else hi,
            "max": float(np.max(np.abs(ew))),
            "rms": float(np.sqrt(np.mean(ew * ew))),
        })
    return out


def metrics(
    sig: Mapping[str, np.ndarray], windows: Iterable[tuple[float, float]] = DEFAULT_WINDOWS
) -> dict[str, Any]:
    """The summary metrics (SI units).

    speed_error = ω − ω*, flux_error = |ψ_r| − ψ*, estimation_error = ω̂ − ω, each with
    max |·|, RMS, final value and per-window max/RMS; peak_current = max |i_s|,
    peak_voltage = max |u_s| (average over a period).
    """
    windows = tuple(windows)
    t = sig["t"]
    return {
        "speed_error": _error_stats(t, sig["w_m"] - sig["w_ref"], windows),
        "flux_error": _error_stats(t, sig["psi_r_mod"] - sig["psi_ref"], windows),
        "estimation_error": _error_stats(t, sig["w_hat"] - sig["w_m"], windows),
        "peak_current": float(np.max(np.hypot(sig["i_sa"], sig["i_sb"]))),
        "peak_voltage": float(np.max(np.hypot(sig["u_sa"], sig["u_sb"]))),
    }


def _fmt(x: float, unit: str) -> str:
    """A number with an SI prefix that keeps three significant digits."""
    if not math.isfinite(x):
        return f"{x} {unit}"
    ax = abs(x)
    for scale, prefix in ((1.0, ""), (1e-3, "m"), (1e-6, "µ")):
        if ax >= scale or scale == 1e-6:
            return f"{x / scale:.3g} {prefix}{unit}"
    return f"{x:.3g} {unit}"  # pragma: no cover


def summary_table(summary: Mapping[str, Any]) -> str:
    """A plain-text table of the metrics: one row per error, columns per window."""
    rows = (("speed error ω−ω*", "speed_error", "rad/s"),
            ("flux error |ψr|−ψ*", "flux_error", "Wb"),
            ("estimation error ω̂−ω", "estimation_error", "rad/s"))
    win = summary["speed_error"]["windows"]
    heads = ["", "max", "rms", "final"] + [
        f"max [{w['from']:g},{w['to']:g})" for w in win
    ]
    lines = [heads]
    for label, key, unit in rows:
        m = summary[key]
        cells = [label, _fmt(m["max"], unit), _fmt(m["rms"], unit), _fmt(m["final"], unit)]
        cells += [_fmt(w["max"], unit) for w in m["windows"]]
        lines.append(cells)
    widths = [max(len(r[j]) for r in lines if j < len(r)) for j in range(len(heads))]
    text = "\n".join(
        "  ".join(c.ljust(widths[j]) if j == 0 else c.rjust(widths[j]) for j, c in enumerate(r))
        for r in lines
    )
    text += (f"\npeak current {summary['peak_current']:.3g} A, "
             f"peak voltage {summary['peak_voltage']:.3g} V")
    return text


def write_summary(path: Path, summary: Mapping[str, Any]) -> None:
    """summary.json, pretty-printed, NaN/inf written as null, replaced atomically."""

    def clean(x: Any) -> Any:
        if isinstance(x, float) and not math.isfinite(x):
            return None
        if isinstance(x, Mapping):
            return {k: clean(v) for k, v in x.items()}
        if isinstance(x, list | tuple):
            return [clean(v) for v in x]
        return x

    text = json.dumps(clean(summary), indent=2, sort_keys=False) + "\n"
    tmp = path.with_name(path.name + ".tmp")
    try:
        tmp.write_text(text)
        os.replace(tmp, path)  # readers see the old summary or the new one, never half
    except OSError:
        tmp.unlink(missing_ok=True)
        raise


def plot_figures(sig: Mapping[str, np.ndarray], out_dir: Path, title: str = "") -> list[Path]:
    """The paper's Fig. 1 (references and load) and Fig. 2 (errors), and the currents/voltages.

    Returns the PNG paths written, or [] when matplotlib is not installed.
    """
    try:
        import matplotlib

        matplotlib.use("Agg")
        import matplotlib.pyplot as plt
    except ImportError:
        return []
    t = sig["t"]
    written: list[Path] = []

    fig, ax = plt.subplots(3, 1, sharex=True, figsize=(7, 7), layout="constrained")
    ax[0].plot(t, sig["w_ref"], label="ω* reference")
    ax[0].plot(t, sig["w_m"], "--", label="ω motor")
    ax[0].set_ylabel("speed [rad/s]")
    ax[1].plot(t, sig["psi_ref"], label="ψ* reference")
    ax[1].plot(t, sig["psi_r_mod"], "--", label="|ψr| motor")
    ax[1].set_ylabel("rotor flux [Wb]")
    ax[2].plot(t, sig["T_L"], color="C3", label="T_L load")
    ax[2].set_ylabel("load torque [N·m]")
    ax[2].set_xlabel("time [s]")
    for a in ax:
        a.grid(True, alpha=0.3)
        a.legend(loc="best", fontsize="small")
    fig.suptitle(f"Fig. 1 — speed and flux references, applied load {title}".strip())
    p = out_dir / "fig1_references.png"
    fig.savefig(p, dpi=110)
    plt.close(fig)
    written.append(p)

    fig, ax = plt.subplots(3, 1, sharex=True, figsize=(7, 7), layout="constrained")
    ax[0].plot(t, sig["w_m"] - sig["w_ref"])
    ax[0].set_ylabel("ω − ω* [rad/s]")
    ax[1].plot(t, sig["psi_r_mod"] - sig["psi_ref"])
    ax[1].set_ylabel("|ψr| − ψ* [Wb]")
    ax[2].plot(t, sig["w_hat"] - sig["w_m"])
    ax[2].set_ylabel("ω̂ − ω [rad/s]")
    ax[2].set_xlabel("time [s]")
    for a in ax:
        a.grid(True, alpha=0.3)
    fig.suptitle(f"Fig. 2 — tracking and estimation errors {title}".strip())
    p = out_dir / "fig2_errors.png"
    fig.savefig(p, dpi=110)
    plt.close(fig)
    written.append(p)

    fig, ax = plt.subplots(2, 1, sharex=True, figsize=(7, 5), layout="constrained")
    ax[0].plot(t, sig["i_sa"], label="i_sa")
    ax[0].plot(t, sig["i_sb"], label="i_sb")
    ax[0].set_ylabel("current [A]")
    ax[1].plot(t, sig["u_sa"], label="u_sa")
    ax[1].plot(t, sig["u_sb"], label="u_sb")
    ax[1].set_ylabel("voltage [V]")
    ax[1].set_xlabel("time [s]")
    for a in ax:
        a.grid(True, alpha=0.3)
        a.legend(loc="upper right", fontsize="small")
    fig.suptitle(f"Stator currents and average voltages {title}".strip())
    p = out_dir / "fig3_currents_voltages.png"
    fig.savefig(p, dpi=110)
    plt.close(fig)
    written.append(p)
    return written
