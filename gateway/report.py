"""Run records: per-cycle signals, the metrics summary, the summary table, the comparison
of runs. The run's figures are :mod:`gateway.figures` (their names are re-exported here).

The same record serves `hil-gateway simulate` and the CAN runs, so their files compare
column for column. Signals are SI; columns are named like the code (``w_m``, ``psi_ref``).
"""

from __future__ import annotations

import csv
import json
import math
from collections.abc import Iterable, Mapping
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from dbc.modes import DriveMode
from gateway.atomicfile import write_text_atomic
from gateway.dotted import flatten
from gateway.figures import DRAWN_ELSEWHERE as DRAWN_ELSEWHERE
from gateway.figures import FIG4_MAX as FIG4_MAX
from gateway.figures import controller_signals
from gateway.figures import fig3_limits_text as fig3_limits_text
from gateway.figures import limits_for as limits_for
from gateway.figures import plot_figures as plot_figures
from gateway.figures import zoom_windows as zoom_windows

#: Metric windows of the paper scenario, s: start-up and first load, load steps, field weakening.
DEFAULT_WINDOWS: tuple[tuple[float, float], ...] = ((0.0, 0.5), (0.5, 1.5), (1.5, math.inf))

#: Memory a record holds per value while a run goes on: a Python float (24 bytes) and its
#: pointer in the row (8), and the float64 copy the metrics and figures make (8); per row
#: also the row tuple's header.
BYTES_PER_VALUE = 40
BYTES_PER_ROW = 56
#: The record size above which a run must be asked for with --allow-long, bytes.
RECORD_LIMIT = 1 << 30


def record_bytes(n_rows: int, n_columns: int) -> int:
    """Estimated memory of a record of ``n_rows`` rows of ``n_columns`` floats, bytes."""
    return int(n_rows) * (n_columns * BYTES_PER_VALUE + BYTES_PER_ROW)


def check_record_size(n_rows: int, n_columns: int, allow_long: bool, what: str) -> None:
    """Refuse (:class:`UserError`) a run whose record would exceed :data:`RECORD_LIMIT`
    unless ``allow_long``; ``what`` describes the run ("600 s at 1ms")."""
    size = record_bytes(n_rows, n_columns)
    if size > RECORD_LIMIT and not allow_long:
        from gateway.errors import UserError

        raise UserError(
            f"{what} is {n_rows:.4g} cycles; their record ({n_columns} columns, about "
            f"{n_columns * BYTES_PER_VALUE + BYTES_PER_ROW} bytes a cycle) would need about "
            f"{size / (1 << 30):.3g} GiB of memory, above the {RECORD_LIMIT / (1 << 30):g} GiB "
            "limit: shorten --duration, lengthen --period, or pass --allow-long to run it "
            "anyway")

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
        #: what the controller identified during the run (``--identify``), for summary.json
        self.identification: dict[str, object] | None = None
        #: a simulation with bus faults: the account of its PDO link
        #: (:class:`gateway.faultlink.LinkAccount`)
        self.link: Any = None

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


def write_columns_csv(path: Path, sig: Mapping[str, np.ndarray]) -> None:
    """Write columns (e.g. from :func:`read_csv`, amended) like :meth:`Record.write_csv`:
    the csv module's header, then the rows joined directly (a float's repr needs no quoting:
    the same bytes, a third faster)."""
    names = list(sig)
    data = np.column_stack([np.asarray(sig[n], dtype=float) for n in names])
    with path.open("w", newline="") as f:
        csv.writer(f).writerow(names)
        f.writelines([",".join(map(repr, row)) + "\r\n" for row in data.tolist()])


def read_csv(path: Path) -> dict[str, np.ndarray]:
    """Read a record written by :meth:`Record.write_csv`."""
    with path.open(newline="") as f:
        r = csv.reader(f)
        header = next(r)
        rows = []
        for n, row in enumerate(r, start=2):
            try:
                if len(row) != len(header):
                    raise ValueError(f"{len(row)} values, the header has {len(header)}")
                rows.append([float(x) for x in row])
            except ValueError as exc:
                raise ValueError(f"{path}, line {n}: {exc} (a truncated or damaged file?)"
                                 ) from None
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
    for w in windows:
        lo, hi = w[0], w[1]
        sel = (t >= lo) & (t < hi)
        if not np.any(sel):
            continue  # a window the run did not reach is not reported
        ew = e[sel]
        entry = {
            "from": lo,
            "to": float(t[sel][-1]) if math.isinf(hi) or hi > t[-1] else hi,
            "max": float(np.max(np.abs(ew))),
            "rms": float(np.sqrt(np.mean(ew * ew))),
        }
        if len(w) > 2:
            entry["label"] = w[2]
        out["windows"].append(entry)
    return out


def metrics(
    sig: Mapping[str, np.ndarray], windows: Iterable[tuple] = DEFAULT_WINDOWS
) -> dict[str, Any]:
    """The summary metrics (SI units).

    speed_error = ω − ω*, flux_error = |ψ_r| − ψ*, estimation_error = ω̂ − ω, each with
    max |·|, RMS, final value and per-window max/RMS (flux_error only where the run has a
    flux, estimation_error only for a controller that logs a speed estimate ``w_hat``);
    peak_current = max |i_s|, peak_voltage = max |u_s| (average over a period).
    ``windows``: (from, to) or (from, to, label) in s, e.g. :func:`profile_windows`;
    those the run did not reach are left out.
    """
    windows = tuple(windows)
    t = sig["t"]
    out = {"speed_error": _error_stats(t, sig["w_m"] - sig["w_ref"], windows)}
    if not np.all(np.isnan(sig["psi_r_mod"])):  # a standard drive reports no flux
        out["flux_error"] = _error_stats(t, sig["psi_r_mod"] - sig["psi_ref"], windows)
    if "w_hat" in sig:  # a controller with a speed estimate (the paper's)
        out["estimation_error"] = _error_stats(t, sig["w_hat"] - sig["w_m"], windows)
    out["peak_current"] = float(np.max(np.hypot(sig["i_sa"], sig["i_sb"])))
    out["peak_voltage"] = float(np.max(np.hypot(sig["u_sa"], sig["u_sb"])))
    return out


def profile_windows(profile: Any, spec: str | None = None) -> tuple[tuple[float, float, str], ...]:
    """Metric windows (from, to, label), s, fitted to ``profile`` (docs/outputs.md).

    ``spec`` None or "auto": one window per segment of the profile — from 0, and from the
    start of each transition of ω*, ψ* or T_L (transitions that start together share one)
    to the next, the last to the end; labelled by what starts it ("speed 0 → 100 rad/s").
    "paper": the paper scenario's [0, 0.5), [0.5, 1.5), [1.5, end). "none": no windows.
    Otherwise comma-separated boundaries in s, e.g. "0.5,1.5".
    """
    from gateway.errors import UserError

    duration = float(profile.duration)
    if spec in (None, "", "auto"):
        starts: dict[float, list[str]] = {}
        for sp in profile.set_points():
            if sp.initial or sp.t_start >= duration:
                continue
            what = f"{sp.signal} {sp.start:g} → {sp.end:g} {sp.unit}"
            starts.setdefault(round(sp.t_start, 9), []).append(what)
        bounds = sorted(t for t in starts if t > 0.0)
        labels = ["start" + (": " + ", ".join(starts[0.0]) if 0.0 in starts else "")]
        labels += [", ".join(starts[t]) for t in bounds]
    elif spec == "paper":
        return tuple((lo, hi, f"paper [{lo:g}, {hi:g})") for lo, hi in DEFAULT_WINDOWS)
    elif spec == "none":
        return ()
    else:
        try:
            bounds = sorted({float(x) for x in spec.split(",") if x.strip()})
        except ValueError:
            bounds = [math.nan]
        if not bounds or not all(0.0 < b < duration for b in bounds):
            raise UserError(f"--windows {spec!r}: give 'auto', 'paper', 'none' or "
                            f"comma-separated times in s inside (0, {duration:g}), e.g. "
                            "0.5,1.5")
        labels = ["start"] + [f"from {b:g} s" for b in bounds]
    edges = [0.0, *bounds, math.inf]
    return tuple((edges[j], edges[j + 1], labels[j]) for j in range(len(edges) - 1))


def _fmt(x: float, unit: str) -> str:
    """A number with an SI prefix that keeps three significant digits."""
    if not math.isfinite(x):
        return f"{x} {unit}"
    ax = abs(x)
    for scale, prefix in ((1.0, ""), (1e-3, "m"), (1e-6, "µ")):
        if ax >= scale or scale == 1e-6:
            return f"{x / scale:.3g} {prefix}{unit}"
    return f"{x:.3g} {unit}"  # pragma: no cover


#: The public name of the SI formatter: a number with a prefix keeping three digits.
format_si = _fmt


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
        if key not in summary:
            continue
        m = summary[key]
        cells = [label, _fmt(m["max"], unit), _fmt(m["rms"], unit), _fmt(m["final"], unit)]
        cells += [_fmt(w["max"], unit) for w in m["windows"]]
        lines.append(cells)
    widths = [max(len(r[j]) for r in lines if j < len(r)) for j in range(len(heads))]
    text = "\n".join(
        "  ".join(c.ljust(widths[j]) if j == 0 else c.rjust(widths[j]) for j, c in enumerate(r))
        for r in lines
    )
    labelled = [w for w in win if w.get("label")]
    if labelled:
        text += "\nwindows: " + "; ".join(f"[{w['from']:g},{w['to']:g}) {w['label']}"
                                          for w in labelled)
    text += (f"\npeak current {summary['peak_current']:.3g} A, "
             f"peak voltage {summary['peak_voltage']:.3g} V")
    if "truth" in summary:
        text += f"\ntruth (ω, |ψr|): {summary['truth']}"
    ident = identification_line(summary.get("identification"))
    if ident:
        text += "\n" + ident
    gain = speed_gain_line(summary.get("identification"))
    if gain:
        text += "\n" + gain
    q = summary.get("quantisation")
    if q and q.get("applied"):
        sig = q["signals"]
        parts = [f"{label} {_fmt(sig[name]['lsb'], sig[name]['unit'])}"
                 for label, name in (("i", "i_sa"), ("u", "u_sa"), ("ω0", "w_0"),
                                     ("ε0", "eps_0"), ("ω (TPDO3)", "w_m"),
                                     ("T*", "target_torque"), ("ω*", "target_velocity"),
                                     ("θ*", "target_position"),
                                     ("ω (0x606C)", "velocity_actual"),
                                     ("T (0x6077)", "torque_actual"),
                                     ("ψr (TPDO3)", "psi_ra")) if name in sig]
        text += ("\nbus resolution (1 LSB): " + ", ".join(parts)
                 + f" ({q.get('source', 'dbc/drive.dbc')})")
    elif q:
        text += f"\nbus resolution: not applied ({q.get('reason', '--no-quantize')})"
    return text


def identification_line(ident: Mapping[str, Any] | None) -> str:
    """The summary's line for an identification (``--identify``, or the commissioning's
    standstill and rotating tests), or ""."""
    if not ident:
        return ""
    if ident.get("test") == "standstill":  # the commissioning test (--controller identify)
        if not ident.get("ok"):
            return f"standstill test: no result ({ident.get('reason', '')})"
        v = ident["values"]
        return (f"standstill test ({ident['samples']} samples): R_s {v['R_s']['value']:.4g} Ω, "
                f"α {v['alpha']['value']:.4g} 1/s, σ {v['sigma']['value']:.4g} H, "
                f"offsets {1e3 * v['offset_a']['value']:.2f}/{1e3 * v['offset_b']['value']:.2f}"
                " mA (hil-gateway identify writes them as a motor file)")
    if ident.get("test") == "rotating":  # --controller identify-rotating
        if not ident.get("ok"):
            return f"rotating test: no result ({ident.get('reason', '')})"
        v = ident["values"]
        return (f"rotating test ({ident['samples']} samples): J {v['J']['value']:.4g} kg·m² "
                f"± {v['J']['std']:.2g}, friction {v['friction_viscous']['value']:.3g} N·m·s "
                f"viscous, {v['friction_coulomb']['value']:.3g} N·m Coulomb")
    inertia = inertia_line(ident.get("inertia"))
    if "accepted" not in ident and "reason" not in ident:  # the inertia tracker alone
        return inertia
    inertia = f"; {inertia}" if inertia else ""
    noise = ""
    if ident.get("mismatch_gain", 1.0) < 1.0:
        noise = (f"; the current sensors' noise ({1e3 * ident['mismatch_rms']:.2g} mA rms "
                 f"against the model at standstill) weighted down to "
                 f"{ident['mismatch_gain']:.2g} in the flux estimate")
    if ident.get("accepted"):
        sensors = ""
        if ident.get("sensors_corrected"):
            sensors = (f"; current sensors corrected: offsets "
                       f"{1e3 * ident['offset_a']:.2f}/{1e3 * ident['offset_b']:.2f} mA, "
                       f"phase b's gain {ident['gain_b']:.4f}")
        if ident.get("u_dead"):
            sensors += (f"; the inverter's dead time corrected: {ident['u_dead']:.3g} V "
                        "(the drive reports the voltage it was told)")
        return (f"identified at standstill ({ident['samples']} samples): R_s "
                f"{ident['R_s']:.4g} Ω, R_r {ident['R_r']:.4g} Ω (α {ident['alpha']:.4g} 1/s)"
                f"{sensors}, used from the end of the magnetisation{noise}{inertia}")
    return (f"standstill identification not applied: {ident.get('reason', '')}"
            f"{noise}{inertia}")


def speed_gain_line(ident: Mapping[str, Any] | None) -> str:
    """The kω the full-order law used where the period bounded it
    (``identification.speed_gain`` of summary.json), or ""."""
    found = (ident or {}).get("speed_gain")
    if not found:
        return ""
    return (f"speed gain kω {found['applied']:.4g} 1/s (asked {found['k_w']:.4g}: kω·T kept "
            f"≤ {found['k_w_T_max']:g} at T = {1e3 * found['T']:g} ms, where the sampled speed "
            "loop through the current loop stays stable; --k-w-t-max inf: the asked kω)")


def inertia_line(found: Mapping[str, Any] | None) -> str:
    """What the inertia tracker found (``identification.inertia`` of summary.json), or ""."""
    if not found:
        return ""
    stopped = (", readings stopped after a coast of lost samples" if found.get("stopped")
               else "")
    load = (f"; load observed, {found['T_L_observed']:.3g} N·m at the end"
            if "T_L_observed" in found else "")
    if found.get("load_rejected_at") is not None:
        load = (f"; the told load rejected at {found['load_rejected_at']:.3f} s, a further "
                f"{found['T_L_observed']:.3g} N·m observed at the end")
    elif found.get("load_watch_stopped_at") is not None:
        load = (f"; the told load no longer watched from {found['load_watch_stopped_at']:.3f}"
                " s (a sample lost at its step)")
    if found.get("applied"):
        return (f"J tracked on line: {found['J']:.4g} kg·m² from {found['at']:.3f} s "
                f"(motor file {found['J_file']:.4g}{stopped}){load}")
    if "reason" in found:
        return f"the motor file's J {found['J_file']:.4g} kg·m² ({found['reason']})"
    return (f"the motor file's J {found['J_file']:.4g} kg·m² kept (on line J_file/J = "
            f"{found['ratio']:.4f} ± {found['ratio_std']:.4f}{stopped}){load}")


#: The bus signals the loop uses, by message (the setpoint message depends on the frame).
_USED_MESSAGES = ("RPDO1", "RPDO2", "RPDO2_AB", "RPDO3", "TPDO1", "TPDO2", "TPDO3")


def quantisation(applied: bool = True, setpoint_message: str | None = None,
                 reason: str = "", dbc: Path | None = None,
                 messages: tuple[str, ...] = _USED_MESSAGES) -> dict[str, Any]:
    """The resolution of each bus signal, from the drive's DBC (``dbc``; default
    ``dbc/drive.dbc``, the emulator's) and its ``messages``: for summary.json.

    ``signals``: name → message, lsb (one raw unit in ``unit``), unit, bits, signed, min,
    max. Integer fields (controlword, statusword, SYNC counter) are left out. ``applied``:
    whether the run's signals went through it (`simulate --no-quantize` or continuous
    time: false, ``reason`` says why). ``source``: the DBC's file name.
    """
    from dbc import DBC_PATH, parse_dbc
    from dbc.codec import INT_SIGNALS

    skip = {"RPDO2", "RPDO2_AB"} - {setpoint_message} if setpoint_message else set()
    parsed = parse_dbc(dbc or DBC_PATH)[0]  # the codec's parse, kept on disk: no cantools
    out: dict[str, Any] = {}
    for name in messages:
        if name in skip or name not in parsed:
            continue
        for sg in parsed[name].signals:
            if sg.name in INT_SIGNALS:
                continue
            raw_lo = -(1 << (sg.bits - 1)) if sg.signed else 0
            raw_hi = (1 << (sg.bits - 1)) - 1 if sg.signed else (1 << sg.bits) - 1
            out[sg.name] = {"message": name, "lsb": sg.factor,
                            "unit": sg.unit.replace("N.m", "N·m"),
                            "bits": sg.bits, "signed": sg.signed,
                            "min": raw_lo * sg.factor, "max": raw_hi * sg.factor}
    source = "dbc/drive.dbc" if dbc is None or Path(dbc) == DBC_PATH else Path(dbc).name
    q: dict[str, Any] = {"applied": bool(applied), "source": source}
    if not applied and reason:
        q["reason"] = reason
    q["signals"] = out
    return q


#: summary["truth"]: where ω and |ψr| of the error metrics come from.
TRUTH_FULL = "emulator, full resolution"
TRUTH_MODEL = "simulated motor state, full resolution"
TRUTH_TPDO3 = "TPDO3, INT16 (ω to 0.03125 rad/s, ψr to 0.1 mWb)"



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
    write_text_atomic(path, text)  # readers see the old summary or the new one, never half


def title_for(config: Mapping[str, Any]) -> str:
    """One line naming the whole configuration of a run, from summary["configuration"]:
    the controller (the paper's: law, flux source and estimator), drive mode, period,
    delay, setpoint frame, and how it ran (simulate, or over CAN with transport and
    timing)."""
    def period_text(p: Any) -> str:
        if p == "continuous" or p is None:
            return "continuous time"
        p = float(p)
        return f"T = {p * 1e3:g} ms" if p >= 1e-3 else f"T = {p * 1e6:g} µs"

    flux = config.get("flux", "?")
    flux_text = ("true flux" if flux == "true"
                 else f"estimated flux ({config.get('estimator', 'open-loop')})")
    name = (config.get("controller") or {}).get("name", "paper")
    head = ([f"{config.get('law', '?')} law", flux_text] if name == "paper"
            else [f"controller {name}"])
    parts = [*head, f"{config.get('drive_mode', '?')} drive", period_text(config.get("period"))]
    if config.get("period") not in (None, "continuous"):
        parts.append(f"delay {config.get('delay', '?')}")
        if config.get("drive_mode") not in {m.value for m in DriveMode if m.standard}:
            parts.append(f"{config.get('setpoint_frame', '?')} setpoints")
    if config.get("command") == "simulate":
        how = "simulate" + ("" if config.get("period") == "continuous" else
                            (", INT16 bus signals" if config.get("quantize", True)
                             else ", unquantised"))
    else:
        bus = str(config.get("bus", "")).split(":")[0] or "CAN"
        how = f"over CANopen ({bus}, {config.get('timing', '?')})"
    return ", ".join(parts) + " — " + how


# --------------------------------------------------------------------------- comparison


@dataclass
class Run:
    """A finished run read back from its directory: ``summary.json`` and ``signals.csv``."""

    path: Path
    summary: dict[str, Any]
    signals: dict[str, np.ndarray]

    @property
    def name(self) -> str:
        return self.path.name or str(self.path)


def load_summary(path: Path) -> dict[str, Any]:
    """A run directory's ``summary.json``; :class:`UserError` naming what is missing or
    damaged."""
    from gateway.errors import UserError

    if not (path / "summary.json").is_file():
        raise UserError(f"{str(path)!r} is not a run directory (no summary.json): give "
                        "directories written by simulate, sim or run")
    try:
        summary = json.loads((path / "summary.json").read_text(encoding="utf-8"))
    except (OSError, ValueError) as exc:
        raise UserError(f"{str(path)!r}: cannot read the run's files ({exc})") from exc
    if not isinstance(summary, dict):
        raise UserError(f"{str(path / 'summary.json')!r} is not a run's summary (a JSON "
                        "table is expected)")
    return summary


def load_run(path: Path) -> Run:
    """Read a run directory; :class:`UserError` naming what is missing."""
    from gateway.errors import UserError

    summary = load_summary(path)
    try:
        sig = read_csv(path / "signals.csv") if (path / "signals.csv").is_file() else {}
    except (OSError, ValueError, StopIteration) as exc:
        raise UserError(f"{str(path)!r}: cannot read the run's files ({exc})") from exc
    return Run(path, summary, sig)


def config_differences(runs: list[Run]) -> dict[str, list[Any]]:
    """The configuration keys (flattened, e.g. ``gains.k_w``) that every run has and whose
    values differ."""
    flats = [flatten(r.summary.get("configuration", {})) for r in runs]
    keys = sorted(set.intersection(*(set(f) for f in flats)))
    return {k: [f.get(k) for f in flats] for k in keys
            if len({json.dumps(f.get(k), sort_keys=True) for f in flats}) > 1}


def config_only_in_some(runs: list[Run]) -> list[str]:
    """Top-level configuration keys that only some runs have (simulate vs bus runs)."""
    keys = [set(r.summary.get("configuration", {})) for r in runs]
    return sorted(set.union(*keys) - set.intersection(*keys))


#: The metrics runs are compared by, side by side: label, unit, summary key, sub-keys.
COMPARED_METRICS: tuple[tuple[str, str, str, tuple[str, ...]], ...] = (
    ("speed error max", "rad/s", "speed_error", ("max",)),
    ("speed error rms", "rad/s", "speed_error", ("rms",)),
    ("speed error final", "rad/s", "speed_error", ("final",)),
    ("flux error max", "Wb", "flux_error", ("max",)),
    ("flux error rms", "Wb", "flux_error", ("rms",)),
    ("estimation error max", "rad/s", "estimation_error", ("max",)),
    ("estimation error rms", "rad/s", "estimation_error", ("rms",)),
    ("peak current", "A", "peak_current", ()),
    ("peak voltage", "V", "peak_voltage", ()),
)


def compare_table(runs: list[Run]) -> str:
    """Errors side by side (one column per run), each controller's own logged signals (last
    value and RMS; "—" for a run whose controller does not log it), and the configuration
    keys that differ."""
    heads = ["", *(r.name for r in runs)]
    lines = [heads]
    for label, unit, key, sub in COMPARED_METRICS:
        cells = [label]
        for r in runs:
            v: Any = r.summary.get(key)
            for k in sub:
                v = v.get(k) if isinstance(v, Mapping) else None
            cells.append("—" if v is None else _fmt(float(v), unit))
        lines.append(cells)
    win_sets = [tuple((w["from"], w.get("label", "")) for w in
                      r.summary.get("speed_error", {}).get("windows", [])) for r in runs]
    if win_sets and all(ws == win_sets[0] for ws in win_sets) and win_sets[0]:
        for j, (lo, _) in enumerate(win_sets[0]):
            cells = [f"speed max from {lo:g} s"]
            cells += [_fmt(r.summary["speed_error"]["windows"][j]["max"], "rad/s")
                      for r in runs]
            lines.append(cells)
    own = [n for r in runs for n in controller_signals(r.signals or {})]
    for name in dict.fromkeys(own):  # each controller's own signals: the last value and RMS
        cells = [f"{name} final / rms"]
        for r in runs:
            x = (r.signals or {}).get(name)
            x = None if x is None else x[np.isfinite(x)]
            cells.append("—" if x is None or not x.size else
                         f"{x[-1]:.4g} / {float(np.sqrt(np.mean(x * x))):.4g}")
        lines.append(cells)
    widths = [max(len(r[j]) for r in lines) for j in range(len(heads))]
    text = "\n".join("  ".join(c.ljust(widths[j]) if j == 0 else c.rjust(widths[j])
                               for j, c in enumerate(r)) for r in lines)
    diffs = config_differences(runs)
    if diffs:
        text += "\nconfiguration differences:"
        for k, vals in diffs.items():
            text += f"\n  {k}: " + " | ".join("—" if v is None else str(v) for v in vals)
    else:
        text += "\nsame configuration"
    some = config_only_in_some(runs)
    if some:
        text += f"\nnot compared (only in some runs): {', '.join(some)}"
    return text


def profile_name(source: Any) -> str:
    """A run's reference profile, compactly: the built-in one ("<embedded>") is "paper", a
    file its stem ("profiles/quick.toml" → "quick"); "" when the summary does not say."""
    if not source:
        return ""
    text = str(source)
    if text == "<embedded>":
        return "paper"
    return text if text.startswith("<") else (Path(text).stem or text)


def compare_labels(runs: list[Run]) -> list[str]:
    """The legend entry of each run in the comparison figure: its name, then the reference
    profile it ran and the configuration keys that differ (at most three), e.g.
    "A (paper, law current-fed)". Two different profile files of the same name are named
    by their whole paths."""
    diffs = config_differences(runs)
    shown = [k for k in diffs if not k.endswith(("bus", "profile", "duration"))][:3]
    sources = [r.summary.get("configuration", {}).get("profile") for r in runs]
    names = [profile_name(s) for s in sources]
    labels = []
    for j, r in enumerate(runs):
        clash = any(n == names[j] and s != sources[j] for n, s in zip(names, sources, strict=True))
        extra = [str(sources[j]) if clash else names[j]] if names[j] else []
        extra += [f"{k.split('.')[-1]} {diffs[k][j]}" for k in shown]
        labels.append(r.name + (f" ({', '.join(extra)})" if extra else ""))
    return labels


def plot_compare(runs: list[Run], out: Path) -> Path | None:
    """Speed and flux errors of every run overlaid, labelled by run, by the reference
    profile it ran and by the configuration keys that differ (:func:`compare_labels`); None
    when matplotlib is not installed."""
    try:
        import matplotlib

        matplotlib.use("Agg")
        import matplotlib.pyplot as plt
    except ImportError:
        return None
    diffs = config_differences(runs)
    labels = compare_labels(runs)
    fig, ax = plt.subplots(2, 1, sharex=True, figsize=(9, 6.5), layout="constrained")
    for j, r in enumerate(runs):
        sig = r.signals
        if not sig or "w_m" not in sig or not np.any(np.isfinite(sig["w_m"])):
            continue
        label = labels[j]
        style = ("-", "--", ":", "-.")[j % 4]  # identical runs stay visible
        ax[0].plot(sig["t"], sig["w_m"] - sig["w_ref"], style, lw=1, label=label)
        ax[1].plot(sig["t"], sig["psi_r_mod"] - sig["psi_ref"], style, lw=1, label=label)
    ax[0].set_ylabel("speed error ω − ω* [rad/s]")
    ax[1].set_ylabel("flux error |ψr| − ψ* [Wb]")
    ax[1].set_xlabel("time [s]")
    for a in ax:
        a.grid(True, alpha=0.3)
    ax[0].legend(loc="best", fontsize="x-small")
    conf0 = runs[0].summary.get("configuration", {})
    title = ", ".join(f"{k.replace('_', ' ')} {conf0[k]}" for k in
                      ("law", "flux", "estimator", "drive_mode", "delay", "setpoint_frame")
                      if k in conf0 and k not in diffs)
    fig.suptitle("Comparison of runs — speed and flux errors"
                 + (f"\ncommon: {title}" if title else ""), fontsize="medium")
    out.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(out, dpi=110)
    plt.close(fig)
    return out
