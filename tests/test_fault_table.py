"""README's fault table agrees with the code (gateway/stop.py) and the tests that inject
each fault (tests/test_faults.py, tests/test_gateway.py, tests/test_bus_faults.py, and the
lockstep and foreign-drive tests of the supervision's time base)."""

from __future__ import annotations

import re
from pathlib import Path

from gateway.stop import StopReason

ROOT = Path(__file__).resolve().parents[1]


def _table() -> list[list[str]]:
    text = (ROOT / "README.md").read_text(encoding="utf-8")
    start = text.index("| fault | `run.stop` |")
    rows = []
    for line in text[start:].splitlines()[2:]:
        if not line.startswith("|"):
            break
        rows.append([c.strip() for c in line.strip("|").split("|")])
    return rows


def test_every_stop_reason_has_a_row_and_every_row_a_reason():
    rows = _table()
    named = {m.group(1) for r in rows for m in [re.fullmatch(r"`(\w+)`", r[1])] if m}
    assert named == {r.name for r in StopReason}
    for r in rows:
        if r[1].startswith("`"):
            exit_status = StopReason[r[1].strip("`")].exit_status
            assert r[5] == str(exit_status), r


def test_every_row_names_tests_that_exist():
    sources = "".join((ROOT / "tests" / f).read_text(encoding="utf-8")
                      for f in ("test_faults.py", "test_gateway.py",
                                "test_lockstep_determinism.py", "test_foreign_drive.py",
                                "test_bus_faults.py"))
    for r in _table():
        tests = re.findall(r"`(test_\w+)`", r[6])
        assert tests, r
        for t in tests:
            assert f"def {t}(" in sources, t
