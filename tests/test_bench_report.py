"""bench/report.py: the targets' table from the benchmarks' JSON, and BENCHMARKS.md's section.

The benchmarks themselves are tested in test_bench.py; here their JSON is given, so that the
verdicts, the failures and the file's handling are checked without timing anything.
"""

from __future__ import annotations

import importlib.util
import json
import sys
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]


@pytest.fixture(scope="module")
def report():
    spec = importlib.util.spec_from_file_location("bench_report_under_test",
                                                  ROOT / "bench" / "report.py")
    assert spec and spec.loader
    mod = importlib.util.module_from_spec(spec)
    sys.modules[spec.name] = mod  # dataclasses look their module up
    spec.loader.exec_module(mod)
    yield mod
    sys.modules.pop(spec.name, None)


#: What each benchmark's --json gave in a run that met every target (figures trimmed to
#: the keys the report reads).
GOOD = {
    "bench_control.py": {
        "exact_current_fed_cpu_us": 8.2, "euler_current_fed_cpu_us": 4.5,
        "recorded_current_fed_us": 27.9, "exact_full_order_cpu_us": 9.9,
        "euler_full_order_cpu_us": 4.9, "recorded_full_order_us": 35.0, "failed": {}},
    "bench_motulator.py": {
        "motulator": "0.5.0", "ratio": 43.0, "ours_x_real_time": 57.3,
        "motulator_250us_ZOH_x_real_time": 1.33, "ours_internal_rate_hz": 10000.0,
        "failed": {}},
    "bench_command.py": {
        "target_s": 1.0, "simulate_s": 0.6, "simulate_cpu_s": 1.0,
        "simulate_no_figures_s": 0.33, "recorded_simulate_s": 2.16, "demo_target_s": 2.0,
        "demo_s": 1.1, "demo_cpu_s": 1.4, "sim_s": 1.0, "recorded_sim_s": 2.82, "failed": {}},
    "bench_lean.py": {
        "lean_bits": 410, "lean_bus_time_us": 410.0, "lean_load_500us": 0.82,
        "default_bits": 765, "default_load_500us": 1.53, "default_min_period_us": 900.0,
        "lean_500us_missed": 0, "lean_500us_cycles": 5000, "lean_500us_rms_rad_s": 0.0024,
        "default_1ms_rms_rad_s": 0.0019, "failed": {}},
    "bench_loop.py": {"inprocess_cycles_per_s": 7082.0, "virtual_cycles_per_s": 3325.0,
                      "failed": {}},
    "bench_twoproc.py": {"where": "User-Mode Linux sandbox, Linux 6.1, 1 CPU(s)",
                         "lockstep_cycles_per_s": [187.0, 217.0, 186.0], "failed": {}},
}


def _fake_runs(report, monkeypatch, data: dict[str, dict | None]):
    """run_bench gives ``data[script]`` (None: the benchmark gave no figures)."""
    calls = []

    def fake(bench, quick, work, vcan=None):
        calls.append((bench.script, quick, vcan))
        got = data[bench.script]
        return (got, "") if got is not None else (None, f"{bench.script} gave no figures "
                                                         "(exit status 1)")
    monkeypatch.setattr(report, "run_bench", fake)
    return calls


def test_every_target_met_gives_exit_0_and_one_row_each(report, monkeypatch, capsys):
    calls = _fake_runs(report, monkeypatch, GOOD)
    assert report.main(["--quick", "--json"]) == 0
    out = capsys.readouterr().out
    rows = json.loads(out.strip().splitlines()[-1])["rows"]
    status = {r["target"]: r["status"] for r in rows}
    assert list(status.values()).count("met") == 9, status
    assert status[report.TWOPROC_ROW] == "not run"
    assert [c[0] for c in calls] == [b.script for b in report.BENCHES]
    assert all(quick for _, quick, _ in calls)
    assert "| controller step, current-fed law" in out and "8.20 µs" in out
    assert "Euler design 4.50 µs (× 1.82)" in out  # the baseline of the same run


def test_with_vcan_the_sandbox_rate_is_reported_with_its_kind(report, monkeypatch, capsys):
    calls = _fake_runs(report, monkeypatch, GOOD)
    assert report.main(["--vcan"]) == 0
    assert ("bench_twoproc.py", False, "auto") in calls
    out = capsys.readouterr().out
    assert "sandbox: auto | 187 | where: User-Mode Linux sandbox" in out  # median of runs
    assert "`.venv/bin/python bench/report.py --vcan`" in out
    calls.clear()
    assert report.main(["--vcan", "uml,qemu"]) == 0
    assert [c for c in calls if c[0] == "bench_twoproc.py"] == [
        ("bench_twoproc.py", False, "uml"), ("bench_twoproc.py", False, "qemu")]
    out = capsys.readouterr().out
    assert "(cycles/s), sandbox: uml |" in out and "(cycles/s), sandbox: qemu |" in out
    assert "report.py --vcan uml,qemu`" in out


def test_vcan_refuses_an_unknown_sandbox_kind(report, monkeypatch, capsys):
    calls = _fake_runs(report, monkeypatch, GOOD)
    with pytest.raises(SystemExit) as exc:
        report.main(["--vcan", "uml,docker"])
    assert exc.value.code == 2 and calls == []
    assert "name sandbox kinds from auto, uml, qemu" in capsys.readouterr().err


@pytest.mark.parametrize("script, key, value, target", [
    ("bench_control.py", "exact_current_fed_cpu_us", 10.5, "current-fed law"),
    ("bench_control.py", "exact_full_order_cpu_us", 12.01, "full-order law"),
    ("bench_motulator.py", "ratio", 39.9, "against motulator"),
    ("bench_command.py", "simulate_s", 1.01, "`hil-gateway simulate`"),
    ("bench_command.py", "demo_s", 2.2, "`scripts/demo`"),
    ("bench_lean.py", "lean_load_500us", 0.86, "bus time"),
    ("bench_lean.py", "lean_500us_missed", 1, "missed cycles"),
    ("bench_loop.py", "inprocess_cycles_per_s", 4999.0, "one process"),
])
def test_a_missed_target_is_marked_and_exits_1(report, monkeypatch, capsys, script, key,
                                               value, target):
    data = {**GOOD, script: {**GOOD[script], key: value}}
    _fake_runs(report, monkeypatch, data)
    assert report.main(["--json"]) == 1
    out, err = capsys.readouterr()
    rows = json.loads(out.strip().splitlines()[-1])["rows"]
    missed = [r["target"] for r in rows if r["status"] == "missed"]
    assert len(missed) == 1 and target in missed[0], missed
    assert "1 target(s) missed or not measured" in err and target in err


def test_a_benchmark_without_figures_fails_its_rows_and_the_others_are_kept(
        report, monkeypatch, capsys):
    data = {**GOOD, "bench_control.py": None,
            "bench_motulator.py": {"motulator": None, "ratio": None,
                                   "motulator_note": "not installed; install it with "
                                                     "`.venv/bin/pip install -e '.[bench]'`",
                                   "ours_x_real_time": 57.0, "ours_internal_rate_hz": 1e4,
                                   "failed": {}},
            "bench_lean.py": {**GOOD["bench_lean.py"], "lean_500us_missed": None,
                              "failed": {"lean_500us_missed": "run 1 of 3: run stopped in "
                                                              "cycle 12: EMCY 0x8130"}}}
    _fake_runs(report, monkeypatch, data)
    assert report.main(["--json"]) == 1
    out = capsys.readouterr().out
    got = json.loads(out.strip().splitlines()[-1])
    status = {r["target"]: r["status"] for r in got["rows"]}
    failed = got["failed"]
    assert sum(s == "failed" for s in status.values()) == 4, status
    assert failed[report.STEP_CF] == "bench_control.py gave no figures (exit status 1)"
    assert "pip install -e '.[bench]'" in next(v for k, v in failed.items()
                                               if "motulator" in k)
    assert "EMCY 0x8130" in next(v for k, v in failed.items() if "missed cycles" in k)
    assert status[report.RATE] == "met"  # ours was measured
    assert status[report.LOOP] == "met"


def test_write_replaces_its_section_only(report, monkeypatch, tmp_path, capsys):
    _fake_runs(report, monkeypatch, GOOD)
    path = tmp_path / "BENCHMARKS.md"
    path.write_text("# Benchmarks\n\nintro\n\n## Bus time\n\nold history\n")
    assert report.main(["--write", "--benchmarks", str(path)]) == 0
    first = path.read_text()
    assert first.startswith("# Benchmarks\n\nintro\n\n" + report.BEGIN + "\n## The "
                            "performance targets")
    assert first.endswith(report.END + "\n\n## Bus time\n\nold history\n")
    assert f"wrote {path}" in capsys.readouterr().out
    # a second run replaces the section in place; nothing else moves
    data = {**GOOD, "bench_loop.py": {**GOOD["bench_loop.py"],
                                      "inprocess_cycles_per_s": 6123.0}}
    _fake_runs(report, monkeypatch, data)
    assert report.main(["--write", "--benchmarks", str(path)]) == 0
    second = path.read_text()
    assert second.count(report.BEGIN) == 1 and second.count(report.END) == 1
    assert "| 6123 |" in second and "| 7082 |" not in second
    assert second.split(report.END)[1] == first.split(report.END)[1]
    assert second.split(report.BEGIN)[0] == first.split(report.BEGIN)[0]


def test_write_refuses_a_file_it_cannot_update_before_measuring(report, monkeypatch,
                                                                 tmp_path, capsys):
    calls = _fake_runs(report, monkeypatch, GOOD)
    missing = tmp_path / "nowhere" / "BENCHMARKS.md"
    assert report.main(["--write", "--benchmarks", str(missing)]) == 1
    err = capsys.readouterr().err
    assert f"cannot update {missing}" in err and "No such file" in err
    one_marker = tmp_path / "B.md"
    one_marker.write_text(f"# B\n\n{report.BEGIN}\n## old\n")
    assert report.main(["--write", "--benchmarks", str(one_marker)]) == 1
    assert "only one of the bench/report.py markers" in capsys.readouterr().err
    assert calls == []  # refused before any benchmark ran
    assert one_marker.read_text() == f"# B\n\n{report.BEGIN}\n## old\n"


def test_the_shipped_benchmarks_md_has_the_section(report):
    """BENCHMARKS.md carries the section report.py writes (one of each marker), so that
    `--write` updates it in place."""
    text = (ROOT / "BENCHMARKS.md").read_text()
    assert text.count(report.BEGIN) == 1 and text.count(report.END) == 1
    section = text.split(report.BEGIN)[1].split(report.END)[0]
    assert "## The performance targets, one run" in section
    assert section.count("\n| ") >= 11  # the header and the ten rows


@pytest.mark.parametrize("script, args", [
    ("bench_control.py", ["--quick"]),
    ("bench_motulator.py", ["--quick", "--t-sim", "0.02", "--repeats", "1"]),
    ("bench_command.py", ["--sim", "--repeats", "1"]),
    ("bench_lean.py", ["--repeats", "1"]),
    ("bench_loop.py", ["--quick", "--repeats", "1", "--realtime-seconds", "0"]),
])
def test_the_report_reads_what_each_benchmark_writes(report, tmp_path, script, args):
    """Each benchmark's real --json run (short) turned into its rows: every row measured
    (met or missed: the figures depend on the host), none failed for a key the report
    expects and the benchmark does not write. motulator is an extra: without it its row
    fails with the command that installs it."""
    import os
    import subprocess

    out = tmp_path / "figures.json"
    p = subprocess.run([sys.executable, str(ROOT / "bench" / script), *args, "--json",
                        str(out)], cwd=ROOT, capture_output=True, text=True, timeout=600,
                       stdin=subprocess.DEVNULL, env={**os.environ, "TMPDIR": str(tmp_path)})
    assert "Traceback" not in p.stdout + p.stderr, p.stdout + p.stderr
    data = json.loads(out.read_text())
    bench = next(b for b in report.BENCHES if b.script == script)
    rows = report.rows_of(bench, data, "")
    failed = report.rows_of(bench, None, "no figures")  # what a run without JSON shows
    assert [r.target for r in rows] == [r.target for r in failed]
    assert [r.goal for r in rows] == [r.goal for r in failed]
    assert all(r.figure == "FAILED: no figures" for r in failed)
    for row in rows:
        if row.status is report.Status.FAILED and script == "bench_motulator.py" \
                and data.get("motulator") is None:
            assert "pip install -e '.[bench]'" in row.figure, row
            continue
        assert row.status in (report.Status.MET, report.Status.MISSED), row
        assert row.value is not None and row.figure and row.baseline, row
    if script == "bench_lean.py":  # the deterministic part: bits and the lockstep run
        assert (data["lean_bits"], data["default_bits"]) == (410, 765)
        assert data["lean_500us_missed"] == 0 and data["lean_500us_cycles"] == 5000
        assert data["lean_500us_rms_rad_s"] < 0.005 and p.returncode == 0
