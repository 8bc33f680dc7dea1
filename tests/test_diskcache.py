"""dbc.diskcache: the parsed DBC kept on disk between processes (its parse and cantools'
import were 0.3 s of every command that encodes frames)."""

from __future__ import annotations

import pickle
from pathlib import Path

import pytest
from import_support import loaded_after

from dbc import codec, diskcache
from dbc.codec import DBC_PATH

ROOT = Path(__file__).resolve().parents[1]


@pytest.fixture
def cache(tmp_path, monkeypatch):
    monkeypatch.setenv("XDG_CACHE_HOME", str(tmp_path / "xdg"))
    monkeypatch.delenv("CAN_DRIVE_HIL_NO_CACHE", raising=False)
    return tmp_path / "xdg" / "can-drive-hil"


def _count(calls):
    def build():
        calls.append(1)
        return {"value": len(calls)}
    return build


def test_a_value_is_built_once_and_found_again(cache, tmp_path):
    f = tmp_path / "a.txt"
    f.write_text("one")
    calls: list[int] = []
    entry = diskcache.key("t", [f], [__file__])
    assert diskcache.cached(entry, _count(calls)) == {"value": 1}
    assert diskcache.cached(entry, _count(calls)) == {"value": 1}
    assert len(calls) == 1 and len(list(cache.glob("t-*.pickle"))) == 1
    assert not list(cache.glob(".*.tmp"))  # written atomically, nothing left behind
    f.write_text("two")  # a changed file is another key
    assert diskcache.key("t", [f], [__file__]) != entry
    assert diskcache.cached(diskcache.key("t", [f], [__file__]), _count(calls)) == {"value": 2}


def test_a_damaged_entry_an_unwritable_cache_and_no_cache_parse_again(cache, tmp_path,
                                                                     monkeypatch):
    f = tmp_path / "a.txt"
    f.write_text("one")
    entry = diskcache.key("t", [f], [__file__])
    calls: list[int] = []
    diskcache.cached(entry, _count(calls))
    (cache / f"{entry}.pickle").write_bytes(b"\x80\x05garbage")
    assert diskcache.cached(entry, _count(calls)) == {"value": 2}  # built again, rewritten
    assert pickle.loads((cache / f"{entry}.pickle").read_bytes()) == {"value": 2}
    monkeypatch.setenv("XDG_CACHE_HOME", "/proc/can-drive-hil-nowhere")
    assert diskcache.cached(entry, _count(calls)) == {"value": 3}
    monkeypatch.setenv("CAN_DRIVE_HIL_NO_CACHE", "1")
    assert diskcache.cache_dir() is None
    assert diskcache.cached(entry, _count(calls)) == {"value": 4}
    assert diskcache.key("t", [tmp_path / "absent-dir" / "x"], [__file__]) is None


def test_a_failing_build_caches_nothing(cache):
    def bad():
        raise ValueError("not a DBC")
    with pytest.raises(ValueError, match="not a DBC"):
        diskcache.cached("t-bad", bad)
    assert not (cache / "t-bad.pickle").exists()


def test_the_dbc_from_the_cache_is_the_parsed_one_and_needs_no_cantools(cache):
    fresh = codec._parse(DBC_PATH)
    kept = codec._parse_kept(DBC_PATH)  # parsed, and kept
    again = codec._parse_kept(DBC_PATH)  # from the disk
    assert pickle.dumps(again) == pickle.dumps(kept) == pickle.dumps(fresh)
    code = "from dbc import codec; codec.parse_dbc()"
    assert loaded_after(code, ("cantools",), {"XDG_CACHE_HOME": str(cache.parent)}) == []


def test_a_drive_profile_checked_once_is_not_checked_again_until_a_file_changes(cache,
                                                                              tmp_path):
    """The drive profile's EDS and DBC checks (python-canopen's import and the EDS read)
    are kept: a second process does not import canopen; a changed EDS is checked again."""
    import shutil

    from gateway.drive_profile import load_drive_profile
    from gateway.errors import UserError

    src = ROOT / "gateway" / "drives" / "emulator.toml"
    for name in ("drive.eds", "drive.dbc", "drive_ab.dbc"):
        if (DBC_PATH.parent / name).is_file():
            shutil.copy(DBC_PATH.parent / name, tmp_path / name)
    text = src.read_text().replace('"builtin:drive.eds"', '"drive.eds"').replace(
        '"builtin:drive.dbc"', '"drive.dbc"')
    prof = tmp_path / "drive.toml"
    prof.write_text(text)
    load_drive_profile(prof)
    assert len(list(cache.glob("drive-check-*.pickle"))) == 1
    code = ("from gateway.drive_profile import load_drive_profile; "
            f"load_drive_profile({str(prof)!r})")
    assert loaded_after(code, ("canopen",), {"XDG_CACHE_HOME": str(cache.parent)}) == []
    eds = tmp_path / "drive.eds"  # the EDS loses the statusword: checked again, refused
    eds.write_text(eds.read_text().replace("[6041]", "[6F41]"))
    with pytest.raises(UserError, match="0x6041"):
        load_drive_profile(prof)
