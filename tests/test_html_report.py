"""`hil-gateway report`: a run, or several, as one HTML page that opens offline."""

from __future__ import annotations

import base64
import json
import shutil
from html.parser import HTMLParser
from pathlib import Path

import pytest

from gateway import htmlreport
from gateway.cli import main

ROOT = Path(__file__).resolve().parents[1]
QUICK = str(ROOT / "profiles" / "quick.toml")


class Page(HTMLParser):
    """The tags, attributes, section titles and text of a page."""

    def __init__(self, text: str) -> None:
        super().__init__()
        self.tags: list[tuple[str, dict[str, str | None]]] = []
        self.text: list[str] = []
        self.headings: list[str] = []
        self.table_heads: list[str] = []
        self._in: list[str] = []
        self.feed(text)

    def handle_starttag(self, tag, attrs):
        self.tags.append((tag, dict(attrs)))
        self._in.append(tag)

    def handle_endtag(self, tag):
        if self._in and self._in[-1] == tag:
            self._in.pop()

    def handle_data(self, data):
        self.text.append(data)
        if self._in and self._in[-1] in ("h2", "h3"):
            self.headings.append(data)
        if self._in and self._in[-1] == "th":
            self.table_heads.append(data)

    def all(self, tag: str) -> list[dict[str, str | None]]:
        return [a for t, a in self.tags if t == tag]

    def plain(self) -> str:
        return "".join(self.text)


def _offline(page: Page) -> None:
    """Nothing on the page comes from elsewhere: no links to style sheets or scripts, every
    image inline, no address of another host."""
    assert not page.all("link") and not page.all("script")
    for attrs in page.all("img"):
        assert attrs["src"].startswith("data:image/png;base64,")
    for _, attrs in page.tags:
        for value in attrs.values():
            assert "http:" not in str(value) and "https:" not in str(value)


def _report(capsys, *args: str) -> tuple[int, str, str]:
    code = main(["report", *args])
    out = capsys.readouterr()
    return code, out.out, out.err


@pytest.fixture(scope="module")
def runs(tmp_path_factory):
    """A short simulation, the same over CANopen in this process (`sim`), a `sim` run with
    a fault injected on its bus, and a simulation that diverged and stopped early."""
    base = tmp_path_factory.mktemp("runs")
    assert main(["simulate", "--profile", QUICK, "--duration", "0.2s",
                 "--out", str(base / "simulated")]) == 0
    assert main(["sim", "--profile", QUICK, "--duration", "0.2s",
                 "--out", str(base / "bus")]) == 0
    assert main(["sim", "--profile", QUICK, "--plant", "bus-babble",
                 "--out", str(base / "babble")]) == 1
    assert main(["simulate", "--profile", str(ROOT / "profiles" / "zero-speed.toml"),
                 "--plant", "rs+10", "--estimator", "drift-free", "--discretisation", "euler",
                 "--no-identify", "--out", str(base / "diverged")]) == 1
    return base


def _copy(runs: Path, name: str, tmp_path: Path) -> Path:
    return Path(shutil.copytree(runs / name, tmp_path / name))


def test_a_simulated_run_becomes_one_page_in_its_directory(runs, tmp_path, capsys):
    run = _copy(runs, "simulated", tmp_path)
    code, out, err = _report(capsys, str(run))
    assert code == 0, err
    assert out.strip() == f"wrote {run / 'report.html'}"
    page = Page((run / "report.html").read_text(encoding="utf-8"))
    _offline(page)
    figures = sorted(run.glob("fig*.png"))
    assert len(figures) == 3
    embedded = [base64.b64decode(a["src"].split(",", 1)[1]) for a in page.all("img")]
    assert embedded == [p.read_bytes() for p in figures]  # each figure, whole, in order
    summary = json.loads((run / "summary.json").read_text())
    text = page.plain()
    assert "Stopped: END_OF_PROFILE" in text and "exit status 0" in text
    from gateway.report import format_si

    assert format_si(summary["speed_error"]["rms"], "rad/s") in text
    for w in summary["speed_error"]["windows"]:
        assert w["label"] in text
    assert {"Outcome", "Configuration", "Metrics", "Figures", "Per window"} <= set(
        page.headings)
    assert "Bus: timing and counters" not in page.headings  # a simulation has no bus
    # written again, it is replaced (a report is derived from the run, not a run)
    assert _report(capsys, str(run))[0] == 0
    assert not list(run.glob("*.tmp"))


def test_a_bus_run_shows_its_timing_counters_shutdown_and_faults(runs, tmp_path, capsys):
    run = _copy(runs, "bus", tmp_path)
    code, _, err = _report(capsys, str(run))
    assert code == 0, err
    page = Page((run / "report.html").read_text(encoding="utf-8"))
    _offline(page)
    text = page.plain()
    assert {"Bus: timing and counters", "Shutdown", "Faults", "TPDO events"} <= set(
        page.headings)
    for key in ("sync_period", "sync_to_tpdo", "reaction", "missed_cycles",
                "bus_frames_logged", "SWITCH_ON_DISABLED"):
        assert key in text
    assert "median, µs" in page.table_heads


def test_a_run_that_stopped_early_says_why_and_its_exit_status(runs, tmp_path, capsys):
    run = _copy(runs, "diverged", tmp_path)
    assert _report(capsys, str(run))[0] == 0  # the page is written; the run failed
    page_text = (run / "report.html").read_text(encoding="utf-8")
    page = Page(page_text)
    summary = json.loads((run / "summary.json").read_text())
    assert '<div class="status bad">' in page_text
    assert "Stopped: DIVERGED" in page.plain() and "exit status 1" in page.plain()
    assert summary["run"]["stop_reason"] in page.plain()


def test_injected_bus_faults_are_shown_with_the_reaction(runs, tmp_path, capsys):
    run = _copy(runs, "babble", tmp_path)
    assert _report(capsys, str(run))[0] == 0
    text = (run / "report.html").read_text(encoding="utf-8")
    page = Page(text)
    assert {"Injected bus faults and the reaction", "Reaction"} <= set(page.headings)
    assert {"fault", "kind", "acted"} <= set(page.table_heads)
    assert "Stopped: FOREIGN_WRITER" in page.plain() and '<div class="status bad">' in text
    assert "<td>{}</td>" not in text  # an empty table of TPDO events reads "none"


def test_sections_the_report_does_not_know_are_shown_as_tables(runs, tmp_path, capsys):
    """Keys a later version adds to summary.json (injected faults and the reactions to
    them, the drive's identity) appear under their own names."""
    run = _copy(runs, "simulated", tmp_path)
    summary = json.loads((run / "summary.json").read_text())
    summary["injected_faults"] = [
        {"t": 0.1, "fault": "EMCY 0x2310", "reaction": "DRIVE_FAULT", "cycles": 1},
        {"t": 0.15, "fault": "heartbeat lost", "reaction": "DRIVE_FAULT", "cycles": 3}]
    summary["drive_identity"] = {"vendor": 0, "product": "0x00000402",
                                 "check": {"passed": True, "checks": 12}}
    (run / "summary.json").write_text(json.dumps(summary))
    assert _report(capsys, str(run))[0] == 0
    page = Page((run / "report.html").read_text(encoding="utf-8"))
    assert {"Injected faults", "Drive identity"} <= set(page.headings)
    assert {"t", "fault", "reaction", "cycles", "check.passed"} <= set(page.table_heads)
    assert "heartbeat lost" in page.plain() and "0x00000402" in page.plain()


def test_a_run_that_never_finished_is_reported_from_its_marker(runs, tmp_path, capsys):
    run = tmp_path / "crashed"
    run.mkdir()
    summary = json.loads((runs / "bus" / "summary.json").read_text())
    marker = {"run": {"status": "running"}, "configuration": summary["configuration"]}
    (run / "running.json").write_text(json.dumps(marker))
    assert _report(capsys, str(run))[0] == 0
    page = Page((run / "report.html").read_text(encoding="utf-8"))
    assert "Did not finish" in page.plain() and "inprocess:hil-sim" in page.plain()
    assert "the run's results were never written" in page.plain()


def test_several_runs_make_one_comparison_page(runs, tmp_path, capsys, monkeypatch):
    out = tmp_path / "cmp.html"
    names = ("simulated", "bus", "diverged")
    code, stdout, err = _report(capsys, *(str(runs / n) for n in names), "-o", str(out))
    assert code == 0, err
    assert stdout.strip() == f"wrote {out}"
    text = out.read_text(encoding="utf-8")
    page = Page(text)
    _offline(page)
    assert text.count("<details") == 3
    ids = [a["id"] for _, a in page.tags if a.get("id")]
    assert len(ids) == len(set(ids))  # every run's sections have their own anchors
    figures = sum(len(list((runs / n).glob("fig*.png"))) for n in names)
    assert len(page.all("img")) == 1 + figures  # the errors overlaid, then each run's
    assert {"Outcome", "Metrics", "Configuration", "Errors overlaid"} <= set(page.headings)
    assert "DIVERGED" in page.plain() and "discretisation" in page.plain()
    for n in names:
        assert n in page.table_heads
    monkeypatch.chdir(tmp_path)  # without -o: ./compare.html
    assert _report(capsys, str(runs / "simulated"), str(runs / "bus"))[0] == 0
    assert (tmp_path / "compare.html").is_file()


def test_what_is_not_a_run_or_cannot_be_written_is_named(runs, tmp_path, capsys):
    code, out, err = _report(capsys, str(tmp_path))
    assert code == 2 and "is not a run directory (no summary.json" in err and out == ""
    assert not (tmp_path / "report.html").exists()
    run = _copy(runs, "simulated", tmp_path)
    code, out, err = _report(capsys, str(run), "-o", str(tmp_path / "r.txt"))
    assert code == 2 and "written as .html or .htm" in err
    (tmp_path / "afile").write_text("")
    target = tmp_path / "afile" / "r.html"
    code, out, err = _report(capsys, str(run), "-o", str(target))
    assert code == 2 and "cannot write the report to" in err and "Traceback" not in err
    assert "wrote" not in out  # never a false "wrote"
    (run / "summary.json").write_text('{"run": ')
    code, out, err = _report(capsys, str(run))
    assert code == 2 and "cannot be read" in err and not (run / "report.html").exists()


def test_force_removes_an_earlier_report(runs, tmp_path, capsys):
    run = _copy(runs, "simulated", tmp_path)
    assert _report(capsys, str(run))[0] == 0
    assert main(["simulate", "--profile", QUICK, "--duration", "0.05s", "--out", str(run),
                 "--force"]) == 0
    assert not (run / "report.html").exists()  # not a stale page of the earlier run


def test_the_controllers_own_figure_is_embedded_too(tmp_path, capsys):
    run = tmp_path / "ifoc"
    assert main(["simulate", "--profile", QUICK, "--duration", "0.1s", "--controller",
                 "ifoc", "--out", str(run)]) == 0
    assert (run / "fig4_controller.png").is_file()
    assert _report(capsys, str(run))[0] == 0
    page = Page((run / "report.html").read_text(encoding="utf-8"))
    assert [a["alt"] for a in page.all("img")] == list(htmlreport.FIGURES)
    assert "controller ifoc" in page.plain()  # the configuration's title
