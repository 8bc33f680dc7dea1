"""Documentation that ships with the project: no citation points outside the repository,
every `§E…`/`§C…` cited exists in docs/paper.md, the example motor file is the default."""

from __future__ import annotations

import re
import subprocess
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
TEXT_SUFFIXES = {".py", ".md", ".toml", ".txt", ".cfg", ""}


def shipped_files() -> list[Path]:
    """The repository's text files (tracked or new, not ignored), this test excluded."""
    out = subprocess.run(["git", "ls-files", "--cached", "--others", "--exclude-standard"],
                         cwd=ROOT, capture_output=True, text=True, check=True).stdout
    files = []
    for name in out.split():
        p = ROOT / name
        if p.is_file() and p.suffix in TEXT_SUFFIXES and p.name != Path(__file__).name:
            files.append(p)
    assert len(files) > 30
    return files


def paper_anchors() -> set[str]:
    text = (ROOT / "docs" / "paper.md").read_text()
    ids = set(re.findall(r'<a id="([ec]\d+)"></a>\n### §([EC]\d+) ', text))
    assert all(a == b.lower() for a, b in ids)
    return {b for _, b in ids}


def test_nothing_cites_a_file_outside_the_repository():
    bad = []
    for p in shipped_files():
        text = p.read_text(errors="replace")
        for needle in ("shared/paper", "ERRATA.md", "ERRATA "):
            if needle in text:
                bad.append(f"{p.relative_to(ROOT)}: {needle}")
    assert not bad


def test_every_paper_section_cited_exists():
    anchors = paper_anchors()
    assert {f"E{n}" for n in range(1, 13)} <= anchors
    cited: dict[str, list[str]] = {}
    for p in shipped_files():
        for ref in re.findall(r"§([EC]\d+)", p.read_text(errors="replace")):
            cited.setdefault(ref, []).append(str(p.relative_to(ROOT)))
    assert cited, "no code cites docs/paper.md"
    missing = {ref: where for ref, where in cited.items() if ref not in anchors}
    assert not missing
    for p in (ROOT / "README.md", ROOT / "docs" / "ARCHITECTURE.md"):
        for anchor in re.findall(r"paper\.md#([a-z0-9-]+)", p.read_text()):
            assert anchor.upper() in anchors, (p.name, anchor)


def test_docs_name_every_record_column_and_summary_key():
    from gateway.cycle import CycleRow
    from gateway.loop import LoopRow

    text = (ROOT / "docs" / "outputs.md").read_text()
    for col in (*CycleRow._fields, *LoopRow._fields):
        assert f"`{col}`" in text, col


def test_example_motor_file_is_the_paper_motor():
    from dbc.motor import MotorParams

    path = ROOT / "gateway" / "motors" / "paper.toml"
    assert MotorParams.from_toml(path) == MotorParams.paper()
    assert "gateway/motors/paper.toml" in (ROOT / "README.md").read_text()


@pytest.mark.parametrize("argv", [["--help"], ["simulate", "--help"], ["sim", "--help"],
                                  ["run", "--help"], ["compare", "--help"],
                                  ["report", "--help"], ["campaign", "--help"],
                                  ["campaign", "show", "--help"]])
def test_help_cites_only_shipped_files(argv, capsys):
    from gateway.cli import main

    with pytest.raises(SystemExit):
        main(argv)
    out = capsys.readouterr().out
    assert "shared/paper" not in out and "ERRATA" not in out
    for doc in re.findall(r"docs/[a-zA-Z_]+\.md", out):
        assert (ROOT / doc).exists(), doc


def test_user_facing_text_cites_no_issue_numbers(capsys):
    """README, the docs, BENCHMARKS.md, the shipped profiles and scenarios and every
    command's --help stand alone: users cannot see the project's issues."""
    from gateway.cli import main

    texts = {p: p.read_text(encoding="utf-8") for p in
             [ROOT / "README.md", ROOT / "BENCHMARKS.md", *(ROOT / "docs").glob("*.md"),
              *(ROOT / "gateway" / "profiles").glob("*.toml"),
              *(ROOT / "plant" / "scenarios").glob("*.toml"),
              *(ROOT / "campaigns").glob("*.toml")]}
    for argv in (["--help"], ["simulate", "--help"], ["sim", "--help"], ["run", "--help"],
                 ["compare", "--help"], ["report", "--help"], ["log", "--help"],
                 ["check", "--help"], ["campaign", "--help"], ["campaign", "show", "--help"]):
        with pytest.raises(SystemExit):
            main(argv)
        texts[" ".join(argv)] = capsys.readouterr().out
    for where, text in texts.items():
        found = re.findall(r"\bissues? #?\d+", text, flags=re.IGNORECASE)
        assert not found, (where, found)
