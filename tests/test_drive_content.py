"""What the master verifies of a drive beyond sizes: with ``remap = false`` the object each
mapping entry carries (index, sub-index, length) against its role; the drive profile's
start-up SDO writes ([[sdo]]), applied and read back; the mode of operation against 0x6502;
EDS records that lack sub-indices named, never a traceback."""

from __future__ import annotations

import json
import re
import shutil
from pathlib import Path

import pytest
from gw_support import gateway_run

import dbc
import gateway
from gateway.cli import main
from gateway.drive_profile import load_drive_profile
from gateway.errors import UserError


def _run(channel: str, profile: Path, out: Path, *args: str) -> int:
    return main(["run", "-i", "virtual", "-c", channel, "--drive", str(profile),
                 "--reference", "profiles/quick.toml", "--duration", "0.05s", "--out",
                 str(out), *args])


def _swap_currents_in_dbc(directory: Path) -> None:
    """The DBC says TX1 starts with Ia, then Ib; the drive maps phase B's object first."""
    dbc_file = directory / "foreign.dbc"
    text = dbc_file.read_text()
    text = text.replace(" Ib :", " TMP :").replace(" Ia :", " Ib :").replace(" TMP :", " Ia :")
    dbc_file.write_text(text)


def test_swapped_objects_are_refused_by_run_and_failed_by_check(foreign, tmp_path, capsys):
    drive, channel, profile = foreign(42)
    _swap_currents_in_dbc(tmp_path)
    rc = _run(channel, profile, tmp_path / "run")
    err = capsys.readouterr().err
    assert rc == 2
    assert "TX1.Ia): the drive maps 0x3101.0, the role needs 0x3100.0" in err, err
    assert "TX1.Ib): the drive maps 0x3100.0, the role needs 0x3101.0" in err, err
    assert not (tmp_path / "run").exists()  # a failed start leaves no directory
    assert drive.state != 0x0237  # never enabled
    rc = main(["check", "-i", "virtual", "-c", channel, "--drive", str(profile), "--json",
               str(tmp_path / "check.json")])
    out = capsys.readouterr().out
    assert rc == 1 and "0x3101.0" in out
    report = json.loads((tmp_path / "check.json").read_text())
    failed = [c for c in report["checks"] if not c["ok"]]
    assert failed and "TX1" in failed[0]["name"] + failed[0]["detail"]


def test_an_object_the_profile_cannot_name_is_not_taken_on_trust(foreign, tmp_path, capsys):
    _, channel, profile = foreign(42)
    text = profile.read_text()
    text = re.sub(r'(?m)^"TX1\.Ia" = .*\n', "", text)
    profile.write_text(text)
    rc = _run(channel, profile, tmp_path / "run")
    err = capsys.readouterr().err
    assert rc == 2
    assert "TX1.Ia): the EDS names no object for it" in err and "[objects]" in err


def test_startup_sdo_writes_are_applied_and_read_back(foreign, tmp_path):
    drive, channel, profile = foreign(42)
    profile.write_text(profile.read_text() + (
        '\n[[sdo]]\nindex = 0x3014\nsub = 0\nvalue = 123\nnote = "dynamometer torque"\n'))
    assert load_drive_profile(profile).sdo[0].describe() == \
        "0x3014.0 = 123 (dynamometer torque)"
    assert _run(channel, profile, tmp_path / "run") == 0
    assert drive.local.sdo[0x3014].raw == 123


def test_a_startup_write_that_reads_back_otherwise_is_named(foreign, tmp_path, capsys):
    drive, channel, profile = foreign(42)
    profile.write_text(profile.read_text() + "\n[[sdo]]\nindex = 0x3014\nsub = 0\nvalue = 5\n")

    def clamp(index, subindex, od):  # the drive limits the value it keeps
        return 2 if index == 0x3014 else None

    drive.local.add_read_callback(clamp)
    rc = _run(channel, profile, tmp_path / "run")
    err = capsys.readouterr().err
    assert rc == 2
    assert "start-up write 0x3014.0 = 5 was accepted but reads back 2" in err, err


@pytest.mark.parametrize("entry, message", [
    ("index = 0x3014\nsub = 0", "has no value"),
    ("index = 0x3014\nsub = 0\nvalue = 1\nsubindex = 2", "unknown key 'subindex'"),
    ("index = 0x3014\nsub = 0\nvalue = true", "value = True has the wrong type"),
    ("index = 0x9999\nsub = 0\nvalue = 1", "has no such object"),
    ("index = 0x3100\nsub = 0\nvalue = 1", "is ro, not writable"),
    ("index = 0x3014\nsub = 0\nvalue = 40000", "outside"),
    ("index = 0x3014\nsub = 0\nvalue = 1.5", "integer object"),
    ("index = 0x10\nsub = 0\nvalue = 1", "not an object of the object dictionary"),
])
def test_bad_startup_writes_are_refused_when_the_profile_loads(foreign, entry, message):
    _, _, profile = foreign(42)
    profile.write_text(profile.read_text() + f"\n[[sdo]]\n{entry}\n")
    with pytest.raises(UserError, match=re.escape(message)):
        load_drive_profile(profile)


def _emulator_profile_with_eds(tmp_path: Path, eds_edit) -> Path:
    """The emulator's drive profile with a copy of its EDS changed by ``eds_edit``."""
    eds = tmp_path / "drive.eds"
    eds.write_text(eds_edit(dbc.EDS_PATH.read_text()))
    shutil.copy(dbc.DBC_PATH, tmp_path / "drive.dbc")
    text = (Path(gateway.__file__).parent / "drives" / "emulator.toml").read_text()
    text = text.replace('"builtin:drive.eds"', '"drive.eds"').replace(
        '"builtin:drive.dbc"', '"drive.dbc"')
    path = tmp_path / "drive.toml"
    path.write_text(text)
    return path


def _drop_section(text: str, section: str) -> str:
    return re.sub(rf"(?ms)^\[{section}\]\n.*?(?=^\[)", "", text)


def test_an_rpdo_record_without_an_event_timer_is_a_note(emulator, tmp_path):
    emu = emulator()
    profile = _emulator_profile_with_eds(tmp_path, lambda t: _drop_section(t, "1400sub5"))
    assert gateway_run(emu, tmp_path / "run", "--drive", str(profile), "--reference",
                       "profiles/quick.toml", "--duration", "0.05s") == 0
    notes = " ".join(json.loads((tmp_path / "run" / "summary.json").read_text())
                     ["configuration_notes"])
    assert "RPDO1: 0x1400 has no sub-index 5 (event timer)" in notes


def test_a_mapping_record_too_small_is_named(emulator, tmp_path, capsys):
    emu = emulator()
    profile = _emulator_profile_with_eds(
        tmp_path, lambda t: _drop_section(_drop_section(t, "1A00sub4"), "1A00sub3"))
    rc = gateway_run(emu, tmp_path / "run", "--drive", str(profile))
    err = capsys.readouterr().err
    assert rc == 2 and "TPDO1: the DBC message has 4 signals" in err, err
    assert "0x1A00 has no sub-index 3, 4 in the EDS" in err and "Traceback" not in err


def test_a_mode_the_drive_does_not_offer_is_refused_by_0x6502(emulator, tmp_path, capsys):
    emu = emulator()
    profile = _emulator_profile_with_eds(tmp_path, lambda t: t)
    text = profile.read_text().replace("[modes]", "[modes]\nposition = 1", 1)
    text = text.replace('[drive]\n', '[drive]\n', 1)
    standard = (Path(gateway.__file__).parent / "drives" / "emulator-standard.toml").read_text()
    standard = standard.replace("position = 8", "position = 1")
    standard = standard.replace('"builtin:drive.eds"', f'"{dbc.EDS_PATH}"')
    standard = standard.replace('"builtin:standard.dbc"',
                                f'"{Path(dbc.__file__).parent / "standard.dbc"}"')
    path = tmp_path / "standard.toml"
    path.write_text(standard)
    rc = gateway_run(emu, tmp_path / "run", "--drive", str(path), "--drive-mode", "position",
                     "--controller", "stream")
    err = capsys.readouterr().err
    assert rc == 2, err
    assert "does not offer mode of operation profile position (PP, 1)" in err
    assert "cyclic synchronous position (CSP, 8)" in err  # what it offers instead
