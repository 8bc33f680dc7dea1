"""`hil-gateway profile new-drive` on a standard CiA 402 drive (gateway/newdrive_standard.py):
a profile and DBC that load and pass `profile check`, in the best mode 0x6502 offers, with
the node's COB-IDs and the file's units (dbc/units402.py), TODO where it states none."""

from __future__ import annotations

import math
import tomllib
from pathlib import Path

import cantools
import pytest
from test_newdrive import BASE, I16, U32, var, write_eds

from dbc.units402 import decode_si_unit, standard_units
from gateway.cli import main
from gateway.drive_profile import load_drive_profile
from gateway.profilecheck import check_drive_profile

I8, I32 = 0x2, 0x4


def standard_objects(modes: int | None = 0x000003A5, **extra: dict[str, str]
                     ) -> dict[str, dict[str, str]]:
    """A standard CiA 402 drive written from the standard: targets and actual values of
    torque, velocity and position, rated torque 2.5 N·m, velocity in rev/min."""
    objs = {**BASE,
            "6060": var("Modes of operation", I8, "rw", False, "0"),
            "6061": var("Modes of operation display", I8, "ro", False, "0"),
            "6071": var("Target torque", I16, "rww"),
            "6077": var("Torque actual value", I16, "ro"),
            "6076": var("Motor rated torque", U32, "rw", False, "2500"),
            "60FF": var("Target velocity", I32, "rww"),
            "606C": var("Velocity actual value", I32, "ro"),
            "607A": var("Target position", I32, "rww"),
            "6064": var("Position actual value", I32, "ro"),
            "60A9": var("SI unit velocity", U32, "rw", False, "0x00B44700")}
    if modes is not None:
        objs["6502"] = var("Supported drive modes", U32, "ro", False, f"0x{modes:08X}")
    objs.update(extra)
    return objs


def new_drive(tmp_path: Path, objs, node: int = 23, *args: str, suffix: str = ".eds"):
    eds = write_eds(tmp_path / f"servo{suffix}", objs, product="Std servo")
    out = tmp_path / "profiles" / "servo.toml"
    assert main(["profile", "new-drive", "--eds", str(eds), "--node", str(node), "-o",
                 str(out), *args]) == 0
    return out, tomllib.loads(out.read_text()), cantools.database.load_file(
        str(out.with_suffix(".dbc")))


def test_a_standard_drive_gets_a_profile_that_loads_and_passes_its_check(tmp_path, capsys):
    out, data, db = new_drive(tmp_path, standard_objects())
    said = capsys.readouterr().out
    assert "a standard CiA 402 drive, velocity mode" in said and "profile check" in said
    assert data["modes"] == {"velocity": 9, "torque": 10, "position": 8, "default": "velocity"}
    assert data["pdo"] == {"control": "RPDO1", "setpoints": "RPDO2", "currents": "TPDO1",
                           "remap": True}
    assert data["signals"] == {"T_e": "TPDO1.torque_actual", "w_m": "TPDO1.velocity_actual"}
    assert data["objects"]["RPDO1.target_velocity"] == "0x60FF.0"
    # node 23 in every COB-ID
    assert {m.name: m.frame_id for m in db.messages} == {"RPDO1": 0x217, "RPDO2": 0x317,
                                                          "TPDO1": 0x197}
    # scalings from the file: per mille of 2.5 N·m, rev/min; position assumed, marked TODO
    sig = {s.name: s for m in db.messages for s in m.signals}
    assert sig["target_torque"].scale == pytest.approx(0.0025)
    assert sig["velocity_actual"].scale == pytest.approx(2 * math.pi / 60)
    assert "TODO" in sig["target_position"].comment and "TODO" not in sig["target_torque"].comment
    header = out.read_text().split("[drive]")[0]
    assert "TODO: the file does not state the position unit" in header
    assert "--drive-mode torque (cyclic synchronous torque (CST, 10))" in header
    prof = load_drive_profile(out)
    assert prof.node == 23 and prof.default_mode.value == "velocity"
    report = check_drive_profile(out)
    assert report.ok and not report.modes[prof.default_mode]
    assert main(["profile", "check", str(out)]) == 0


@pytest.mark.parametrize("modes, default, values", [
    (0x00000200, "torque", {"torque": 10}),  # CST only
    (0x00000080, "position", {"position": 8}),  # CSP: the speed profile as position
    (0x00000004, "velocity", {"velocity": 3}),  # profile velocity
    (0x0000000C, "velocity", {"velocity": 3, "torque": 4}),  # PV and PT
])
def test_the_mode_is_the_best_0x6502_offers(tmp_path, modes, default, values):
    out, data, _ = new_drive(tmp_path, standard_objects(modes))
    assert data["modes"] == {**values, "default": default}
    assert check_drive_profile(out).ok


def test_without_0x6502_the_modes_come_from_the_targets_and_say_so(tmp_path):
    out, data, _ = new_drive(tmp_path, standard_objects(None))
    assert data["modes"]["default"] == "velocity"
    assert "no 0x6502 default" in out.read_text()


def test_factor_group_and_dcf_values(tmp_path):
    """A DCF: ParameterValue wins over DefaultValue (rated torque 4 N·m); 0x608F gives the
    position unit and, without 0x60A9, the velocity unit (position units per second)."""
    objs = standard_objects()
    del objs["60A9"]
    objs["6076"] = {**objs["6076"], "ParameterValue": "4000"}
    objs["608F"] = {"ParameterName": "Position encoder resolution", "ObjectType": "0x9",
                    "SubNumber": "3"}
    objs["608Fsub0"] = var("Highest sub-index supported", 0x5, "ro", False, "2")
    objs["608Fsub1"] = var("Encoder increments", U32, "rw", False, "4096")
    objs["608Fsub2"] = var("Motor revolutions", U32, "rw", False, "1")
    out, _, db = new_drive(tmp_path, objs, 5, suffix=".dcf")
    sig = {s.name: s for m in db.messages for s in m.signals}
    assert sig["target_torque"].scale == pytest.approx(0.004)
    assert sig["target_position"].scale == pytest.approx(2 * math.pi / 4096)
    assert sig["velocity_actual"].scale == pytest.approx(2 * math.pi / 4096)
    assert "TODO" not in out.read_text()


def test_scalings_from_a_vendor_dbc(tmp_path):
    vendor = tmp_path / "vendor.dbc"
    vendor.write_text('VERSION ""\n\nNS_ :\n\nBS_:\n\nBU_: DRIVE\n\n'
                      'BO_ 385 TxPDO1: 4 DRIVE\n'
                      ' SG_ Velocity_actual_value : 0|32@1- (0.01,0) [0|0] "rpm" Vector__XXX\n')
    _, _, db = new_drive(tmp_path, standard_objects(), 23, "--dbc", str(vendor))
    sig = {s.name: s for m in db.messages for s in m.signals}
    assert sig["velocity_actual"].scale == pytest.approx(0.01)
    assert "vendor DBC TxPDO1.Velocity_actual_value" in sig["velocity_actual"].comment


def test_a_bad_vendor_dbc_is_named(tmp_path, capsys):
    bad = tmp_path / "bad.dbc"
    bad.write_text("BO_ nonsense")
    eds = write_eds(tmp_path / "servo.eds", standard_objects())
    assert main(["profile", "new-drive", "--eds", str(eds), "--dbc", str(bad)]) == 2
    assert "--dbc" in capsys.readouterr().err


def test_a_mode_the_eds_does_not_offer_fails_profile_check(tmp_path):
    out, _, _ = new_drive(tmp_path, standard_objects())
    out.write_text(out.read_text().replace("velocity = 9", "velocity = 2"))
    report = check_drive_profile(out)
    assert not report.ok
    assert "does not offer" in report.not_offered[load_drive_profile(out).default_mode]


@pytest.mark.parametrize("value, si, text", [
    (0x00B44700, 2 * math.pi / 60, "rev/min"),
    (0xFDB44700, 2 * math.pi / 60000, "0.001 rev/min"),
    (0x00B40300, 2 * math.pi, "rev/s"),
    (0x00100300, 1.0, "rad/s"),
    (0x00414700, math.pi / 180 / 60, "°/min"),
])
def test_si_unit_velocity_decodes(value, si, text):
    got = decode_si_unit(value, with_time=True)
    assert got is not None and got[0] == pytest.approx(si) and got[1] == text


def test_unknown_si_units_are_not_guessed():
    assert decode_si_unit(0x00B49900, with_time=True) is None
    units = standard_units(lambda i, s: 0x00B49900 if i == 0x60A9 else None)
    # no unit the file states: CiA 402's default, one position unit (assumed) per second
    assert "velocity" in units.assumed and "position unit per second" in units.sources[
        "velocity"]


def test_canopeneditor_empty_keys_are_read_as_absent(tmp_path):
    """CANopenEditor writes `VendorNumber=` and similar empty keys: read as absent."""
    eds = write_eds(tmp_path / "servo.eds", standard_objects(), product="Std servo")
    eds.write_text(eds.read_text().replace(
        "VendorName=ACME drives", "VendorName=ACME drives\nVendorNumber=\nProductNumber=\n"
        "RevisionNumber=\nOrderCode=\nGranularity=\nDynamicChannelsSupported=").replace(
        "[6071]\n", "[6071]\nLowLimit=\nHighLimit=\n"))
    out = tmp_path / "servo.toml"
    assert main(["profile", "new-drive", "--eds", str(eds), "--node", "4", "-o",
                 str(out)]) == 0
    assert main(["profile", "check", str(out)]) == 0


def test_a_number_key_that_is_not_a_number_is_named_with_its_line(tmp_path, capsys):
    eds = write_eds(tmp_path / "servo.eds", standard_objects())
    lines = eds.read_text().splitlines()
    k = lines.index("[6071]") + 3  # its DataType
    assert lines[k].startswith("DataType=")
    lines[k] = "DataType=INTEGER16"
    eds.write_text("\n".join(lines))
    assert main(["profile", "new-drive", "--eds", str(eds)]) == 2
    err = capsys.readouterr().err
    assert f"line {k + 1}, [6071] DataType=INTEGER16" in err and "must be a number" in err
    assert "Traceback" not in err
