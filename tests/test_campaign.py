"""`hil-gateway campaign`: the campaign file, its points, the table, in this process.

The Dask engine (a local cluster, Ctrl-C, a killed worker, an external scheduler) is
tests/test_campaign_dask.py.
"""

from __future__ import annotations

import csv
import json
import shlex
import subprocess
import sys
from pathlib import Path

import pyarrow.parquet as pq
import pytest

from gateway.campaign.model import Op, load_campaign, parse_campaign
from gateway.campaign.options import Command, command_options
from gateway.campaign.points import plan
from gateway.campaign.summary import criteria_of, passes
from gateway.cli import main
from gateway.errors import UserError

ROOT = Path(__file__).resolve().parents[1]


def campaign(text: str, source: str = "c.toml"):
    return parse_campaign(text, source, command_options)


def write(path: Path, text: str) -> Path:
    path.write_text(text, encoding="utf-8")
    return path


SMALL = """
[campaign]
name = "small"
command = "simulate"
[base]
profile = "profiles/quick.toml"
duration = "250ms"
estimator = "drift-free"
[grid]
"plant.motor.Rs" = [0.9, 1.1]
[random]
n = 2
seed = 3
"plant.motor.J" = {dist = "uniform", low = 0.8, high = 1.2}
[pass]
speed_rms = "< 0.2"
"""


def cli(*args: str, cwd: Path = ROOT, env: dict | None = None, timeout: float = 300
        ) -> subprocess.CompletedProcess:
    return subprocess.run([sys.executable, "-m", "gateway", *args], capture_output=True,
                          text=True, cwd=cwd, env=env, timeout=timeout)


# ------------------------------------------------------------------------- the file


def test_grid_crossed_with_random_draws_and_draws_kept_when_n_grows():
    c = campaign(SMALL)
    assert c.size == 4 and c.command is Command.SIMULATE
    points, same = plan(c, ROOT)
    assert same == 0 and len(points) == 4
    assert [p.values["plant.motor.Rs"] for p in points] == [0.9, 0.9, 1.1, 1.1]
    js = [p.values["plant.motor.J"] for p in points]
    assert js[0] == js[2] and js[1] == js[3] and js[0] != js[1]  # the same draw per grid point
    assert all(0.8 <= j <= 1.2 for j in js)
    more, _ = plan(campaign(SMALL.replace("n = 2", "n = 5")), ROOT)
    assert [p.values["plant.motor.J"] for p in more[:2]] == js[:2]
    assert {p.hash for p in more} > {p.hash for p in points}
    assert "Rs = 0.9\n" in points[0].plant[0] and "J = " in points[0].plant[0]
    assert points[0].argv[0] == f"--reference={(ROOT / 'profiles/quick.toml').resolve()}"
    assert points[0].options[0] == "--reference=profiles/quick.toml"
    assert [str(x) for x in c.criteria] == ["speed_rms < 0.2"]


def test_identical_points_run_once_and_the_hash_follows_file_content(tmp_path):
    prof = tmp_path / "p.toml"
    prof.write_bytes((ROOT / "profiles/quick.toml").read_bytes())
    text = f"""
[campaign]
name = "dup"
[base]
profile = "{prof}"
[grid]
delay = [1, 1, 0]
"""
    points, same = plan(campaign(text), tmp_path)
    assert len(points) == 2 and same == 1
    prof.write_text(prof.read_text() + "\n# edited\n")
    again, _ = plan(campaign(text), tmp_path)
    assert {p.hash for p in again}.isdisjoint({p.hash for p in points})


def test_plant_keys_go_into_the_named_scenario_and_settings_tables_set_several_options():
    text = """
[campaign]
name = "mix"
[base]
plant = "rs+10"
[grid]
"plant.sensors.noise" = [0.0, 0.005]
variant = [{label = "true flux", flux = "true"},
           {label = "adaptive", estimator = "rs-adaptive", discretisation = "euler"}]
"""
    points, _ = plan(campaign(text), ROOT)
    assert len(points) == 4
    p = points[3]
    assert p.values == {"plant.sensors.noise": 0.005, "variant": "adaptive"}
    scenario = p.plant[0]
    assert "Rs = 1.1" in scenario and "noise = 0.005" in scenario  # rs+10's, and the axis'
    assert "--estimator=rs-adaptive" in p.argv and "--discretisation=euler" in p.argv
    assert p.plant_changed
    q = plan(campaign(text.replace('"plant.sensors.noise" = [0.0, 0.005]\n', "")), ROOT)[0][0]
    assert not q.plant_changed and "--plant=rs+10" in q.options  # reproduced by its name


def test_bus_fault_keys_are_set_in_every_fault_of_the_named_scenario():
    text = """
[campaign]
name = "faults"
command = "sim"
[base]
plant = "bus-drop"
[grid]
"bus.probability" = [0.1, 0.5]
"""
    points, _ = plan(campaign(text), ROOT)
    assert [p.values["bus.probability"] for p in points] == [0.1, 0.5]
    scenario = points[1].plant[0]
    assert "probability = 0.5" in scenario and 'kind = "drop"' in scenario
    assert points[1].plant_changed
    with pytest.raises(UserError) as exc:
        plan(campaign(text.replace('plant = "bus-drop"\n', "")), ROOT)
    assert "has no [[bus.fault]]" in str(exc.value) and "bus-drop" in str(exc.value)


@pytest.mark.parametrize(("text", "words"), [
    ('[campaign]\nname = "x"\n[base]\nperiode = "1ms"\n',
     ["'periode' is not an option", "period"]),
    ('[campaign]\nname = "x"\n[base]\nout = "d"\n', ["'out' cannot be set by a campaign"]),
    ('[campaign]\nname = "x"\n[grid]\n"bus.fault.kind" = ["drop"]\n', ["bus.probability"]),
    ('[campaign]\nname = "x"\n[pass]\nspeed_rms = 0.05\n', ['e.g. "< 0.05"']),
    ('[campaign]\nname = "x"\n[pass]\nspeed = "< 1"\n', ["'speed' is not a metric", "speed_rms"]),
    ('[campaign]\nname = "x"\n[base]\nidentify = "yes"\n', ["--identify is a flag"]),
    ('[campaign]\nname = "x"\n[random]\nJ = {dist = "uniform", low = 1}\n',
     ["J: give high as a finite number"]),
    ('[campaign]\nname = "x"\n[random]\n"plant.motor.J" = {dist = "gauss"}\n',
     ["uniform, loguniform, normal"]),
    ('[campaign]\nname = "x"\n[grid]\n"plant.motors.J" = [1]\n', ["plant.<table>.<key>"]),
    ('[campaign]\nname = "x"\ncommand = "run"\n', ['"simulate"', '"sim"']),
    ('[campaign]\nname = "x"\n[grid]\nperiod = ["1ms"]\n"period" = 2\n', ["not valid TOML"]),
])
def test_a_bad_campaign_file_is_named_with_its_key_and_the_fix(text, words):
    with pytest.raises(UserError) as exc:
        campaign(text)
    assert str(exc.value).startswith("c.toml")
    for w in words:
        assert w in str(exc.value)


def test_criteria_need_a_finite_value_and_a_point_that_ran():
    c = campaign('[campaign]\nname = "x"\n[pass]\nspeed_rms = "<= 0.1"\nexit_status = "== 0"\n')
    assert c.criteria[0].op is Op.LE
    meta = {"criteria": [{"metric": k.metric, "op": k.op.value, "threshold": k.threshold}
                         for k in c.criteria]}
    crit = criteria_of(meta)
    ok = {"status": "ok", "speed_rms": 0.1, "exit_status": 0}
    assert passes(ok, crit)
    assert not passes({**ok, "speed_rms": float("nan")}, crit)
    assert not passes({**ok, "speed_rms": None}, crit)
    assert not passes({**ok, "status": "stopped"}, crit)


def test_the_shipped_campaigns_load_and_plan():
    sizes = {}
    for path in sorted((ROOT / "campaigns").glob("*.toml")):
        c = load_campaign(path)
        points, same = plan(c, ROOT)
        sizes[c.name] = (len(points), same)
    assert sizes["motor-population"] == (1000, 0)
    # bench/robustness.py's 199 cases, three of them in two blocks (run once)
    assert sizes["robustness"] == (174, 25)  # its identify = false rows are its others
    assert sizes["period-delay"] == (32, 0)


# ------------------------------------------------------------------- running here


def test_a_simulate_campaign_of_bus_faults_runs_each_point_on_the_pdo_link(tmp_path, capsys):
    """`bus.<key>` axes on `simulate`: each point injects its faults on the PDO link, the
    table has the bus loop's account (missed cycles) and the stop of each."""
    camp = write(tmp_path / "faults.toml", """
[campaign]
name = "faults"
command = "simulate"
[base]
reference = "profiles/quick.toml"
plant = "bus-delay"
[grid]
"bus.probability" = [0.1, 0.5]
""")
    out = tmp_path / "out"
    assert main(["campaign", str(camp), "--out", str(out), "--in-process"]) == 0
    rows = pq.read_table(out / "results.parquet").to_pylist()
    assert [r["bus.probability"] for r in sorted(rows, key=lambda r: r["point"])] == [0.1, 0.5]
    assert all(r["status"] == "ok" and r["stop"] == "END_OF_PROFILE" for r in rows)
    missed = {r["bus.probability"]: r["missed_cycles"] for r in rows}
    assert 0 < missed[0.1] < missed[0.5]  # more frames delayed, more cycles missed


def test_in_process_campaign_table_summary_resume_and_reproduction(tmp_path, capsys):
    camp = write(tmp_path / "small.toml", SMALL)
    out = tmp_path / "out"
    status = main(["campaign", str(camp), "--out", str(out), "--in-process", "--csv"])
    text = capsys.readouterr()
    assert status in (0, 1)
    assert "4 points of `simulate`; 0 already in" in text.out
    assert "speed_rms < 0.2" in text.out and "worst 4 by speed_rms" in text.out
    assert "points/s" in text.err  # the progress bar
    table = pq.read_table(out / "results.parquet")
    rows = table.to_pylist()
    assert len(rows) == 4 and {r["status"] for r in rows} == {"ok"}
    assert {r["point"] for r in rows} == {0, 1, 2, 3}
    assert table.schema.field("plant.motor.Rs").type == "double"
    assert all(r["speed_rms"] > 0 and r["speed_max"] >= r["speed_rms"] for r in rows)
    assert all(r["speed_max_w1"] is not None for r in rows)  # per window
    assert all(r["exit_status"] == 0 and r["wall_time_s"] > 0 for r in rows)
    assert not any(r["run_dir"] for r in rows) and not (out / "runs").exists()
    meta = json.loads(table.schema.metadata[b"can_drive_hil.campaign"])
    assert meta["name"] == "small" and meta["text"] == SMALL
    with (out / "results.csv").open(newline="") as f:
        csv_rows = list(csv.DictReader(f))
    assert [r["hash"] for r in csv_rows] == [r["hash"] for r in rows]
    assert float(csv_rows[0]["speed_rms"]) == rows[0]["speed_rms"]
    assert {p.name for p in (out / "figures").iterdir()} == {
        "metric_vs_params.png", "distribution.png",
        "map_plant.motor.Rs__plant.motor.J.png"}
    assert status == (0 if all(r["speed_rms"] < 0.2 for r in rows) else 1)

    # the same command again: nothing runs, the same rows
    assert main(["campaign", str(camp), "--out", str(out), "--in-process"]) == status
    assert "4 already in" in capsys.readouterr().out
    again = pq.read_table(out / "results.parquet").to_pylist()
    assert [r["session"] for r in again] == [r["session"] for r in rows]

    # the worst point's command, alone, gives its metrics again
    worst = max(rows, key=lambda r: r["speed_rms"])
    line = next(ln.strip() for ln in text.out.splitlines()
                if ln.strip().startswith("hil-gateway simulate")
                and f"{worst['point']:05d}-" in ln)
    words = shlex.split(line)[1:]
    assert main([*words, "--out", str(tmp_path / "alone")]) == 0
    alone = json.loads((tmp_path / "alone" / "summary.json").read_text())
    assert alone["speed_error"]["rms"] == worst["speed_rms"]

    # show redraws from the table alone
    (out / "campaign.json").unlink()
    for p in (out / "figures").iterdir():
        p.unlink()
    assert main(["campaign", "show", str(out / "results.parquet"), "--metric", "flux_max"]) == 0
    shown = capsys.readouterr().out
    assert "campaign small: 4 points" in shown and "worst 4 by flux_max" in shown
    assert (out / "figures" / "distribution.png").exists()


def test_points_past_their_time_limit_and_points_that_fail_are_rows(tmp_path):
    """A long point is stopped at its time limit (a row 'timeout' with what it computed),
    a point refused by its inputs is a row 'error' with the message, a diverging one
    'stopped' with its run directory kept; the others are unaffected."""
    camp = write(tmp_path / "c.toml", """
[campaign]
name = "mixed"
[base]
profile = "profiles/zero-speed.toml"
discretisation = "euler"
identify = false
[grid]
variant = [{label = "fine", duration = "100ms"},
           {label = "long", duration = "3000s", allow-long = true},
           {label = "runaway", estimator = "drift-free", plant = "rs+10"},
           {label = "refused", duration = "100ms", "plant.motor.M" = 5.0}]
""")
    out = tmp_path / "out"
    p = cli("campaign", str(camp), "--out", str(out), "--in-process", "--timeout", "15s")
    assert p.returncode == 1, p.stderr
    assert "Traceback" not in p.stderr
    rows = {r["variant"]: r for r in pq.read_table(out / "results.parquet").to_pylist()}
    assert rows["fine"]["status"] == "ok" and rows["fine"]["run_dir"] is None
    assert rows["long"]["status"] == "timeout" and rows["long"]["exit_status"] == 124
    assert "time limit of 15 s" in rows["long"]["stop_reason"]
    assert 0 < rows["long"]["cycles"] < 3_000_000
    assert rows["runaway"]["status"] == "stopped" and rows["runaway"]["stop"] == "DIVERGED"
    kept = Path(rows["runaway"]["run_dir"])
    assert (kept / "summary.json").exists() and (kept / "signals.csv").exists()
    assert rows["refused"]["status"] == "error" and rows["refused"]["exit_status"] == 2
    assert "M" in rows["refused"]["stop_reason"]
    assert "status: 1 ok, 1 stopped (1 diverged), 1 error, 1 timeout" in p.stdout
    # --retry-failed runs the error and the timeout again, not the others
    p = cli("campaign", str(camp), "--out", str(out), "--in-process", "--timeout", "15s",
            "--retry-failed")
    assert "2 already in" in p.stdout and "2 to run" in p.stdout


def test_a_run_that_never_returns_is_left_behind_as_a_row(tmp_path):
    """A controller that blocks for ever ignores the stop request: the point becomes a row
    'timeout' after its grace, the campaign goes on to the next point."""
    (tmp_path / "stuck_ctl.py").write_text(STUCK_CONTROLLER)
    camp = write(tmp_path / "c.toml", """
[campaign]
name = "stuck"
[base]
profile = "profiles/quick.toml"
duration = "20ms"
[grid]
controller = ["stuck_ctl:Stuck", "paper"]
""")
    out = tmp_path / "out"
    import os

    env = {**os.environ, "PYTHONPATH": f"{ROOT}{os.pathsep}{tmp_path}"}
    p = cli("campaign", str(camp), "--out", str(out), "--in-process", "--timeout", "1s",
            env=env)
    assert "Traceback" not in p.stderr
    rows = {r["controller"]: r for r in pq.read_table(out / "results.parquet").to_pylist()}
    assert rows["stuck_ctl:Stuck"]["status"] == "timeout"
    assert "left behind" in rows["stuck_ctl:Stuck"]["stop_reason"]
    assert rows["paper"]["status"] == "ok"


def test_batch_sizes_balance_the_tail_only_when_several_points_run_at_once():
    """One point at a time: every batch is sized to about a second (small tail batches
    only add their table writes); several at once: the tail is spread over them."""
    from gateway.campaign.runner import BATCH_MAX, BatchSizer

    sizer = BatchSizer()
    assert sizer.size(100, 1) == 1  # nothing measured yet: one point first
    sizer.observe([0.01])
    assert sizer.size(10, 1) == min(BATCH_MAX, 100)
    assert sizer.size(10, 2) == 3  # ceil(10 / (2 batches in flight × 2))


def _points(n: int, plant: bool = False):
    from gateway.campaign.points import PointConfig

    return [PointConfig(i, f"h{i}", Command.SIMULATE,
                        ("--reference=profiles/quick.toml", "--duration=20ms"),
                        (f"[motor]\nRs = {1 + i / 100!r}\n", f"<p{i}>") if plant else None)
            for i in range(n)]


def test_a_batch_runs_in_one_thread_and_each_point_has_its_own_time_limit(monkeypatch):
    """The runner thread goes from point to point by itself; a point past its limit that
    stops is a 'timeout' row and the next points run with their own limits; a point that
    ignores the stop request is left behind and no later point of the batch starts."""
    import threading
    import time

    from gateway.campaign import runpoint

    plan_ = {0: 0.05, 1: 5.0, 2: 0.05, 3: 0.05, 4: None, 5: 0.05}
    threads, ran = set(), []

    def fake(point, limits, options, signals, t0):
        threads.add(threading.get_ident())
        ran.append(point.index)
        wait = plan_[point.index]
        if wait is None:  # ignores the stop request
            time.sleep(2.0)
        else:
            signals.requested.wait(wait)
        return runpoint.outcome(runpoint.PointStatus.OK, "fine", 0,
                                time.perf_counter() - t0, "END_OF_PROFILE")

    monkeypatch.setattr(runpoint, "_run_checked", fake)
    limits = runpoint.Limits(timeout=0.6, grace=0.3)
    t0 = time.perf_counter()
    result = runpoint.run_batch(_points(6), limits)
    took = time.perf_counter() - t0
    rows = result.outcomes
    assert [rows[f"h{i}"]["status"] for i in range(4)] == ["ok", "timeout", "ok", "ok"]
    assert "stopped (fine)" in rows["h1"]["stop_reason"]
    assert rows["h4"]["status"] == "timeout" and "left behind" in rows["h4"]["stop_reason"]
    assert result.abandoned and "h5" not in rows
    assert len(threads) == 1 and threading.get_ident() not in threads
    assert took < 0.6 + 0.3 + 0.6 + 0.3 + 1.0  # two time limits and graces, no more
    time.sleep(2.0)  # the left-behind point returns: the thread starts nothing after it
    assert ran == [0, 1, 2, 3, 4]


def test_points_that_differ_only_in_their_plant_share_their_checked_options():
    """A batch parses and checks a command line once for the points that share it; the
    run's inputs are those the command line makes, and each point has its own copy of
    the parsed options."""
    from gateway.campaign.options import shared_parser
    from gateway.campaign.runpoint import _Options
    from gateway.cli import simulate_inputs
    from gateway.sim import scenario_from_text

    options = _Options(shared_parser())
    a, b = _points(2, plant=True)
    args_a, checked_a = options.of(a)
    args_b, checked_b = options.of(b)
    assert checked_a is checked_b and args_a is not args_b and vars(args_a) == vars(args_b)
    plant = scenario_from_text(*b.plant)
    shared = simulate_inputs(args_b, plant, None, checked_b)
    alone = simulate_inputs(args_b, plant)
    assert shared.spec == alone.spec and shared.windows == alone.windows
    assert list(shared.spec.plant.motor_factors.values()) == [pytest.approx(1.01)]


STUCK_CONTROLLER = '''
import threading


class Stuck:
    """A controller whose first step never returns (it ignores every stop request)."""

    signals = ()
    requires = ()

    def __init__(self, context, params):
        pass

    def step(self, refs, sample):
        threading.Event().wait()

    def withhold(self):
        pass

    def coast(self):
        pass


class Dies:
    """A controller whose first step ends its process."""

    signals = ()
    requires = ()

    def __init__(self, context, params):
        pass

    def step(self, refs, sample):
        import os

        os._exit(3)

    def withhold(self):
        pass

    def coast(self):
        pass
'''


def test_bad_campaign_input_is_one_paragraph_and_exit_2(tmp_path):
    camp = write(tmp_path / "c.toml", SMALL.replace('duration = "250ms"', 'period = "1"'))
    write(tmp_path / "ok.toml", SMALL)
    p = cli("campaign", str(camp), "--out", str(tmp_path / "o"), "--in-process")
    assert p.returncode == 2 and "Traceback" not in p.stderr
    assert "point #0" in p.stderr and "--period" in p.stderr
    assert not (tmp_path / "o").exists()
    (tmp_path / "mine").mkdir()
    (tmp_path / "mine" / "notes.txt").write_text("mine")
    p = cli("campaign", str(camp.with_name("ok.toml")), "--out", str(tmp_path / "mine"),
            "--in-process")
    assert p.returncode == 2 and "not a campaign's directory" in p.stderr
    assert [f.name for f in (tmp_path / "mine").iterdir()] == ["notes.txt"]
    p = cli("campaign", "show", str(tmp_path))
    assert p.returncode == 2 and "not a campaign's table" in p.stderr
    p = cli("campaign", str(camp), "--workers", "2", "--in-process")
    assert p.returncode == 2 and "not allowed with argument" in p.stderr


def test_a_sim_point_runs_over_canopen_against_the_emulator(tmp_path, capsys):
    """`command = "sim"`: the point goes through `sim`'s own inputs and the bus loop; its
    run directory (the bus log) is removed again when the point ran to its end."""
    camp = write(tmp_path / "c.toml", """
[campaign]
name = "bus"
command = "sim"
[base]
profile = "profiles/quick.toml"
duration = "50ms"
[grid]
"plant.sensors.offset_a" = [0.01]
""")
    out = tmp_path / "out"
    assert main(["campaign", str(camp), "--out", str(out), "--in-process"]) == 0
    (row,) = pq.read_table(out / "results.parquet").to_pylist()
    assert row["status"] == "ok" and row["cycles"] == 50 and row["missed_cycles"] == 0
    assert row["command"] == "sim" and row["run_dir"] is None
    assert not any((out / "runs").iterdir())
    assert "hil-gateway sim --reference=profiles/quick.toml" in capsys.readouterr().out


def test_sigterm_stops_a_campaign_and_keeps_what_it_ran(tmp_path):
    """SIGTERM (as from a batch system) stops the campaign like Ctrl-C: exit 130, every
    point that came back in the table, the same command then runs only the others."""
    import signal
    import time

    camp = write(tmp_path / "c.toml", """
[campaign]
name = "long"
[base]
profile = "profiles/quick.toml"
duration = "20ms"
[random]
n = 120
"plant.motor.J" = {dist = "uniform", low = 0.8, high = 1.2}
""")
    out = tmp_path / "out"
    p = subprocess.Popen([sys.executable, "-m", "gateway", "campaign", str(camp), "--out",
                          str(out), "--in-process"], cwd=ROOT, stdout=subprocess.PIPE,
                         stderr=subprocess.PIPE, text=True)
    t0 = time.monotonic()
    while not list((out / "parts").glob("part-*.parquet")) if (out / "parts").is_dir() else True:
        assert p.poll() is None and time.monotonic() - t0 < 300
        time.sleep(0.1)
    p.send_signal(signal.SIGTERM)
    _, err = p.communicate(timeout=300)
    assert p.returncode == 130 and "Traceback" not in err
    rows = pq.read_table(out / "results.parquet").to_pylist()
    assert 0 < len(rows) < 120 and len({r["hash"] for r in rows}) == len(rows)
    again = cli("campaign", str(camp), "--out", str(out), "--in-process")
    assert f"{len(rows)} already in" in again.stdout
    assert len(pq.read_table(out / "results.parquet")) == 120


def test_report_of_a_campaign_is_one_page_with_its_points_criteria_and_figures(tmp_path,
                                                                               capsys):
    """`hil-gateway report DIR` on a campaign's directory: one self-contained page (the
    statuses, the criteria, the worst points and their commands, the figures embedded,
    the points worst first) into DIR/report.html."""
    import html as html_lib
    import re

    # the motor file's J held (J tracked on line, all four points would pass)
    camp = write(tmp_path / "small.toml", SMALL.replace('"< 0.2"', '"< 1.5"').replace(
        'estimator = "drift-free"', 'estimator = "drift-free"\ninertia = "file"'))
    out = tmp_path / "out"
    main(["campaign", str(camp), "--out", str(out), "--in-process"])
    rows = pq.read_table(out / "results.parquet").to_pylist()
    capsys.readouterr()
    assert main(["report", str(out)]) == 0
    assert capsys.readouterr().out.strip() == f"wrote {out / 'report.html'}"
    page = (out / "report.html").read_text(encoding="utf-8")
    text = html_lib.unescape(page)
    n_pass = sum(r["status"] == "ok" and r["speed_rms"] < 1.5 for r in rows)
    assert 0 < n_pass < 4, "the threshold splits the points (else pick another)"
    assert f"{n_pass} of 4 points passed every criterion" in text
    assert 'class="status bad"' in page
    assert "<td>speed_rms &lt; 1.5</td>" in page  # the criterion's row
    assert re.search(rf"<td>speed_rms &lt; 1.5</td><td class=\"num\">{n_pass}</td>"
                     rf"<td class=\"num\">{4 - n_pass}</td>", page)
    assert page.count("data:image/png;base64,") == 3  # vs params, map, distribution
    assert "src=\"http" not in page and "<script src" not in page  # opens offline
    worst = max(rows, key=lambda r: r["speed_rms"])
    assert "hil-gateway simulate" in text and f"{worst['point']:05d}-" in text
    body = text[text.index("<h2>Points (4)</h2>"):]
    order = [int(m) for m in re.findall(r"<tr><td class=\"num\">(\d+)</td>", page[
        page.index("<h2>Points (4)</h2>"):])]
    assert order[0] == worst["point"] or not any(
        r["point"] == order[0] and r["speed_rms"] < 1.5 for r in rows)
    assert sorted(order) == [0, 1, 2, 3] and "results.parquet" not in body

    # -o elsewhere; a campaign with run directories is refused in one paragraph
    assert main(["report", str(out / "results.parquet"), "-o", str(tmp_path / "c.html")]) == 0
    assert (tmp_path / "c.html").is_file()
    p = cli("report", str(out), str(tmp_path), "-o", str(tmp_path / "x.html"))
    assert p.returncode == 2 and "one campaign" in p.stderr and "Traceback" not in p.stderr
