"""A campaign's figures, from its table (``DIR/figures/``):

* ``metric_vs_params.png``: the metric against each axis, a panel per axis (points that
  passed in one colour, those that did not in another, those without a value at the top);
* ``map_<A>__<B>.png``: the metric over two axes (the first two grid axes of more than one
  value, or ``--map A,B``): each cell the worst point there, crossed where a point did not
  pass — the stability region;
* ``distribution.png`` (a campaign with random draws): the metric's distribution, the
  criterion's threshold, the fraction that passed.

Each is written under a temporary name and renamed; without matplotlib, none.
"""

from __future__ import annotations

import math
import os
import re
from collections.abc import Mapping, Sequence
from pathlib import Path
from typing import Any

from gateway.campaign.summary import criteria_of, passes

PASS_COLOR, FAIL_COLOR = "C2", "C3"


def _values(rows: Sequence[Mapping[str, Any]], metric: str) -> list[float]:
    out = []
    for r in rows:
        try:
            out.append(float(r.get(metric)))  # type: ignore[arg-type]
        except (TypeError, ValueError):
            out.append(math.nan)
    return out


def _numeric(values: Sequence[Any]) -> bool:
    return all(isinstance(v, int | float) and not isinstance(v, bool) for v in values
               if v is not None)


def _log_scale(ys: Sequence[float]) -> bool:
    pos = [y for y in ys if math.isfinite(y) and y > 0]
    return bool(pos) and len(pos) == sum(math.isfinite(y) for y in ys) and (
        max(pos) / min(pos) > 100)


def _save(fig: Any, path: Path) -> Path:
    tmp = path.with_name(f".{path.name}.tmp-{os.getpid()}.png")
    try:
        fig.savefig(tmp, dpi=100)
        os.replace(tmp, path)
    finally:
        tmp.unlink(missing_ok=True)
    return path


def _threshold(meta: Mapping[str, Any], metric: str) -> float | None:
    for c in criteria_of(meta):
        if c.metric == metric:
            return c.threshold
    return None


def _categories(rows: Sequence[Mapping[str, Any]], key: str, meta: Mapping[str, Any]
                ) -> list[str]:
    for a in meta.get("axes", []):
        if a["key"] == key and a.get("values"):
            return list(a["values"])
    return sorted({str(r.get(key)) for r in rows})


def _scatter(ax: Any, rows: Sequence[Mapping[str, Any]], key: str, metric: str,
             meta: Mapping[str, Any]) -> None:
    criteria = criteria_of(meta)
    xs_raw = [r.get(key) for r in rows]
    ys = _values(rows, metric)
    if _numeric(xs_raw):
        xs = [math.nan if x is None else float(x) for x in xs_raw]
    else:
        cats = _categories(rows, key, meta)
        index = {c: i for i, c in enumerate(cats)}
        xs = [float(index.get(str(x), -1)) for x in xs_raw]
        ax.set_xticks(range(len(cats)), cats, rotation=30 if len(cats) > 4 else 0,
                      ha="right" if len(cats) > 4 else "center", fontsize="small")
    finite = [y for y in ys if math.isfinite(y)]
    top = (max(finite) * (3 if _log_scale(ys) else 1.1)) if finite else 1.0
    ok = [passes(r, criteria) for r in rows]
    for good, color, label in ((True, PASS_COLOR, "passed"), (False, FAIL_COLOR, "not passed")):
        pts = [(x, y) for x, y, g in zip(xs, ys, ok, strict=True) if g == good and
               math.isfinite(y)]
        if pts:
            ax.scatter(*zip(*pts, strict=True), s=10, alpha=0.6, color=color, label=label)
    missing = [x for x, y in zip(xs, ys, strict=True) if not math.isfinite(y)]
    if missing:
        ax.scatter(missing, [top] * len(missing), marker="x", color="k", s=18,
                   label="no value (failed)")
    if _log_scale(ys):
        ax.set_yscale("log")
    t = _threshold(meta, metric)
    if t is not None:
        ax.axhline(t, color="k", lw=0.8, ls="--", label=f"threshold {t:g}")
    ax.set_xlabel(key)
    ax.set_ylabel(metric)
    ax.grid(True, alpha=0.3)


def metric_vs_params(plt: Any, rows: Sequence[Mapping[str, Any]], meta: Mapping[str, Any],
                     metric: str, out: Path) -> Path | None:
    keys = [a["key"] for a in meta.get("axes", [])]
    keys = [k for k in keys if len({str(r.get(k)) for r in rows}) > 1]
    if not keys:
        return None
    cols = min(3, len(keys))
    nrows = math.ceil(len(keys) / cols)
    fig, axes = plt.subplots(nrows, cols, figsize=(4.6 * cols, 3.6 * nrows), squeeze=False,
                             layout="constrained")
    for ax, key in zip(axes.flat, keys, strict=False):
        _scatter(ax, rows, key, metric, meta)
    for ax in list(axes.flat)[len(keys):]:
        ax.set_visible(False)
    axes.flat[0].legend(fontsize="x-small")
    fig.suptitle(f"campaign {meta.get('name', '')}: {metric} against each axis "
                 f"({len(rows)} points)")
    try:
        return _save(fig, out / "metric_vs_params.png")
    finally:
        plt.close(fig)


def map_axes(meta: Mapping[str, Any], rows: Sequence[Mapping[str, Any]],
             given: Sequence[str] | None = None) -> tuple[str, str] | None:
    """The two axes of the map: ``given``, else the first two grid axes of more than one
    value, else the first two axes."""
    if given:
        return given[0], given[1]
    axes = meta.get("axes", [])
    multi = [a["key"] for a in axes if len({str(r.get(a["key"])) for r in rows}) > 1]
    grid = [k for k in multi if any(a["key"] == k and a.get("grid") for a in axes)]
    pick = grid if len(grid) >= 2 else multi
    return (pick[0], pick[1]) if len(pick) >= 2 else None


def stability_map(plt: Any, rows: Sequence[Mapping[str, Any]], meta: Mapping[str, Any],
                  metric: str, out: Path, keys: tuple[str, str]) -> Path:
    from matplotlib.colors import LogNorm

    a, b = keys
    criteria = criteria_of(meta)
    ys = _values(rows, metric)
    fig, ax = plt.subplots(figsize=(7.5, 5.8), layout="constrained")
    if _numeric([r.get(a) for r in rows]) and _numeric([r.get(b) for r in rows]) and len(
            {(r.get(a), r.get(b)) for r in rows}) > 0.5 * len(rows) > 25:
        # continuous draws: a scatter coloured by the metric
        vals = [y if math.isfinite(y) else math.nan for y in ys]
        norm = LogNorm() if _log_scale(ys) else None
        sc = ax.scatter([r.get(a) for r in rows], [r.get(b) for r in rows], c=vals, s=14,
                        cmap="viridis", norm=norm)
        bad = [(r.get(a), r.get(b)) for r in rows if not passes(r, criteria)]
        if bad:
            ax.scatter(*zip(*bad, strict=True), marker="x", color=FAIL_COLOR, s=20,
                       label="not passed")
            ax.legend(fontsize="small")
        fig.colorbar(sc, ax=ax, label=metric)
    else:
        ca, cb = _categories(rows, a, meta), _categories(rows, b, meta)
        la, lb = ca, cb
        if _numeric([r.get(a) for r in rows]):
            values = sorted({r.get(a) for r in rows if r.get(a) is not None})
            ca, la = [str(v) for v in values], [f"{v:.4g}" for v in values]
        if _numeric([r.get(b) for r in rows]):
            values = sorted({r.get(b) for r in rows if r.get(b) is not None})
            cb, lb = [str(v) for v in values], [f"{v:.4g}" for v in values]
        ia, ib = {c: i for i, c in enumerate(ca)}, {c: i for i, c in enumerate(cb)}
        import numpy as np

        grid = np.full((len(cb), len(ca)), np.nan)
        failed = np.zeros((len(cb), len(ca)), dtype=bool)
        seen = np.zeros((len(cb), len(ca)), dtype=bool)
        for r, y in zip(rows, ys, strict=True):
            i, j = ib.get(str(r.get(b))), ia.get(str(r.get(a)))
            if i is None or j is None:
                continue
            seen[i, j] = True
            worst = y if math.isfinite(y) else np.inf
            grid[i, j] = worst if np.isnan(grid[i, j]) else max(grid[i, j], worst)
            failed[i, j] |= not passes(r, criteria)
        finite = grid[np.isfinite(grid)]
        shown = np.where(np.isinf(grid), np.nan, grid)
        norm = LogNorm() if finite.size and finite.min() > 0 and (
            finite.max() / finite.min() > 100) else None
        im = ax.imshow(shown, origin="lower", aspect="auto", cmap="viridis", norm=norm)
        fig.colorbar(im, ax=ax, label=f"{metric} (worst point of the cell)")
        for i in range(len(cb)):
            for j in range(len(ca)):
                if not seen[i, j]:
                    continue
                if np.isinf(grid[i, j]):
                    ax.text(j, i, "no value", ha="center", va="center", fontsize="x-small",
                            color=FAIL_COLOR)
                elif failed[i, j]:
                    ax.plot(j, i, marker="x", color=FAIL_COLOR, ms=12, mew=2)
                if len(ca) * len(cb) <= 64 and np.isfinite(grid[i, j]):
                    ax.text(j, i - 0.3, f"{grid[i, j]:.3g}", ha="center", va="center",
                            fontsize="x-small", color="w")
        ax.set_xticks(range(len(ca)), la, rotation=30 if len(ca) > 6 else 0)
        ax.set_yticks(range(len(cb)), lb)
    ax.set_xlabel(a)
    ax.set_ylabel(b)
    ax.set_title(f"campaign {meta.get('name', '')}: {metric} over {a} × {b} "
                 "(× = a point did not pass)", fontsize="medium")
    name = re.sub(r"[^A-Za-z0-9.+_-]+", "_", f"map_{a}__{b}") + ".png"
    try:
        return _save(fig, out / name)
    finally:
        plt.close(fig)


def distribution(plt: Any, rows: Sequence[Mapping[str, Any]], meta: Mapping[str, Any],
                 metric: str, out: Path) -> Path | None:
    import numpy as np

    ys = np.array([y for y in _values(rows, metric) if math.isfinite(y)])
    if ys.size < 2:
        return None
    criteria = criteria_of(meta)
    fig, ax = plt.subplots(figsize=(7.5, 4.5), layout="constrained")
    if ys.min() > 0 and ys.max() / ys.min() > 20:
        bins = np.geomspace(ys.min(), ys.max(), 40)
        ax.set_xscale("log")
    else:
        bins = 40
    ax.hist(ys, bins=bins, color="C0", alpha=0.8)
    t = _threshold(meta, metric)
    if t is not None:
        ax.axvline(t, color="k", ls="--", lw=1, label=f"threshold {t:g}")
        ax.legend()
    ok = sum(passes(r, criteria) for r in rows)
    missing = len(rows) - ys.size
    ax.set_xlabel(metric)
    ax.set_ylabel("points")
    ax.set_title(f"campaign {meta.get('name', '')}: {metric} over {len(rows)} points; "
                 f"{ok} passed ({100 * ok / len(rows):.1f} %)"
                 + (f", {missing} without a value" if missing else ""), fontsize="medium")
    ax.grid(True, alpha=0.3)
    try:
        return _save(fig, out / "distribution.png")
    finally:
        plt.close(fig)


def draw(rows: Sequence[Mapping[str, Any]], meta: Mapping[str, Any], metric: str,
         out: Path, map_keys: Sequence[str] | None = None) -> list[Path] | None:
    """Every figure the table allows, into ``out``; None without matplotlib."""
    try:
        import matplotlib

        matplotlib.use("Agg")
        import matplotlib.pyplot as plt
    except ImportError:
        return None
    if not rows:
        return []
    out.mkdir(parents=True, exist_ok=True)
    written = [metric_vs_params(plt, rows, meta, metric, out)]
    keys = map_axes(meta, rows, map_keys)
    if keys is not None:
        written.append(stability_map(plt, rows, meta, metric, out, keys))
    if int(meta.get("random_n", 1)) > 1:
        written.append(distribution(plt, rows, meta, metric, out))
    return [p for p in written if p is not None]
