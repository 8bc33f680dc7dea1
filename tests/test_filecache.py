"""Parsed files kept while the files are unchanged (dbc/filecache.py), and its users: the
DBC reader, the drive-profile loader, the controllers' entry points."""

from __future__ import annotations

import os
import shutil
from pathlib import Path

import pytest

from dbc import codec
from dbc.filecache import FileMemo, file_id
from gateway.control.interface import registered
from gateway.drive_profile import load_drive_profile
from gateway.errors import UserError

ROOT = Path(__file__).resolve().parents[1]


def _touch_later(path: Path) -> None:
    """``path`` modified: its mtime moved 1 s on (a file system's clock may be coarse)."""
    st = path.stat()
    os.utime(path, ns=(st.st_atime_ns, st.st_mtime_ns + 1_000_000_000))


def test_a_value_is_built_once_while_its_files_are_unchanged(tmp_path):
    f = tmp_path / "a.txt"
    f.write_text("one")
    memo: FileMemo[str] = FileMemo()
    builds = []

    def build():
        builds.append(1)
        return f.read_text(), (f,)

    assert memo.get("k", build) == "one"
    assert memo.get("k", build) == "one"
    assert len(builds) == 1
    f.write_text("two!")  # another size
    assert memo.get("k", build) == "two!"
    f.write_text("thre")  # same size: the mtime tells
    _touch_later(f)
    assert memo.get("k", build) == "thre"
    assert len(builds) == 3


def test_a_vanished_or_new_file_builds_again_and_a_failed_build_keeps_nothing(tmp_path):
    f = tmp_path / "a.txt"
    memo: FileMemo[bool] = FileMemo()

    def build():
        if not f.exists():
            return False, (f,)
        if f.read_text() == "bad":
            raise ValueError("bad file")
        return True, (f,)

    assert memo.get("k", build) is False  # the file's absence is part of the value
    f.write_text("ok")
    assert memo.get("k", build) is True
    f.write_text("bad")
    with pytest.raises(ValueError, match="bad file"):
        memo.get("k", build)
    f.unlink()
    assert memo.get("k", build) is False
    assert file_id(f) is None


def test_the_memo_is_bounded_least_recently_used_first(tmp_path):
    memo: FileMemo[int] = FileMemo(size=2)
    calls: list[int] = []

    def build(n):
        return lambda: (calls.append(n) or n, ())

    memo.get(1, build(1))
    memo.get(2, build(2))
    memo.get(1, build(1))  # 1 used last: 2 goes first
    memo.get(3, build(3))
    assert len(memo) == 2
    memo.get(1, build(1))
    memo.get(2, build(2))
    assert calls == [1, 2, 3, 2]
    with pytest.raises(ValueError, match="at least one"):
        FileMemo(size=0)


def test_a_dbc_is_read_once_and_again_when_it_changed(tmp_path):
    dbc = tmp_path / "drive.dbc"
    shutil.copy(codec.DBC_PATH, dbc)
    first = codec.load_database(dbc)
    assert codec.load_database(dbc) is first
    assert codec.parse_dbc(dbc) is codec.parse_dbc(dbc)
    text = dbc.read_text()
    dbc.write_text(text.replace("TPDO1", "TPDOX", 1))
    again = codec.load_database(dbc)
    assert again is not first
    names = {m.name for m in again.messages}
    assert "TPDOX" in names and "TPDO1" not in names
    assert "TPDOX" in codec.parse_dbc(dbc)[0]
    dbc.write_text("this is not a DBC\n")
    with pytest.raises(ValueError, match="not a readable DBC"):
        codec.load_database(dbc)


def test_a_drive_profile_is_checked_again_when_its_eds_changed(tmp_path):
    for name in ("drive_standard.eds", "drive.dbc", "drive_ab.dbc"):
        src = ROOT / "dbc" / name
        if src.exists():
            shutil.copy(src, tmp_path / name)
    text = (ROOT / "gateway" / "drives" / "emulator.toml").read_text()
    eds_line = next(line for line in text.splitlines() if line.startswith("eds"))
    dbc_line = next(line for line in text.splitlines() if line.startswith("dbc"))
    shutil.copy(ROOT / "dbc" / "drive.eds", tmp_path / "drive.eds")
    prof_file = tmp_path / "drive.toml"
    prof_file.write_text(text.replace(eds_line, 'eds = "drive.eds"')
                         .replace(dbc_line, 'dbc = "drive.dbc"'))
    first = load_drive_profile(prof_file)
    assert load_drive_profile(prof_file) is first
    eds = tmp_path / "drive.eds"
    eds.write_text(eds.read_text().replace("[6040]", "[6040x]", 1))
    with pytest.raises(UserError):
        load_drive_profile(prof_file)


def test_the_registered_controllers_are_a_fresh_dict_each_time():
    names = registered()
    assert "paper" in names
    names.pop("paper")
    assert "paper" in registered()
