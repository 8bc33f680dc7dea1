"""`hil-gateway compare`: the figure's legend names the reference profile each run ran."""

from __future__ import annotations

from pathlib import Path
from typing import Any

import numpy as np
import pytest

from gateway import report
from gateway.cli import main
from gateway.report import Run, compare_labels, profile_name

ROOT = Path(__file__).resolve().parents[1]


def _run(name: str, profile: str | None, **config: Any) -> Run:
    t = np.linspace(0.0, 0.1, 11)
    sig = {"t": t, "w_m": np.sin(t), "w_ref": np.zeros_like(t),
           "psi_r_mod": np.ones_like(t), "psi_ref": np.ones_like(t)}
    conf = {"command": "simulate", "law": "current-fed", **config}
    if profile is not None:
        conf["profile"] = profile
    return Run(Path("runs") / name, {"configuration": conf}, sig)


def _legend_texts(monkeypatch: pytest.MonkeyPatch, runs: list[Run], out: Path) -> list[str]:
    """The legend texts of the figure plot_compare draws (captured as it is saved)."""
    import matplotlib.figure

    texts: list[str] = []
    save = matplotlib.figure.Figure.savefig

    def capture(fig: Any, *args: Any, **kw: Any) -> Any:
        for ax in fig.axes:
            legend = ax.get_legend()
            if legend is not None:
                texts.extend(t.get_text() for t in legend.get_texts())
        return save(fig, *args, **kw)

    monkeypatch.setattr(matplotlib.figure.Figure, "savefig", capture)
    assert report.plot_compare(runs, out) == out
    return texts


@pytest.mark.parametrize(("source", "name"), [
    ("<embedded>", "paper"), ("profiles/quick.toml", "quick"),
    ("/abs/dir/zero-speed.toml", "zero-speed"), (None, ""), ("<string>", "<string>")])
def test_profile_name_is_compact(source: str | None, name: str) -> None:
    assert profile_name(source) == name


def test_legend_names_each_runs_profile(monkeypatch, tmp_path) -> None:
    pytest.importorskip("matplotlib")
    runs = [_run("A", "<embedded>", period=0.001),
            _run("B", "profiles/reversal.toml", period=0.00025)]
    labels = compare_labels(runs)
    assert labels == ["A (paper, period 0.001)", "B (reversal, period 0.00025)"]
    texts = _legend_texts(monkeypatch, runs, tmp_path / "compare.png")
    assert texts == labels
    # the same profile everywhere is still named in every entry
    same = [_run("A", "profiles/quick.toml", law="current-fed"),
            _run("B", "profiles/quick.toml", law="voltage-fed")]
    assert compare_labels(same) == ["A (quick, law current-fed)", "B (quick, law voltage-fed)"]


def test_legend_tells_apart_profiles_of_the_same_name(tmp_path) -> None:
    runs = [_run("A", "profiles/quick.toml"), _run("B", "/tmp/mine/quick.toml"),
            _run("C", None)]
    assert compare_labels(runs) == ["A (profiles/quick.toml)", "B (/tmp/mine/quick.toml)",
                                    "C"]


def test_compare_of_runs_of_two_profiles_names_both(monkeypatch, tmp_path, capsys) -> None:
    """End to end: `compare` of a run of the built-in paper profile and one of quick.toml;
    the figure's legend says which ran which."""
    pytest.importorskip("matplotlib")
    a, b = tmp_path / "a", tmp_path / "b"
    assert main(["simulate", "--duration", "0.1s", "--out", str(a)]) == 0
    assert main(["simulate", "--profile", str(ROOT / "profiles" / "quick.toml"),
                 "--duration", "0.1s", "--out", str(b)]) == 0
    capsys.readouterr()
    runs = [report.load_run(a), report.load_run(b)]
    texts = _legend_texts(monkeypatch, runs, tmp_path / "compare.png")
    assert texts == ["a (paper)", "b (quick)"]
    monkeypatch.chdir(tmp_path)
    assert main(["compare", str(a), str(b)]) == 0
    assert (tmp_path / "compare.png").read_bytes()[:4] == b"\x89PNG"
