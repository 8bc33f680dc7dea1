"""One writer of a run's results (gateway/results.py): `simulate`, `sim` and `run` write
signals.csv, every figure and the final summary.json once each, with the metrics computed
once (in `sim` from the emulator's full-resolution truth, merged before the first write).
`sim`/`run` also write the marker running.json before the loop, which a crash leaves behind
and a finished run removes once summary.json is written (README, "Faults and the
shutdown")."""

from __future__ import annotations

import json
from collections import Counter

import pytest
from gw_support import gateway_run

from gateway import report
from gateway.cli import main

QUICK = "profiles/quick.toml"


@pytest.fixture
def writes(monkeypatch):
    """Counts of what the report functions write, by file name."""
    seen: Counter[str] = Counter()
    real_csv, real_sum, real_plot = (report.write_columns_csv, report.write_summary,
                                     report.plot_figures)
    metrics_calls = []
    real_metrics = report.metrics

    def csv(path, sig):
        seen[path.name] += 1
        return real_csv(path, sig)

    def summary(path, s):
        seen[path.name + (" running" if s.get("run", {}).get("status") == "running"
                          else "")] += 1
        return real_sum(path, s)

    def plot(*a, **k):
        paths = real_plot(*a, **k)
        seen.update(p.name for p in paths)
        return paths

    def metrics(*a, **k):
        metrics_calls.append(1)
        return real_metrics(*a, **k)

    monkeypatch.setattr(report, "write_columns_csv", csv)
    monkeypatch.setattr(report, "write_summary", summary)
    monkeypatch.setattr(report, "plot_figures", plot)
    monkeypatch.setattr(report, "metrics", metrics)
    seen.metrics = metrics_calls  # type: ignore[attr-defined]
    return seen


FIGURES = ("fig1_references.png", "fig2_errors.png", "fig3_currents_voltages.png")


def _once(seen: Counter, *extra: str) -> None:
    for name in ("signals.csv", "summary.json", *FIGURES, *extra):
        assert seen[name] == 1, (name, dict(seen))
    assert len(seen.metrics) == 1, "the metrics were computed more than once"


def test_simulate_writes_each_file_once(tmp_path, writes):
    assert main(["simulate", "--reference", QUICK, "--out", str(tmp_path / "o")]) == 0
    _once(writes)
    assert writes["running.json running"] == 0


def test_sim_writes_each_file_once_with_the_truth_merged_first(tmp_path, writes):
    out = tmp_path / "o"
    assert main(["sim", "--reference", QUICK, "--out", str(out)]) == 0
    _once(writes)
    assert writes["running.json running"] == 1  # the crash marker before the loop
    assert writes["summary.json running"] == 0
    assert not (out / "running.json").exists()  # the run finished: no marker left
    s = json.loads((out / "summary.json").read_text())
    assert s["truth"] == report.TRUTH_FULL and s["configuration"]["command"] == "sim"


def test_run_writes_each_file_once(emulator, tmp_path, writes):
    emu = emulator()
    assert gateway_run(emu, tmp_path / "o", "--reference", QUICK, "--duration", "0.2s") == 0
    _once(writes)
    s = json.loads((tmp_path / "o" / "summary.json").read_text())
    assert s["truth"] == report.TRUTH_TPDO3 and s["configuration"]["command"] == "run"


def test_a_users_controller_draws_its_figure_once(tmp_path, writes):
    assert main(["sim", "--controller", "ifoc", "--reference", QUICK,
                 "--out", str(tmp_path / "o")]) == 0
    _once(writes, "fig4_controller.png")


def test_the_figures_of_a_run_that_stopped_early_say_so(tmp_path, monkeypatch):
    """A run stopped by the divergence guard: its figures are drawn up to the stop and told
    why it stopped (every title says so, a red line marks the last sample)."""
    seen = {}
    real = report.plot_figures

    def plot(*a, **k):
        seen.update(k)
        return real(*a, **k)

    monkeypatch.setattr(report, "plot_figures", plot)
    assert main(["simulate", "--plant", "rs-10", "--no-identify", "--out",
                 str(tmp_path / "o")]) == 1
    assert seen["stopped"].startswith("DIVERGED")
    assert (tmp_path / "o" / "fig1_references.png").is_file()


def test_fig3_says_which_limits_it_draws():
    """Fig. 3's title names the limits drawn, and says when no voltage limit is known (an
    ideal current source has none) instead of claiming 'with limits'."""
    text = report.fig3_limits_text(report.limits_for(type("G", (), {"i_max": 10.0})(), 200.0,
                                                     30.0))
    assert "i_max" in text and "over-current trip" in text and "u_dc/√3" in text
    assert "no voltage limit" not in text
    ideal = report.fig3_limits_text({"i_max": 10.0})
    assert "i_max" in ideal and "no voltage limit known" in ideal
