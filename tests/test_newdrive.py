"""`hil-gateway profile new-drive`: drive-profile skeletons from EDS files (gateway/newdrive.py)."""

from __future__ import annotations

import importlib.util
import re
import sys
import tomllib
from pathlib import Path

import cantools
import pytest

import dbc
import gateway
from dbc.cia301 import is_service
from gateway import newdrive
from gateway.cli import main
from gateway.drive_profile import load_drive_profile
from gateway.errors import UserError


def _gen_eds():
    path = Path(__file__).resolve().parents[1] / "tools" / "gen_eds.py"
    spec = importlib.util.spec_from_file_location("gen_eds", path)
    assert spec is not None and spec.loader is not None
    module = importlib.util.module_from_spec(spec)
    sys.modules["gen_eds"] = module
    spec.loader.exec_module(module)
    return module


def write_eds(path: Path, objects: dict[str, dict[str, str]], product: str = "Vendor drive"):
    """A small EDS: ``objects`` maps section names ("6040", "3100sub1") to their keys."""
    lines = ["[FileInfo]", "FileName=" + path.name, "FileVersion=1", "FileRevision=0",
             "EDSVersion=4.0", "", "[DeviceInfo]", "VendorName=ACME drives",
             "ProductName=" + product, "NrOfRXPDO=4", "NrOfTXPDO=4", ""]
    for section, keys in objects.items():
        lines.append(f"[{section}]")
        lines += [f"{k}={v}" for k, v in keys.items()]
        lines.append("")
    path.write_text("\n".join(lines), encoding="ascii")
    return path


def var(name: str, dtype: int, access: str, pdo: bool = True, default: str = "0"):
    return {"ParameterName": name, "ObjectType": "0x7", "DataType": f"0x{dtype:04X}",
            "AccessType": access, "DefaultValue": default, "PDOMapping": str(int(pdo))}


I16, U16, U32, I8, REAL32 = 0x3, 0x6, 0x7, 0x2, 0x8

BASE = {
    "1000": var("Device type", U32, "ro", False, "0x00020192"),
    "1001": var("Error register", 0x5, "ro", False),
    "1017": var("Producer heartbeat time", U16, "rw", False, "0"),
    "1018": {"ParameterName": "Identity", "ObjectType": "0x9", "SubNumber": "2"},
    "1018sub0": var("Highest sub-index supported", 0x5, "ro", False, "1"),
    "1018sub1": var("Vendor-ID", U32, "ro", False, "0x12345678"),
    "6040": var("Controlword", U16, "rww"),
    "6041": var("Statusword", U16, "ro"),
    "6060": var("Modes of operation", I8, "rw", False),
    "6061": var("Modes of operation display", I8, "ro"),
}


def foreign_eds(path: Path) -> Path:
    return write_eds(path, {**BASE, **{
        "1016": {"ParameterName": "Consumer heartbeat time", "ObjectType": "0x8",
                 "SubNumber": "2"},
        "1016sub0": var("Number of entries", 0x5, "ro", False, "1"),
        "1016sub1": var("Consumer heartbeat time", U32, "rw", False),
        "6079": var("DC link circuit voltage", U32, "ro"),
        "6502": var("Supported drive modes", U32, "ro", False, "0x00030000"),
        "3010": var("Phase current A", I16, "ro"),
        "3011": var("Phase current B", I16, "ro"),
        "3012": var("Current beta (fixed frame)", I16, "ro"),
        "3020": var("Output voltage alpha", I16, "ro"),
        "3021": var("Output voltage beta", I16, "ro"),
        "3100": {"ParameterName": "Vector setpoints", "ObjectType": "0x9", "SubNumber": "3"},
        "3100sub0": var("Highest sub-index supported", 0x5, "ro", False, "2"),
        "3100sub1": var("Id reference", I16, "rww"),
        "3100sub2": var("Iq reference", I16, "rww"),
        "3102": var("Field angle", U16, "rww"),
        "3103": var("Field speed", I16, "rww"),
        "3200": var("Phase current A filtered", REAL32, "ro", False),
        "3201": var("Id reference limit", U16, "rw", False),
        "6073": var("Max current", U16, "rw", False, "2000"),  # per mille of rated current
        "6075": var("Motor rated current", U32, "rw", False, "10000"),  # mA
    }})


def standard_only_eds(path: Path) -> Path:
    return write_eds(path, {**BASE, **{
        "6071": var("Target torque", I16, "rww"),
        "6077": var("Torque actual value", I16, "ro"),
        "6078": var("Current actual value", I16, "ro"),
        "6079": var("DC link circuit voltage", U32, "ro"),
        "6502": var("Supported drive modes", U32, "ro", False, "0x000003A5"),
    }}, product="Standard servo")


def chosen(choices) -> dict[str, tuple[int, int] | None]:
    return {name: None if c.chosen is None else (c.chosen.obj.index, c.chosen.obj.sub)
            for name, c in choices.items()}


# ---- candidates --------------------------------------------------------------------------------


def test_own_eds_gives_the_emulators_objects_for_every_role():
    gen_eds = _gen_eds()
    choices = newdrive.choose(newdrive.read_eds(dbc.EDS_PATH))
    assert set(choices) == set(gen_eds.SIGNAL_INDEX)
    assert chosen(choices) == {name: (index, 0) for name, index in gen_eds.SIGNAL_INDEX.items()}


def test_foreign_eds_gives_the_vendors_objects(tmp_path):
    eds = newdrive.read_eds(foreign_eds(tmp_path / "acme.eds"))
    choices = newdrive.choose(eds)
    got = chosen(choices)
    assert got["controlword"] == (0x6040, 0) and got["statusword"] == (0x6041, 0)
    assert got["i_sa"] == (0x3010, 0)
    assert got["i_sb"] == (0x3012, 0)  # beta, not phase B
    assert got["u_sa"] == (0x3020, 0) and got["u_sb"] == (0x3021, 0)
    assert got["u_dc"] == (0x6079, 0)
    assert got["i_sd_ref"] == (0x3100, 1) and got["i_sq_ref"] == (0x3100, 2)
    assert got["eps_0"] == (0x3102, 0) and got["w_0"] == (0x3103, 0)
    for role in ("T_L", "sync_counter", "w_m", "psi_ra", "psi_rb", "T_e", "u_sd_ref"):
        assert got[role] is None, role
    # phase B is listed, with the remark that it is not beta
    b = {c.obj.index: c for c in choices["i_sb"].candidates}
    assert 0x3011 in b and "not beta" in b[0x3011].note
    # non-mappable look-alikes are listed as not usable, never chosen
    a = {c.obj.index: c for c in choices["i_sa"].candidates}
    assert not a[0x3200].usable
    assert all(len(c.candidates) <= 3 for c in choices.values())


def test_access_and_direction_decide(tmp_path):
    eds = newdrive.read_eds(write_eds(tmp_path / "x.eds", {**BASE, **{
        "3000": var("Phase current A", I16, "rw"),  # writable: a candidate for i_sa too
        "3001": var("Ia", I16, "wo"),  # write-only: never a measurement
        "3002": var("I_alpha", I16, "ro", False),  # not mappable
    }}))
    choices = newdrive.choose(eds)
    assert chosen(choices)["i_sa"] == (0x3000, 0)
    assert 0x3001 not in {c.obj.index for c in choices["i_sa"].candidates if c.usable}


# ---- the skeleton ------------------------------------------------------------------------------


def test_skeleton_of_the_foreign_eds(tmp_path, capsys):
    (tmp_path / "vendor").mkdir()
    eds = foreign_eds(tmp_path / "vendor" / "acme.eds")
    out = tmp_path / "profiles" / "acme.toml"
    assert main(["profile", "new-drive", "--eds", str(eds), "--node", "5", "-o", str(out)]) == 0
    assert "wrote" in capsys.readouterr().out
    text = out.read_text()
    data = tomllib.loads(text)
    assert data["drive"]["eds"] == "../vendor/acme.eds"
    assert data["drive"]["dbc"] == "acme.dbc" and data["drive"]["node"] == 5
    assert data["drive"]["device_type"] == 0x00020192
    assert data["modes"] == {"current": -1, "voltage": -2}
    assert data["limits"] == {"current_peak_a": 20.0}
    assert data["pdo"]["setpoints"] == "RPDO2" and "truth" not in data["pdo"]
    assert data["signals"]["i_sa"] == "TPDO1.i_sa" and data["signals"]["u_dc"] == "TPDO2.u_dc"
    assert "T_L" not in data["signals"]
    assert "CANNOT RUN" not in text
    assert re.search(r"# u_sd_ref .*\n#   none found: look in the manual", text)
    assert re.search(r"# T_L .*\n#   none found \(optional: leave it out\)", text)
    assert "0x3010:00 'Phase current A'  INTEGER16 ro PDO" in text
    # the DBC skeleton carries the chosen objects with their sizes
    db = cantools.database.load_file(str(out.with_suffix(".dbc")))
    tpdo2 = db.get_message_by_name("TPDO2")
    assert [(s.name, s.length) for s in tpdo2.signals] == [("u_sa", 16), ("u_sb", 16),
                                                           ("u_dc", 32)]
    # the node id is honoured in every COB-ID, as a third-party tool sees node 5's frames
    assert tpdo2.frame_id == 0x285 and tpdo2.length == 8
    assert db.get_message_by_name("RPDO1").frame_id == 0x205
    assert all(s.scale == 1 for m in db.messages for s in m.signals)
    # without [signals] (until the lead's loader knows it) it is a valid drive profile
    bare = out.with_name("bare.toml")
    bare.write_text(text[:text.index("\n[signals]")] + "\n")
    prof = load_drive_profile(bare)
    assert prof.node == 5 and prof.eds.resolve() == eds.resolve()
    from gateway.process_data import process_data

    pd = process_data(prof)  # and the gateway uses them as they are
    assert {p.name: p.cob_id for p in pd.tpdos}["TPDO2"] == 0x285
    assert {p.name: p.cob_id for p in pd.rpdos}["RPDO1"] == 0x205


def test_skeleton_of_our_own_eds_is_a_valid_profile(tmp_path):
    out = tmp_path / "emu.toml"
    assert main(["profile", "new-drive", "--eds", str(dbc.EDS_PATH), "-o", str(out)]) == 0
    text = out.read_text()
    data = tomllib.loads(text)
    assert data["pdo"] == {"control": "RPDO1", "setpoints": "RPDO2", "load": "RPDO3",
                           "currents": "TPDO1", "voltages": "TPDO2", "truth": "TPDO3",
                           "remap": True}
    assert len(data["signals"]) == 19  # RPDO2_AB's roles are candidates only
    bare = out.with_name("bare.toml")
    bare.write_text(text[:text.index("\n[signals]")] + "\n")
    load_drive_profile(bare)
    # the DBC skeleton has the layout of drive.dbc (scalings aside)
    ours = {m.name: [(s.name, s.length, s.is_signed) for s in m.signals]
            for m in dbc.load_database().messages
            if m.name != "RPDO2_AB" and not is_service(m.frame_id)}
    new = {m.name: [(s.name, s.length, s.is_signed) for s in m.signals]
           for m in cantools.database.load_file(str(out.with_suffix(".dbc"))).messages}
    assert new == ours


def test_a_drive_with_no_mode_the_gateway_streams_gives_the_refusal_note(tmp_path, capsys):
    """0x6502 offers profile position only: neither the laws nor a standard mode can run."""
    eds = standard_only_eds(tmp_path / "servo.eds")
    eds.write_text(eds.read_text().replace("0x000003A5", "0x00000001"))
    assert main(["profile", "new-drive", "--eds", str(eds)]) == 0
    text = capsys.readouterr().out
    header = " ".join(line.lstrip("#! ") for line in text[:text.index("[drive]")].splitlines())
    assert "THIS DRIVE CANNOT RUN THESE CONTROL LAWS" in header
    for what in ("0x6071 target torque", "0x6077 torque actual value",
                 "0x6078 current actual value", "0x6079 DC link circuit voltage",
                 "manufacturer-specific objects"):
        assert what in header, what
    data = tomllib.loads(text)
    assert "current" not in data["modes"]
    assert data["signals"] == {"controlword": "RPDO1.controlword",
                               "statusword": "TPDO1.statusword", "u_dc": "TPDO2.u_dc"}
    assert re.search(r"# i_sa .*\n#   none found: look in the manual", text)
    assert re.search(r'setpoints = "RPDO2" +# no candidate', text)


@pytest.mark.parametrize("content, words", [
    (None, "does not exist"),
    (b"this is not an EDS\n", "cannot be read as CiA 306"),
    (b"\x00\x01\x02garbage", "binary file"),
    (b"[FileInfo]\nFileName=x.eds\n", "no object sections"),
    (b"[FileInfo]\n[1000]\nParameterName=x\nDataType=zz\nAccessType=ro\n",
     "line 4, [1000] DataType=zz"),
])
def test_bad_eds_is_one_paragraph_and_exit_2(tmp_path, capsys, content, words):
    path = tmp_path / "bad.eds"
    if content is not None:
        path.write_bytes(content)
    assert main(["profile", "new-drive", "--eds", str(path)]) == 2
    err = capsys.readouterr().err
    assert words in err and "Traceback" not in err
    assert err.startswith("hil-gateway: error: ") and err.count("\n") == 1


def test_bad_node_and_output(tmp_path, capsys):
    assert main(["profile", "new-drive", "--eds", str(dbc.EDS_PATH), "--node", "0"]) == 2
    assert main(["profile", "new-drive", "--eds", str(dbc.EDS_PATH), "-o",
                 str(tmp_path / "x.txt")]) == 2
    assert "1..127" in capsys.readouterr().err


def test_latin1_eds_is_read(tmp_path):
    path = foreign_eds(tmp_path / "umlaut.eds")
    path.write_bytes(path.read_bytes().replace(b"Field speed", "Feldgeschw. ÄÖ".encode("cp1252")))
    eds = newdrive.read_eds(path)
    assert eds.objects[(0x3103, 0)].name == "Feldgeschw. ÄÖ"


def test_eds_without_cia402_objects_is_told(tmp_path):
    objects = {k: v for k, v in BASE.items() if k not in ("6040", "6060")}
    eds = newdrive.read_eds(write_eds(tmp_path / "io.eds", objects, product="IO module"))
    text = newdrive.render_toml(eds, newdrive.choose(eds))
    header = " ".join(line.lstrip("#! ") for line in text[:text.index("[drive]")].splitlines())
    assert "has no 0x6040 controlword, 0x6060 modes of operation" in header
    assert tomllib.loads(text)["signals"] == {"statusword": "TPDO1.statusword"}


def test_a_skeleton_passes_its_own_profile_check(tmp_path, capsys):
    """`profile new-drive` on a third-party EDS at node 23 writes a profile whose DBC has node
    23's COB-IDs and whose [objects] name the EDS object of each signal, so `profile check`
    passes it: every signal fits its object, and the vector modes have their roles."""
    sys.path.insert(0, str(Path(__file__).parent))
    from foreign_drive import write_files

    write_files(tmp_path, 23)
    out = tmp_path / "new.toml"
    assert main(["profile", "new-drive", "--eds", str(tmp_path / "foreign.eds"), "--node",
                 "23", "-o", str(out)]) == 0
    data = tomllib.loads(out.read_text())
    assert data["objects"]["TPDO1.i_sa"].startswith("0x3")
    capsys.readouterr()
    assert main(["profile", "check", str(out)]) == 0
    text = capsys.readouterr().out
    assert "ERROR" not in text and "0x197" in text
    assert "--drive-mode current-loop runs the paper's laws" in text


@pytest.mark.parametrize("value", ["3010", "0x301", "0x3010.", "0x3010.1.2", 12304])
def test_a_bad_objects_entry_is_one_paragraph(tmp_path, capsys, value):
    from gateway.drive_profile import load_drive_profile

    text = (Path(gateway.__file__).parent / "drives" / "emulator.toml").read_text()
    path = tmp_path / "d.toml"
    rhs = f'"{value}"' if isinstance(value, str) else str(value)
    path.write_text(text + f'\n[objects]\n"TPDO1.i_sa" = {rhs}\n')
    with pytest.raises(UserError, match=r"\[objects\]\.TPDO1\.i_sa"):
        load_drive_profile(path)


def test_an_objects_entry_maps_the_signal(tmp_path):
    """[objects] wins over the name: i_sa mapped to 0x2101 (the emulator's i_sb object) is
    what the check reports."""
    from gateway.profilecheck import check_drive_profile

    text = (Path(gateway.__file__).parent / "drives" / "emulator.toml").read_text()
    text = text.replace('dbc = "builtin:drive.dbc"', f'dbc = "{dbc.DBC_PATH}"').replace(
        'eds = "builtin:drive.eds"', f'eds = "{dbc.EDS_PATH}"')
    path = tmp_path / "d.toml"
    path.write_text(text + '\n[objects]\n"TPDO1.i_sa" = "0x2101.0"\n')
    report = check_drive_profile(path)
    row = next(s for s in report.signals if s.pdo == "TPDO1" and s.signal == "i_sa")
    assert row.obj == "0x2101.0" and not row.problem
