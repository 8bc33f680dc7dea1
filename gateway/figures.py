"""A run's figures: the paper's Fig. 1 and Fig. 2, Fig. 3 (currents and voltages) and Fig. 4
(the controller's own signals), drawn from the record's columns into PNG files.

Drawn with matplotlib's object API and the Agg canvas (no pyplot, whose import alone costs
about 0.2 s), with fixed margins in inches instead of a layout engine (constrained layout
measures every tick label once more: 40 % of a figure's drawing): the margins hold tick
labels of up to eight characters, an axis label and the title's lines. A series longer than
four points per pixel column is drawn through each column's first, lowest, highest and last
point (:func:`drawn`): the same picture, fewer segments; the data are never touched. Each
file is written under a temporary name and renamed when complete, so a figure that fails
or is interrupted leaves no partial file behind.

:func:`plot_figures` draws in this process, or hands the drawing to a worker started
before the run ended (:class:`gateway.drawing.FigureWorker`); :func:`draw` is what either
runs. Units: SI throughout (s, rad/s, Wb, N·m, A, V).
"""

from __future__ import annotations

import math
import os
from collections.abc import Callable, Iterable, Mapping, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Protocol

import numpy as np

DPI = 110
#: Fixed margins, inches: left (y tick labels of up to eight characters and the axis
#: label), right, bottom (x tick labels and the axis label), the gap between stacked panels
#: (room for an axis's offset text, "1e−5"), and per line of the title.
LEFT, RIGHT, BOTTOM, GAP, TITLE_LINE = 1.05, 0.2, 0.6, 0.22, 0.17

#: The signals Fig. 2 already shows, and the paper's flux estimate (checked by the guard):
#: not drawn again in Fig. 4.
DRAWN_ELSEWHERE = frozenset({"w_hat", "psi_r_mod_hat", "psi_rd_hat", "psi_rq_hat"})
#: Fig. 4 draws at most this many of the controller's signals.
FIG4_MAX = 8

Suptitle = Callable[[Any, str], None]


@dataclass
class FigureJob:
    """What the figures of a run are drawn from (it pickles: a worker process gets it).

    sig: the record's columns. out_dir: where the PNG files go. title: the configuration
    (:func:`gateway.report.title_for`). windows: the summary's metric windows (dicts with
    "from", "to", "label"). limits: :func:`limits_for`. delay_s: from a row's sample to its
    setpoints acting, s. stopped: why the run ended before its profile, or "".
    """

    sig: Mapping[str, np.ndarray]
    out_dir: Path
    title: str = ""
    windows: list[Mapping[str, Any]] = field(default_factory=list)
    limits: dict[str, float] = field(default_factory=dict)
    delay_s: float = 0.0
    stopped: str = ""


class Worker(Protocol):
    """Draws a :class:`FigureJob` elsewhere (:class:`gateway.drawing.FigureWorker`)."""

    def draw(self, job: FigureJob) -> list[Path]: ...


def plot_figures(sig: Mapping[str, np.ndarray], out_dir: Path, title: str = "",
                 windows: Iterable[Mapping[str, Any]] = (),
                 limits: Mapping[str, float] | None = None, delay_s: float = 0.0,
                 stopped: str = "", worker: Worker | None = None) -> list[Path]:
    """The paper's Fig. 1 (references and load) and Fig. 2 (errors), and Fig. 3 (stator
    currents and voltages: the whole run's magnitudes, then zoomed panels of start-up, a
    load step and steady state with the setpoints and the limits); Fig. 4 when the
    controller logs signals of its own.

    ``title``: the configuration (:func:`gateway.report.title_for`); ``windows``: the metric
    windows of the summary (drawn in Fig. 2, used to pick Fig. 3's zooms); ``limits``:
    :func:`limits_for`; ``delay_s``: time from a row's sample to its setpoints acting
    (delay·T); ``stopped``: why a run ended before its profile (said in every title, and a
    red line at its last sample in Figs. 1, 2 and 4); ``worker``: draws them in another
    process (:class:`gateway.drawing.FigureWorker`), else this one does. Returns the PNG
    paths written, or [] when matplotlib is not installed; OSError when one cannot be
    written.
    """
    job = FigureJob(sig, Path(out_dir), title, list(windows), dict(limits or {}), delay_s,
                    stopped)
    return worker.draw(job) if worker is not None else draw(job)


def figure_names(sig: Mapping[str, np.ndarray]) -> list[str]:
    """The files a job draws, in order."""
    names = ["fig1_references.png", "fig2_errors.png", "fig3_currents_voltages.png"]
    return [*names, "fig4_controller.png"] if controller_signals(sig) else names


def draw(job: FigureJob, names: Sequence[str] | None = None) -> list[Path]:
    """Draw the figures ``names`` (default :func:`figure_names`) of ``job`` in this process;
    the paths written, [] without matplotlib."""
    try:
        from matplotlib import rc_context
    except ImportError:
        return []
    sig = job.sig
    suptitle = _suptitler(sig["t"], job.title, job.stopped)
    draws: dict[str, Callable[[Path], None]] = {
        "fig1_references.png": lambda p: _fig1(sig, p, suptitle),
        "fig2_errors.png": lambda p: _fig2(sig, p, job.windows, suptitle),
        "fig3_currents_voltages.png": lambda p: _fig3(sig, p, job.windows, job.limits,
                                                      job.delay_s, suptitle),
        "fig4_controller.png": lambda p: _fig4(sig, controller_signals(sig), p, suptitle),
    }
    written = []
    # titles at the top of their panels: none has tick labels there, and placing them
    # clear of such labels measures every panel once more
    with rc_context({"axes.titley": 1.0}):
        for name in figure_names(sig) if names is None else names:
            path = job.out_dir / name
            draws[name](path)
            written.append(path)
    return written


def warm_up() -> bool:
    """Import what drawing needs and load the font (a worker does it while the run goes
    on); False without matplotlib."""
    try:
        from matplotlib.backends.backend_agg import FigureCanvasAgg
        from matplotlib.figure import Figure
    except ImportError:
        return False
    fig = Figure(figsize=(1, 1))
    fig.text(0.5, 0.5, "ω 0.5")
    FigureCanvasAgg(fig).draw()
    return True


# --------------------------------------------------------------------------- pieces


def limits_for(gains: Any, u_lim: float | None = None, i_trip: float | None = None
               ) -> dict[str, float]:
    """The limits Fig. 3 draws: the controller's current limit ``gains.i_max``, and the
    drive's voltage limit and over-current trip when known."""
    out = {"i_max": float(gains.i_max)}
    if u_lim is not None:
        out["u_lim"] = float(u_lim)
    if i_trip is not None and math.isfinite(i_trip):
        out["i_trip"] = float(i_trip)
    return out


def controller_signals(sig: Mapping[str, np.ndarray]) -> list[str]:
    """The columns a controller logged (:attr:`DriveController.signals`) that no other
    figure draws: those not of the cycle, the bus or :data:`DRAWN_ELSEWHERE`."""
    from gateway.cycle import BUS_COLUMNS, CYCLE_COLUMNS

    known = set(CYCLE_COLUMNS) | set(BUS_COLUMNS) | DRAWN_ELSEWHERE
    return [n for n in sig if n not in known]


def zoom_windows(sig: Mapping[str, np.ndarray], windows: Iterable[Mapping[str, Any]] = ()
                 ) -> list[tuple[str, float, float]]:
    """Fig. 3's zoomed panels, chosen from the profile's segments: start-up (to the end of
    the first speed window, at most 0.3 s after it starts), the first load step (50 ms
    before to 150 ms after), steady state (the last 150 ms). Panels outside the run are left
    out."""
    t = sig["t"]
    if not t.size:
        return []
    t0, t1 = float(t[0]), float(t[-1])
    span = min(0.15, 0.3 * (t1 - t0))
    w = list(windows)
    out: list[tuple[str, float, float]] = []
    speed = [x for x in w if "speed" in str(x.get("label", ""))]
    end_start = min(t1, 0.5 if not speed else max(min(speed[0]["to"], speed[0]["from"] + 0.3),
                                                  0.1))
    out.append(("start-up", t0, max(end_start, t0 + span)))
    load = [x for x in w if "load" in str(x.get("label", ""))]
    if load:
        tl = float(load[0]["from"])
        if t0 < tl < t1:
            out.append((f"load step at {tl:g} s", max(t0, tl - span / 3), min(t1, tl + span)))
    else:
        dT = np.abs(np.diff(sig["T_L"])) if "T_L" in sig else np.array([])
        if dT.size and np.max(dT) > 0:
            tl = float(t[int(np.argmax(dT))])
            out.append((f"load change at {tl:.3g} s", max(t0, tl - span / 3),
                        min(t1, tl + span)))
    out.append(("steady state (end)", max(t0, t1 - span), t1))
    return out


def fig3_limits_text(limits: Mapping[str, float]) -> str:
    """What Fig. 3's title says of the limits it draws: the ones drawn, and that no voltage
    limit is known when none is (an ideal current source has none; a real drive's is its
    own)."""
    drawn = [text for key, text in (("i_max", "the current limit i_max"),
                                     ("i_trip", "the over-current trip"),
                                     ("u_lim", "the voltage limit u_dc/√3")) if key in limits]
    out = f", with {', '.join(drawn)}" if drawn else ""
    return out + ("" if "u_lim" in limits else " (no voltage limit known)")


def drawn(t: np.ndarray, y: np.ndarray, columns: int = 1000) -> tuple[np.ndarray, np.ndarray]:
    """(t, y) as drawn across ``columns`` pixel columns: unchanged up to four points per
    column; beyond, each column's first, lowest, highest and last point, in time order —
    the polyline covers the same pixels (every peak and every NaN gap stays)."""
    n = len(t)
    if n <= 4 * columns:
        return t, y
    k = n // columns  # points per column; the remainder is kept whole
    m = columns * k
    block = y[:m].reshape(columns, k)
    base = np.arange(columns) * k
    with np.errstate(invalid="ignore"):
        keep = np.concatenate([base, base + np.argmin(block, axis=1),
                               base + np.argmax(block, axis=1), base + k - 1,
                               np.arange(m, n)])
    keep = np.unique(keep)
    return t[keep], y[keep]


def _setpoints_ab(sig: Mapping[str, np.ndarray]) -> tuple[np.ndarray, np.ndarray]:
    """The current setpoints in the (a, b) frame: (i_sd*, i_sq*) turned by the frame angle
    sent with them (for the interval they act on)."""
    i = (sig["i_sd_ref"] + 1j * sig["i_sq_ref"]) * np.exp(1j * sig["eps_0"])
    return i.real, i.imag


# --------------------------------------------------------------------------- layout


def _figure(width: float, height: float) -> Any:
    from matplotlib.figure import Figure

    return Figure(figsize=(width, height), dpi=DPI)


def _column(fig: Any, rows: int, gap: float = GAP, right: float = RIGHT) -> None:
    """Margins of ``rows`` panels stacked on a common time axis (the top one: :func:`_top`,
    when the title is known)."""
    w, h = fig.get_size_inches()
    fig.subplots_adjust(left=LEFT / w, right=1.0 - right / w, bottom=BOTTOM / h,
                        hspace=_space(gap, rows, _panels_height(h)))


def _title_height(h: float, lines: int) -> float:
    """Inches above the panels for a title of ``lines`` lines (at 0.98 of the height)."""
    return 0.02 * h + lines * TITLE_LINE + 0.22


def _panels_height(h: float) -> float:
    """Inches the panels of a figure ``h`` inches high share, below a three-line title."""
    return h - _title_height(h, 3) - BOTTOM


def _space(gap: float, n: int, total: float) -> float:
    """subplots_adjust's hspace/wspace (a fraction of a panel) for ``gap`` inches between
    ``n`` panels sharing ``total`` inches."""
    if n < 2:
        return 0.0
    panel = (total - (n - 1) * gap) / n
    return gap / max(panel, 1e-3)


def _top(fig: Any, lines: int) -> None:
    """Room above the panels for a title of ``lines`` lines (at 0.98 of the height)."""
    h = fig.get_size_inches()[1]
    fig.subplots_adjust(top=1.0 - _title_height(h, lines) / h)


def _suptitler(t: np.ndarray, title: str, stopped: str) -> Suptitle:
    """The figures' title writer: what a figure shows, then the configuration ``title``
    (:func:`gateway.report.title_for`, one line each side of " — "); a run ``stopped``
    early says why in dark red and gets a red dashed line at its last sample ``t[-1]`` (s)
    on the time axes. Makes room for the title (:func:`_top`)."""
    def suptitle(fig: Any, what: str) -> None:
        conf = title.replace(" — ", "\n")  # configuration, then how it ran
        if stopped:
            conf += f"\nSTOPPED EARLY at t = {t[-1]:.3f} s: {stopped}"
            for a in fig.axes:
                if a.get_xlabel() == "time [s]" or a.get_shared_x_axes().joined(a, fig.axes[0]):
                    a.axvline(t[-1], color="red", ls="--", lw=1)
        text = f"{what}\n{conf}" if title or stopped else what
        fig.suptitle(text, fontsize="medium", color="darkred" if stopped else "black")
        _top(fig, text.count("\n") + 1)

    return suptitle


def _save(fig: Any, path: Path) -> None:
    """The figure as PNG at ``path``, written under a temporary name and renamed when
    complete (a failed or interrupted write leaves no partial file)."""
    tmp = path.with_name(f".{path.name}.{os.getpid()}.tmp")
    try:  # zlib level 1: 15 % larger files than the default 6, a tenth of the drawing
        fig.savefig(tmp, dpi=DPI, format="png", pil_kwargs={"compress_level": 1})
        os.replace(tmp, path)
    except BaseException:
        tmp.unlink(missing_ok=True)
        raise


# --------------------------------------------------------------------------- figures


def _fig1(sig: Mapping[str, np.ndarray], path: Path, suptitle: Suptitle) -> None:
    """Fig. 1: speed (rad/s) and flux (Wb) references against the motor's, and the load
    torque (N·m)."""
    t = sig["t"]
    fig = _figure(8, 7.5)
    ax = fig.subplots(3, 1, sharex=True)
    _column(fig, 3)
    ax[0].plot(*drawn(t, sig["w_ref"]), label="ω* reference")
    ax[0].plot(*drawn(t, sig["w_m"]), "--", label="ω motor")
    ax[0].set_ylabel("speed [rad/s]")
    ax[1].plot(*drawn(t, sig["psi_ref"]), label="ψ* reference")
    ax[1].plot(*drawn(t, sig["psi_r_mod"]), "--", label="|ψr| motor")
    ax[1].set_ylabel("rotor flux [Wb]")
    ax[2].plot(*drawn(t, sig["T_L"]), color="C3", label="T_L load")
    ax[2].set_ylabel("load torque [N·m]")
    ax[2].set_xlabel("time [s]")
    for a in ax:
        a.grid(True, alpha=0.3)
        a.legend(loc="best", fontsize="small")
    suptitle(fig, "Fig. 1 — speed and flux references, applied load")
    _save(fig, path)


def _fig2(sig: Mapping[str, np.ndarray], path: Path, windows: list,
          suptitle: Suptitle) -> None:
    """Fig. 2: the speed (rad/s) and flux (Wb) tracking errors, and the speed estimate's
    error when there is one (``w_hat``); dotted lines where the metric ``windows`` after
    the first start."""
    t = sig["t"]
    estimate = "w_hat" in sig
    fig = _figure(8, 7.5 if estimate else 5.5)
    ax = fig.subplots(3 if estimate else 2, 1, sharex=True)
    _column(fig, len(ax))
    ax[0].plot(*drawn(t, sig["w_m"] - sig["w_ref"]))
    ax[0].set_ylabel("ω − ω* [rad/s]")
    ax[1].plot(*drawn(t, sig["psi_r_mod"] - sig["psi_ref"]))
    ax[1].set_ylabel("|ψr| − ψ* [Wb]")
    if estimate:
        ax[2].plot(*drawn(t, sig["w_hat"] - sig["w_m"]))
        ax[2].set_ylabel("ω̂ − ω [rad/s]")
    ax[-1].set_xlabel("time [s]")
    for a in ax:
        a.grid(True, alpha=0.3)
        for w in windows[1:]:
            a.axvline(w["from"], color="0.6", lw=0.8, ls=":")
    suptitle(fig, "Fig. 2 — tracking and estimation errors (dotted: metric windows)"
             if estimate else "Fig. 2 — tracking errors (dotted: metric windows)")
    _save(fig, path)


def _fig4(sig: Mapping[str, np.ndarray], names: list[str], path: Path,
          suptitle: Suptitle) -> None:
    """Fig. 4: the controller's own signals, one panel each (the first FIG4_MAX)."""
    shown = names[:FIG4_MAX]
    fig = _figure(8, 1.2 + 1.6 * len(shown))
    ax = fig.subplots(len(shown), 1, sharex=True, squeeze=False)
    _column(fig, len(shown))
    for a, name in zip(ax[:, 0], shown, strict=True):
        a.plot(*drawn(sig["t"], sig[name]), lw=1)
        a.set_ylabel(name)
        a.grid(True, alpha=0.3)
    ax[-1, 0].set_xlabel("time [s]")
    more = f" (first {FIG4_MAX} of {len(names)})" if len(names) > FIG4_MAX else ""
    suptitle(fig, f"Fig. 4 — the controller's signals{more}")
    _save(fig, path)


def _fig3(sig: Mapping[str, np.ndarray], path: Path, windows: list,
          limits: Mapping[str, float], delay_s: float, suptitle: Suptitle) -> None:
    """Fig. 3: the whole run's |i_s| (A) and |u_s| (V) on top, below one column per zoom
    (:func:`zoom_windows`) of the (a, b) currents with their setpoints (acting ``delay_s``
    after their row) and the period-average voltages; the ``limits`` drawn dotted."""
    t = sig["t"]
    zooms = zoom_windows(sig, windows)
    i_ref_a, i_ref_b = _setpoints_ab(sig)
    t_ref = t + delay_s
    w, h = 11.0, 8.0
    fig = _figure(w, h)
    right = 0.8  # the overview's second axis: |u_s| ticks and label
    fig.subplots_adjust(left=LEFT / w, right=1.0 - right / w, bottom=BOTTOM / h)
    # the overview, then the zooms (0.75 in between for the overview's time axis and the
    # zooms' titles); the zooms' currents share the time axis of the voltages below them
    n = max(len(zooms), 1)
    outer = fig.add_gridspec(2, 1, height_ratios=(1.0, 2.6),
                             hspace=_space(0.75, 2, _panels_height(h)))
    grid = outer[1].subgridspec(2, n, hspace=_space(GAP, 2, _panels_height(h) * 2.6 / 3.6),
                                wspace=_space(0.65, n, w - LEFT - right))
    _fig3_overview(fig.add_subplot(outer[0]), sig, zooms, limits)
    for j, zoom in enumerate(zooms):
        au = fig.add_subplot(grid[1, j])
        ai = fig.add_subplot(grid[0, j], sharex=au)
        ai.tick_params(labelbottom=False)
        _fig3_zoom(ai, au, sig, zoom, (t_ref, i_ref_a, i_ref_b), limits)
        if j == 0:
            ai.set_ylabel("current [A]")
            au.set_ylabel("voltage, period average [V]")
        for a in (ai, au):
            a.grid(True, alpha=0.3)
        if j == len(zooms) - 1:
            ai.legend(loc="upper right", fontsize="x-small")
            au.legend(loc="upper right", fontsize="x-small")
    suptitle(fig, "Fig. 3 — stator currents (solid: measured, dashed: setpoints) and "
                  f"average voltages{fig3_limits_text(limits)}")
    _save(fig, path)


def _fig3_overview(top: Any, sig: Mapping[str, np.ndarray],
                   zooms: list[tuple[str, float, float]], limits: Mapping[str, float]) -> None:
    """Fig. 3's top panel: |i_s| (A) and, on a twin axis, |u_s| (V) over the whole run,
    with ``i_max`` and ``u_lim`` dotted and the ``zooms`` (name, from, to in s) shaded."""
    t = sig["t"]
    top.plot(*drawn(t, np.hypot(sig["i_sa"], sig["i_sb"])), label="|i_s| [A]")
    top.set_ylabel("|i_s| [A]")
    top2 = top.twinx()
    top2.plot(*drawn(t, np.hypot(sig["u_sa"], sig["u_sb"])), color="C1", lw=0.8,
              label="|u_s| [V]")
    top2.set_ylabel("|u_s| [V]", color="C1")
    if "i_max" in limits:
        top.axhline(limits["i_max"], color="C0", ls=":", lw=1, label="i_max (controller)")
    if "u_lim" in limits:
        top2.axhline(limits["u_lim"], color="C1", ls=":", lw=1, label="u_dc/√3 (drive)")
    for _, lo, hi in zooms:
        top.axvspan(lo, hi, color="0.85", zorder=0)
    top.set_xlabel("time [s] (shaded: the zoomed panels below)")
    top.grid(True, alpha=0.3)
    h1, l1 = top.get_legend_handles_labels()
    h2, l2 = top2.get_legend_handles_labels()
    top.legend(h1 + h2, l1 + l2, loc="upper left", fontsize="x-small", ncol=4)


def _fig3_zoom(ai: Any, au: Any, sig: Mapping[str, np.ndarray], zoom: tuple[str, float, float],
               ref: tuple[np.ndarray, np.ndarray, np.ndarray],
               limits: Mapping[str, float]) -> None:
    """One zoomed column of Fig. 3 over ``zoom`` (name, from, to in s): the (a, b) currents
    (A) and, dashed, their setpoints ``ref`` (acting times in s, i_sa*, i_sb* in A) in
    ``ai``; the voltages (V) in ``au``; ±i_max, ±i_trip and ±u_dc/√3 dotted if known."""
    name, lo, hi = zoom
    t = sig["t"]
    t_ref, i_ref_a, i_ref_b = ref
    sel = (t >= lo) & (t <= hi)
    sel_ref = (t_ref >= lo) & (t_ref <= hi)
    ai.plot(*drawn(t[sel], sig["i_sa"][sel], 300), color="C0", label="i_sa")
    ai.plot(*drawn(t[sel], sig["i_sb"][sel], 300), color="C2", label="i_sb")
    ai.step(t_ref[sel_ref], i_ref_a[sel_ref], "--", where="post", color="C0", lw=0.9,
            label="i_sa* setpoint")
    ai.step(t_ref[sel_ref], i_ref_b[sel_ref], "--", where="post", color="C2", lw=0.9,
            label="i_sb* setpoint")
    au.plot(*drawn(t[sel], sig["u_sa"][sel], 300), color="C1", label="u_sa")
    au.plot(*drawn(t[sel], sig["u_sb"][sel], 300), color="C4", label="u_sb")
    for key, a, color, text in (("i_max", ai, "k", "±i_max"), ("i_trip", ai, "C3", "±i_trip"),
                                ("u_lim", au, "C3", "±u_dc/√3")):
        if key in limits:
            for sign in (1, -1):
                a.axhline(sign * limits[key], color=color, ls=":", lw=1,
                          label=text if sign > 0 else None)
    ai.set_title(name, fontsize="small")
    au.set_xlabel("time [s]")
