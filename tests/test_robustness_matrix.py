"""bench/robustness_matrix.py: the targets of the robustness matrix, and one block run
through the campaign command (the whole matrix is BENCHMARKS.md's)."""

from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT / "bench"))

from robustness_matrix import Cell, Row, target  # noqa: E402


def _row(block: str, plant: str, **cells: Cell) -> Row:
    return Row(block, plant, {k.replace("_", " "): v for k, v in cells.items()})


@pytest.mark.parametrize("row, ok", [
    (_row("current-fed", "nominal", defaults=Cell(0.004, 0.01), true_flux=Cell(0.001, 0.003)),
     True),
    (_row("current-fed", "nominal", defaults=Cell(0.006, 0.01), true_flux=Cell(0.001, 0.003)),
     False),
    (_row("full-order", "nominal", defaults=Cell(0.0048, 0.02), true_flux=Cell(0.004, 0.02)),
     True),
    (_row("full-order", "nominal", defaults=Cell(0.28, 0.5), true_flux=Cell(0.3, 0.5)), False),
    # R_s rows: 2 × the true flux, or 0.02 where larger
    (_row("current-fed", "rs+10", defaults=Cell(0.019, 0.1), true_flux=Cell(0.001, 0.003)),
     True),
    (_row("current-fed", "offset10mA", defaults=Cell(0.03, 0.1), true_flux=Cell(0.014, 0.1)),
     False),
    (_row("current-fed", "offset10mA", defaults=Cell(0.027, 0.1), true_flux=Cell(0.014, 0.1)),
     True),
    # a stop is never met, whatever the RMS up to it
    (_row("current-fed", "rs-10", defaults=Cell(0.001, 0.1, stopped=True),
          true_flux=Cell(0.001, 0.003)), False),
    (_row("current-fed", "lm+10", defaults=Cell(0.049, 0.2), true_flux=Cell(0.01, 0.1)), True),
    (_row("current-fed", "inertia-half", defaults=Cell(2.8, 12), true_flux=Cell(2.8, 12)),
     False),
    (_row("current-fed", "noise5mA", defaults=Cell(0.0069, 0.03), true_flux=Cell(0.0046, 0.01)),
     True),
    (_row("current-fed", "gain-b+2", defaults=Cell(0.07, 0.3), true_flux=Cell(0.046, 0.2)),
     False),
    (_row("low speed/zero-speed", "rs+10", defaults=Cell(0.1, 0.99), true_flux=Cell(0, 0)),
     True),
    (_row("low speed/zero-speed", "rs+10", defaults=Cell(0.1, 1.01), true_flux=Cell(0, 0)),
     False),
    (_row("load", "nominal", told=Cell(0.1, 1), observed=Cell(0.19, 1),
          not_told=Cell(9.0, 50, stopped=True)), True),  # --load untold: shown, not held
    (_row("load", "nominal", told=Cell(0.1, 1), observed=Cell(0.21, 1),
          not_told=Cell(0.1, 1)), False),
    (_row("load", "nominal", told=Cell(0.1, 1), observed=Cell(0.19, 1, stopped=True),
          not_told=Cell(0.1, 1)), False),
    (_row("current-fed", "real-drive", defaults=Cell(0.03, 0.2), true_flux=Cell(0.03, 0.2)),
     True),
])
def test_targets(row, ok):
    assert target(row)[1] is ok


def test_a_failed_point_is_not_a_verdict():
    row = _row("current-fed", "rs+10", defaults=Cell(failed="error: boom"),
               true_flux=Cell(0.001, 0.003))
    assert target(row)[1] is None


def test_one_block_through_the_campaign(tmp_path):
    """The low-speed block (both laws), in this process: its table, its verdicts and the
    JSON line."""
    out = tmp_path / "matrix"
    p = subprocess.run([sys.executable, str(ROOT / "bench" / "robustness_matrix.py"),
                        "--in-process", "--only", "low speed", "--out", str(out), "--json",
                        "--png", str(tmp_path / "m.png")],
                       capture_output=True, text=True, cwd=ROOT, timeout=600)
    assert p.returncode == 0, p.stderr[-2000:]
    figures = json.loads(p.stdout.strip().splitlines()[-1])
    assert figures["rows"] == 8 and figures["met"] == 8 and figures["missed"] == []
    for law in ("", ", full-order"):  # both laws
        cell = figures[f"low speed/zero-speed{law}: rs+10 / defaults"]
        assert 0.0 < cell["rms"] < cell["max"] <= 1.0 and cell["stopped"] is False
    assert "8 of 8 rows meet their target" in p.stdout
    assert (tmp_path / "m.png").stat().st_size > 10_000


def test_a_load_row_is_held_to_the_load_told_on_the_nominal_motor():
    """The untold-load plant's "told" run is told the profile's load only (the shaft
    carries more): its observed run is held to twice the nominal motor's told run, not to
    twice that one."""
    row = _row("load", "untold-load", told=Cell(0.166, 3.4), observed=Cell(0.081, 1.1),
               not_told=Cell(14.2, 55, stopped=True))
    assert target(row)[1] is True  # against its own told run: a loophole
    row.told_ref = Cell(0.00188, 0.006)
    text, ok = target(row)
    assert ok is False and "0.00376" in text
