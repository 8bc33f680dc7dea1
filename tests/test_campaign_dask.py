"""Campaigns on Dask: the 1000-point Monte Carlo of tests/campaigns/monte-carlo-1000.toml on
a local cluster (Ctrl-C, then a re-run during which a worker is killed: the table ends
complete, nothing lost and nothing run twice), the same file unchanged against a separately
started `dask scheduler` with two `dask worker` processes, and a point that kills its
worker. Everything on 127.0.0.1. The deadlines below only keep a broken run from hanging
the suite; no result depends on a time."""

from __future__ import annotations

import json
import os
import signal
import subprocess
import sys
import time
from collections import Counter
from pathlib import Path

import psutil
import pyarrow.parquet as pq
import pytest

ROOT = Path(__file__).resolve().parents[1]
MC = ROOT / "tests" / "campaigns" / "monte-carlo-1000.toml"
DEADLINE = 600.0  # s: a broken run fails the test instead of hanging the suite

pytestmark = pytest.mark.slow


def env(*paths: Path) -> dict[str, str]:
    """The environment of the campaign and of the Dask processes: this checkout first."""
    return {**os.environ,
            "PYTHONPATH": os.pathsep.join(str(p) for p in (ROOT, *paths))}


def _ctrl_c_reaches_it() -> None:
    """In the child, before exec: SIGINT's default disposition. A process started in the
    background by a non-interactive shell (``cmd &``, a CI runner's) has SIGINT ignored,
    which its children inherit across exec and Python then leaves ignored: the campaign
    would never see the Ctrl-C this test sends."""
    signal.signal(signal.SIGINT, signal.SIG_DFL)


def campaign(*args: str, extra: tuple[Path, ...] = (), log: Path) -> subprocess.Popen:
    return subprocess.Popen([sys.executable, "-m", "gateway", "campaign", *args], cwd=ROOT,
                            env=env(*extra), stdout=log.open("w"),
                            stderr=(log.with_suffix(".err")).open("w"),
                            preexec_fn=_ctrl_c_reaches_it)


def finish(p: subprocess.Popen) -> int:
    try:
        return p.wait(DEADLINE)
    except subprocess.TimeoutExpired:
        p.kill()
        raise


def rows_in_parts(out: Path) -> int:
    parts = out / "parts"
    n = 0
    for f in parts.glob("part-*.parquet") if parts.is_dir() else []:
        try:
            n += pq.read_metadata(f).num_rows
        except OSError:  # renamed into place as we looked
            continue
    return n


def wait_for_rows(out: Path, n: int, p: subprocess.Popen) -> None:
    t0 = time.monotonic()
    while rows_in_parts(out) < n:
        assert p.poll() is None, f"the campaign ended (status {p.returncode}) before {n} rows"
        assert time.monotonic() - t0 < DEADLINE, "no progress"
        time.sleep(0.2)


def worker_processes(p: subprocess.Popen) -> list[psutil.Process]:
    """The local cluster's worker processes (the nannies' spawned children)."""
    return [c for c in psutil.Process(p.pid).children(recursive=True)
            if "spawn_main" in " ".join(c.cmdline())]


def table(out: Path) -> list[dict]:
    return pq.read_table(out / "results.parquet").to_pylist()


def test_monte_carlo_on_a_local_cluster_survives_ctrl_c_and_a_killed_worker(tmp_path):
    out = tmp_path / "mc"
    first = campaign(str(MC), "--out", str(out), "--workers", "2", log=tmp_path / "1.log")
    wait_for_rows(out, 150, first)
    seen = rows_in_parts(out)
    first.send_signal(signal.SIGINT)
    status = finish(first)
    err = (tmp_path / "1.err").read_text()
    assert status == 130, (f"Ctrl-C sent with {seen} rows in the parts; the campaign ended "
                           f"{status}:\n{err[-3000:]}")
    assert "Traceback" not in err
    assert "interrupted" in err and "run the same command again" in err
    assert "points/s" in err and "left" in err  # the progress bar: rate and time left
    assert "dashboard: http://127.0.0.1:" in (tmp_path / "1.log").read_text()
    before = table(out)
    assert 150 <= len(before) < 1000
    assert len({r["hash"] for r in before}) == len(before)
    assert not list((out / "parts").glob("*.parquet"))  # compacted on the way out

    second = campaign(str(MC), "--out", str(out), "--workers", "2", log=tmp_path / "2.log")
    wait_for_rows(out, 100, second)
    victims = worker_processes(second)
    assert len(victims) == 2
    victims[0].kill()
    status = finish(second)
    log = (tmp_path / "2.log").read_text()
    assert status in (0, 1), (tmp_path / "2.err").read_text()
    assert f"1000 points of `simulate`; {len(before)} already in" in log
    after = table(out)
    assert len(after) == 1000 and len({r["hash"] for r in after}) == 1000
    assert sorted(r["point"] for r in after) == list(range(1000))
    by_hash = {r["hash"]: r for r in after}
    # the first run's rows are kept as they were: none of their points ran again
    assert all(by_hash[r["hash"]]["session"] == r["session"] for r in before)
    sessions = Counter(r["session"] for r in after)
    assert sorted(sessions.values()) == sorted([len(before), 1000 - len(before)])
    assert {r["status"] for r in after} == {"ok"}
    assert "flux_max < 0.01" in log and "worst 5 by flux_max" in log
    figures = {p.name for p in (out / "figures").iterdir()}
    assert {"distribution.png", "metric_vs_params.png"} <= figures


def test_the_same_file_on_a_dask_scheduler_and_two_workers_started_apart(tmp_path):
    sched_file = tmp_path / "scheduler.json"
    procs = [subprocess.Popen([sys.executable, "-m", "dask", "scheduler", "--host",
                               "127.0.0.1", "--port", "0", "--no-dashboard",
                               "--scheduler-file", str(sched_file)], cwd=tmp_path, env=env(),
                              stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)]
    try:
        t0 = time.monotonic()
        while not sched_file.exists() or not sched_file.read_text().strip():
            assert procs[0].poll() is None and time.monotonic() - t0 < 120
            time.sleep(0.2)
        address = json.loads(sched_file.read_text())["address"]
        assert address.startswith("tcp://127.0.0.1:")
        for _ in range(2):
            procs.append(subprocess.Popen(
                [sys.executable, "-m", "dask", "worker", address, "--nthreads", "1",
                 "--host", "127.0.0.1", "--no-dashboard"], cwd=tmp_path, env=env(),
                stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL))
        out = tmp_path / "mc"
        run = campaign(str(MC), "--out", str(out), "--scheduler", address,
                       log=tmp_path / "run.log")
        status = finish(run)
        log = (tmp_path / "run.log").read_text()
        assert status in (0, 1), (tmp_path / "run.err").read_text()
        assert f"running on Dask scheduler {address}" in log
        rows = table(out)
        assert len(rows) == 1000 and {r["status"] for r in rows} == {"ok"}
        assert len({r["worker"] for r in rows}) == 2  # both workers ran points
    finally:
        for p in reversed(procs):
            p.terminate()
        for p in procs:
            try:
                p.wait(30)
            except subprocess.TimeoutExpired:
                p.kill()


def test_a_point_that_kills_its_worker_is_a_row_and_the_others_run(tmp_path):
    from test_campaign import STUCK_CONTROLLER

    (tmp_path / "stuck_ctl.py").write_text(STUCK_CONTROLLER)
    camp = tmp_path / "c.toml"
    camp.write_text("""
[campaign]
name = "deadly"
[base]
profile = "profiles/quick.toml"
[grid]
controller = ["paper", "stuck_ctl:Dies"]
duration = ["10ms", "20ms", "30ms"]
""")
    out = tmp_path / "out"
    p = campaign(str(camp), "--out", str(out), "--workers", "2", extra=(tmp_path,),
                 log=tmp_path / "run.log")
    assert finish(p) == 1
    assert "Traceback" not in (tmp_path / "run.err").read_text()
    rows = table(out)
    assert len(rows) == 6
    for r in rows:
        if r["controller"] == "paper":
            assert r["status"] == "ok"
        else:
            assert r["status"] == "worker-died" and r["exit_status"] == 137
            assert "died" in r["stop_reason"]


def test_the_local_clusters_workers_run_one_thread_without_the_stack_profiler():
    """The local cluster's workers: one thread each, and Dask's statistical profiler off
    (it samples every thread's stack every 10 ms: a tenth of a worker's time on short
    points)."""
    import dask

    from gateway.campaign.engine import DaskEngine
    from gateway.campaign.options import Command

    engine = DaskEngine(Command.SIMULATE, workers=1)
    try:
        assert list(engine.client.nthreads().values()) == [1]
        seen = engine.client.run(
            lambda: dask.config.get("distributed.worker.profile.enabled"))
        assert list(seen.values()) == [False]
    finally:
        engine.close()
