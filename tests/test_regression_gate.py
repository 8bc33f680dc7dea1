"""`hil-gateway compare --baseline`: the regression gate, its tolerance file and its JUnit
XML; the runs are honest short simulations of profiles/quick.toml."""

from __future__ import annotations

import json
import shutil
import xml.etree.ElementTree as ET
from pathlib import Path

import pytest

from gateway.cli import main
from gateway.gate import Verdict, evaluate
from gateway.tolerance import Direction, Limit, load_tolerances

ROOT = Path(__file__).resolve().parents[1]
QUICK = str(ROOT / "profiles" / "quick.toml")
EXAMPLE = str(ROOT / "examples" / "tolerance.toml")


@pytest.fixture(scope="module")
def runs(tmp_path_factory):
    """The baseline, the same run again, and the same controller on a motor whose stator
    resistance is 10 % above what the controller believes (its RMS speed error grows from
    mrad/s to rad/s), all without the standstill identification (which would find it)."""
    base = tmp_path_factory.mktemp("gate")
    for name, extra in (("base", ()), ("same", ()), ("warm", ("--plant", "rs+10"))):
        assert main(["simulate", "--profile", QUICK, "--no-identify", "--out",
                     str(base / name), *extra]) == 0
    return base


def _gate(capsys, runs: Path, *names: str, tolerance: str = EXAMPLE, baseline: str = "base",
          junit: Path | None = None) -> tuple[int, str, str]:
    argv = ["compare", "--baseline", str(runs / baseline), *(str(runs / n) for n in names),
            "--tolerance", tolerance]
    if junit is not None:
        argv += ["--junit", str(junit)]
    code = main(argv)
    out = capsys.readouterr()
    return code, out.out, out.err


def _rows(stdout: str) -> dict[tuple[str, str], str]:
    """(run, metric) → result, from the printed table."""
    out = {}
    for line in stdout.splitlines():
        cells = line.split()
        if len(cells) >= 3 and cells[-1] in {v.value for v in Verdict}:
            out[(cells[0], cells[1])] = cells[-1]
    return out


def test_an_equal_run_passes(runs, tmp_path, capsys):
    junit = tmp_path / "gate.xml"
    code, out, err = _gate(capsys, runs, "same", junit=junit)
    assert code == 0, out + err
    limits = load_tolerances(Path(EXAMPLE))
    assert _rows(out) == {("same", lim.key): "pass" for lim in limits}
    assert "regression gate: passed, 5 checks within tolerance" in out
    root = ET.parse(junit).getroot()
    assert root.tag == "testsuites"
    assert (root.get("tests"), root.get("failures"), root.get("errors")) == ("5", "0", "0")
    cases = root.findall("./testsuite/testcase")
    assert [c.get("name") for c in cases] == [lim.key for lim in limits]
    assert not root.findall(".//failure") and not root.findall(".//error")


def test_a_run_whose_rms_grew_past_the_tolerance_fails(runs, tmp_path, capsys):
    junit = tmp_path / "gate.xml"
    code, out, err = _gate(capsys, runs, "same", "warm", junit=junit)
    assert code == 1, out + err
    rows = _rows(out)
    assert rows[("warm", "speed_error.rms")] == "FAIL"
    assert rows[("same", "speed_error.rms")] == "pass"
    assert rows[("warm", "run.exit_status")] == "pass"  # it ran to its end, just worse
    base = json.loads((runs / "base" / "summary.json").read_text())["speed_error"]["rms"]
    warm = json.loads((runs / "warm" / "summary.json").read_text())["speed_error"]["rms"]
    assert warm > 100 * base  # honestly worse: R_s +10 % unknown to the controller
    failed = sum(v == "FAIL" for v in rows.values())
    assert f"regression gate: FAILED, {failed} of 10 checks failed" in out
    root = ET.parse(junit).getroot()
    assert (root.get("tests"), root.get("failures"), root.get("errors")) == (
        "10", str(failed), "0")
    suites = root.findall("testsuite")
    assert [s.get("name") for s in suites] == ["regression gate: same",
                                               "regression gate: warm"]
    assert [s.get("failures") for s in suites] == ["0", str(failed)]
    case = next(c for c in suites[1] if c.get("name") == "speed_error.rms")
    assert case.get("classname") == "warm"
    message = case.find("failure").get("message")
    assert message.startswith(f"speed_error.rms grew from {base:.4g} to {warm:.4g}")
    assert "abs 0.001 + rel 0.2 × |baseline|, growth" in message
    props = {p.get("name"): p.get("value") for p in suites[0].iter("property")}
    assert props == {"baseline": str(runs / "base"), "tolerance": EXAMPLE}


def test_only_growth_counts_unless_the_limit_says_otherwise(runs, tmp_path, capsys):
    """Against the worse run as the baseline, the better one passes an "up" limit and fails
    "down" and "both"."""
    tol = tmp_path / "t.toml"
    tol.write_text('"speed_error.rms" = { rel = 0.2 }\n'
                   '[speed_error.max]\nrel = 0.2\ndirection = "down"\n'
                   '[flux_error]\nrms = { rel = 0.2, direction = "both" }\n')
    code, out, _ = _gate(capsys, runs, "base", tolerance=str(tol), baseline="warm")
    assert code == 1
    assert _rows(out) == {("base", "speed_error.rms"): "pass",
                          ("base", "speed_error.max"): "FAIL",
                          ("base", "flux_error.rms"): "FAIL"}


@pytest.mark.parametrize(("rel", "abs_", "direction", "base", "value", "exceeded"), [
    (0.2, 0.0, "up", 1.0, 1.2, False),     # exactly the limit passes
    (0.2, 0.0, "up", 1.0, 1.2001, True),
    (0.2, 0.1, "up", -1.0, -0.7, False),   # |baseline|: 0.1 + 0.2
    (0.0, 0.0, "up", 1.0, 0.5, False),     # a decrease never fails "up"
    (0.0, 0.0, "down", 1.0, 0.5, True),
    (0.0, 0.5, "both", 1.0, 0.4, True),
    (0.0, 0.5, "both", 1.0, 1.5, False),
])
def test_the_limit_is_abs_plus_rel_times_the_baseline(rel, abs_, direction, base, value,
                                                      exceeded):
    lim = Limit("m", rel, abs_, Direction(direction))
    assert lim.exceeded(base, value) is exceeded
    checks = evaluate({"m": base}, [("r", {"m": value})], [lim])
    assert checks[0].verdict is (Verdict.FAIL if exceeded else Verdict.PASS)


def test_a_metric_that_is_not_a_number_in_the_run_fails():
    checks = evaluate({"a": {"rms": 1.0}}, [("r", {"a": {"rms": None}})], [Limit("a.rms")])
    assert checks[0].verdict is Verdict.FAIL and "null in summary.json" in checks[0].message


@pytest.mark.parametrize(("text", "said"), [
    ('"speed_error.windows.9.rms" = { rel = 0.2 }',
     "the baseline has no 'speed_error.windows.9.rms': under 'speed_error.windows' there is "
     "a list of 3 (index 0..2)"),
    ('"speed_error.median" = { rel = 0.2 }', "under 'speed_error' there is a table of"),
    ('"configuration.law" = { rel = 0.2 }',
     "'configuration.law' is str 'current-fed' in the baseline, not a number"),
    ('"speed_error" = { rel = 0.2 }', "'speed_error' is a table (speed_error.max"),
    ('"speed_error.windows" = { abs = 1 }', "'speed_error.windows' is a list of 3"),
])
def test_a_metric_that_cannot_be_compared_is_named_and_exits_2(runs, tmp_path, capsys, text,
                                                              said):
    tol = tmp_path / "t.toml"
    tol.write_text(text + '\n"speed_error.rms" = { rel = 0.2 }\n')
    junit = tmp_path / "gate.xml"
    code, out, err = _gate(capsys, runs, "same", tolerance=str(tol), junit=junit)
    assert code == 2 and said in err and "Traceback" not in err
    assert "cannot be compared" in err and "ERROR" in out and "could not be made" in out
    root = ET.parse(junit).getroot()  # CI still sees which check could not be made
    assert (root.get("tests"), root.get("failures"), root.get("errors")) == ("2", "0", "1")
    assert said in root.find(".//error").get("message")


def test_a_metric_missing_in_a_run_only_is_named(runs, tmp_path, capsys):
    run = Path(shutil.copytree(runs / "same", tmp_path / "old"))
    summary = json.loads((run / "summary.json").read_text())
    del summary["peak_current"]
    (run / "summary.json").write_text(json.dumps(summary))
    code = main(["compare", "--baseline", str(runs / "base"), str(run), "--tolerance",
                 EXAMPLE])
    err = capsys.readouterr().err
    assert code == 2 and "old has no 'peak_current': at the top there is a table of" in err


@pytest.mark.parametrize(("text", "said"), [
    ("speed_error.rms = [", "not valid TOML"),
    ("", "names no metric"),
    ('"speed_error.rms" = 0.2', "a limit is a table such as"),
    ('"speed_error.rms" = { rel = -0.2 }', "speed_error.rms.rel = -0.2: give a number ≥ 0"),
    ('"speed_error.rms" = { abs = "1e-3" }', "speed_error.rms.abs = '1e-3': give a number"),
    ('"speed_error.rms" = { rel = true }', "speed_error.rms.rel = True: give a number"),
    ('"speed_error.rms" = { relative = 0.2, abs = 1 }', "has relative, which a limit does "
                                                         "not know"),
    ('"speed_error.rms" = { rel = 0.2, direction = "sideways" }',
     "direction = 'sideways': give 'up', 'down', 'both'"),
])
def test_a_bad_tolerance_file_is_named_and_nothing_is_written(runs, tmp_path, capsys, text,
                                                             said):
    tol = tmp_path / "t.toml"
    tol.write_text(text + "\n")
    junit = tmp_path / "gate.xml"
    code, out, err = _gate(capsys, runs, "same", tolerance=str(tol), junit=junit)
    assert code == 2 and said in err and f"--tolerance {tol}" in err, err
    assert out == "" and not junit.exists()


def test_the_gates_options_need_each_other(runs, tmp_path, capsys):
    assert main(["compare", str(runs / "same"), "--tolerance", EXAMPLE]) == 2
    assert "--tolerance belongs to the regression gate" in capsys.readouterr().err
    assert main(["compare", "--baseline", str(runs / "base"), str(runs / "same")]) == 2
    assert "--baseline needs --tolerance" in capsys.readouterr().err
    assert main(["compare", "--baseline", str(tmp_path), str(runs / "same"),
                 "--tolerance", EXAMPLE]) == 2
    assert "is not a run directory (no summary.json)" in capsys.readouterr().err
    code, out, err = _gate(capsys, runs, "same", junit=tmp_path / "nodir" / "g.xml")
    assert code == 2 and "--junit" in err and "cannot write it" in err
    assert "wrote" not in out


def test_with_a_figure_asked_for_the_gate_draws_it(runs, tmp_path, capsys):
    out = tmp_path / "gate.png"
    code = main(["compare", "--baseline", str(runs / "base"), str(runs / "same"),
                 "--tolerance", EXAMPLE, "-o", str(out)])
    assert code == 0 and out.read_bytes()[:4] == b"\x89PNG"
    assert f"wrote {out}" in capsys.readouterr().out
