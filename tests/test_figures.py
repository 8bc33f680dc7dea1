"""A run's figures (gateway/figures.py) and the worker that draws them (gateway/drawing.py):
the same files drawn by the worker as in process, each written whole or not at all, a worker
that is gone replaced by the process itself, a figure that cannot be written an OSError as in
process, Ctrl-C not the worker's to act on, long series thinned for drawing only, and
`--no-figures`."""

from __future__ import annotations

import json
import os
import signal
import sys

import numpy as np
import pytest

from gateway import figures
from gateway.cli import main
from gateway.drawing import FigureWorker
from gateway.figures import FigureJob, drawn, figure_names

pytest.importorskip("matplotlib")
worker_only = pytest.mark.skipif(sys.platform != "linux", reason="the worker forks (Linux)")


@pytest.fixture(scope="module")
def job_sig():
    from dbc.motor import MotorParams
    from gateway.reference import paper_profile
    from gateway.session import run
    from gateway.spec import RunSpec

    res = run(RunSpec(duration=0.6), paper_profile(), MotorParams.paper())
    return res.sig, res.summary["speed_error"]["windows"]


def _job(job_sig, out, **kw) -> FigureJob:
    sig, windows = job_sig
    return FigureJob(sig, out, "current-fed law — simulate", windows, {"i_max": 20.0},
                     1e-3, **kw)


def _pngs(path) -> list[str]:
    return sorted(p.name for p in path.iterdir())


@worker_only
def test_the_worker_draws_what_the_process_draws(job_sig, tmp_path):
    here, there = tmp_path / "here", tmp_path / "there"
    here.mkdir()
    there.mkdir()
    drawn_here = figures.draw(_job(job_sig, here))
    with FigureWorker.start() as worker:
        assert worker is not None
        drawn_there = figures.plot_figures(*_args(job_sig, there), worker=worker)
    assert [p.name for p in drawn_here] == [p.name for p in drawn_there]
    assert [p.name for p in drawn_there] == figure_names(job_sig[0])
    assert _pngs(here) == _pngs(there) == sorted(figure_names(job_sig[0]))  # no temp files
    for p in drawn_there:
        assert p.read_bytes()[:4] == b"\x89PNG"


def _args(job_sig, out):
    sig, windows = job_sig
    return sig, out, "current-fed law — simulate", windows, {"i_max": 20.0}, 1e-3


@worker_only
def test_a_worker_gone_leaves_the_drawing_to_the_process(job_sig, tmp_path):
    worker = FigureWorker.start()
    assert worker is not None
    os.kill(worker.pid, signal.SIGKILL)
    os.waitpid(worker.pid, 0)  # gone and reaped: close() tolerates both
    got = figures.plot_figures(*_args(job_sig, tmp_path), worker=worker)
    assert [p.name for p in got] == figure_names(job_sig[0])
    assert _pngs(tmp_path) == sorted(figure_names(job_sig[0]))


@worker_only
def test_ctrl_c_is_not_the_workers(job_sig, tmp_path):
    """SIGINT reaches the whole process group from a terminal: the worker keeps going and
    the parent, which decides when a run stops, still gets its figures."""
    with FigureWorker.start() as worker:
        assert worker is not None
        os.kill(worker.pid, signal.SIGINT)
        os.kill(worker.pid, signal.SIGTERM)
        got = figures.plot_figures(*_args(job_sig, tmp_path), worker=worker)
    assert [p.name for p in got] == figure_names(job_sig[0])


@pytest.mark.parametrize("use_worker", [False, pytest.param(True, marks=worker_only)])
def test_a_figure_that_cannot_be_written_is_an_oserror(job_sig, tmp_path, use_worker):
    missing = tmp_path / "gone"
    worker = FigureWorker.start() if use_worker else None
    try:
        with pytest.raises(OSError):
            figures.plot_figures(*_args(job_sig, missing), worker=worker)
    finally:
        if worker is not None:
            worker.close()
    assert not missing.exists()


def test_a_failed_write_leaves_no_partial_file(job_sig, tmp_path, monkeypatch):
    from matplotlib.figure import Figure

    def half_written(self, path, **kw):
        path.write_bytes(b"\x89PNG half")
        raise OSError(28, "No space left on device", str(path))

    monkeypatch.setattr(Figure, "savefig", half_written)
    with pytest.raises(OSError):
        figures.draw(_job(job_sig, tmp_path))
    assert list(tmp_path.iterdir()) == []


def test_long_series_are_thinned_for_drawing_only():
    t = np.arange(100_000) * 1e-4
    y = np.sin(t * 7.0) + (t > 5.0) * 3.0
    y[12_345] = 40.0  # a one-sample spike
    y[50_000:50_010] = np.nan  # a gap
    tt, yy = drawn(t, y, 1000)
    assert len(tt) <= 4 * 1000 + 100 and np.all(np.diff(tt) > 0)
    assert tt[0] == t[0] and tt[-1] == t[-1]
    assert 40.0 in yy and np.isnan(yy).any()
    assert np.nanmax(yy) == np.nanmax(y) and np.nanmin(yy) == np.nanmin(y)
    short_t, short_y = t[:3000], y[:3000]
    assert drawn(short_t, short_y, 1000)[0] is short_t  # up to four per column: as is


def test_no_figures(tmp_path, capsys):
    out = tmp_path / "o"
    assert main(["simulate", "--reference", "profiles/quick.toml", "--no-figures",
                 "--out", str(out)]) == 0
    assert _pngs(out) == ["signals.csv", "summary.json"]
    text = capsys.readouterr().out
    assert "matplotlib" not in text and "next:" not in text
    assert json.loads((out / "summary.json").read_text())["run"]["exit_status"] == 0


def test_simulate_does_not_load_the_bus_modules():
    """`simulate` builds its own parser only: python-can and canopen are not imported."""
    from import_support import loaded_after

    code = "from gateway.cli import build_parser; build_parser('simulate'); import gateway.sim"
    assert loaded_after(code, ("can", "canopen", "matplotlib")) == []
