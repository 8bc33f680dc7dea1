"""`hil-plant run --eds FILE --node N`: the emulated drive as a twin of the drive another EDS or
DCF describes (plant/twin.py), with the EDS of tests/standard_eds.py (a CiA 402 servo written
from the standard) at node 23: its identity, its default PDOs, its standard objects on the
motor model in its units, its modes, its other objects as plain storage; python-canopen's
BaseNode402, built from the same file, as the master."""

from __future__ import annotations

import math
import os
import signal
import subprocess
import sys
from pathlib import Path

import canopen
import pytest
from node402_support import Master402
from standard_eds import (
    DEVICE_TYPE,
    INCREMENTS,
    PRODUCT,
    RATED_CURRENT_MA,
    RATED_TORQUE_MNM,
    REVISION,
    SERIAL,
    STORAGE,
    VENDOR,
    sections,
    write_drive_file,
)

from dbc.edsfile import read_eds
from dbc.motor import MotorParams
from plant.cli import main
from plant.device import DriveDevice
from plant.profile import ProfileSettings
from plant.servo import ServoParams
from plant.twin import load_twin

NODE = 23
VELOCITY_UNIT = 2 * math.pi / INCREMENTS  #: 1 increment per second, rad/s
TORQUE_UNIT = RATED_TORQUE_MNM * 1e-6  #: 1/1000 of the rated torque, N·m
CURRENT_UNIT = RATED_CURRENT_MA * 1e-6  #: 1/1000 of the rated current, A
ENV = {k: v for k, v in os.environ.items() if not k.startswith("CAN_")}


def twin_master(path: Path, node: int | None = NODE) -> Master402:
    twin = load_twin(path, node)
    return Master402(lambda bus: DriveDevice(bus, twin.node_id, dictionary=twin.dictionary),
                     twin.node_id, path)


@pytest.fixture
def eds(tmp_path) -> Path:
    return write_drive_file(tmp_path / "servo.eds")


@pytest.fixture
def master(eds):
    m = twin_master(eds)
    yield m
    m.close()


def test_identity_by_sdo(master):
    sdo = master.node.sdo
    assert sdo[0x1000].raw == DEVICE_TYPE
    assert [sdo[0x1018][k].raw for k in (1, 2, 3, 4)] == [VENDOR, PRODUCT, REVISION, SERIAL]
    assert sdo[0x1008].raw == "Std servo 402" and sdo[0x100A].raw == "FW 3.4.5"
    assert sdo[0x1014].raw == 0x80 + NODE  # $NODEID resolved for node 23
    assert sdo[0x1400][1].raw == 0x200 + NODE and sdo[0x1801][1].raw == 0x280 + NODE
    assert sdo[0x1401][1].raw == 0x80000300 + NODE  # not valid, as the file says
    with pytest.raises(canopen.SdoAbortedError) as exc:
        sdo.upload(0x2200, 1)  # the emulator's own motor parameters are not the twin's
    assert exc.value.code == 0x06020000


def test_modes_are_the_files_that_the_emulator_has(master):
    node = master.node
    assert node.sdo[0x6502].raw == 0x384  # pv, csp, csv, cst of the file's 0x3A5
    assert node.is_op_mode_supported("CYCLIC SYNCHRONOUS VELOCITY")
    assert not node.is_op_mode_supported("PROFILED POSITION")
    node.nmt.state = "PRE-OPERATIONAL"
    for mode in (1, 4, 6, -1):  # pp, hm (the file's), pt (not the file's), a vector mode
        with pytest.raises(canopen.SdoAbortedError) as exc:
            node.sdo[0x6060].raw = mode
        assert exc.value.code == 0x06090030, mode
    node.sdo[0x6060].raw = 3
    assert node.sdo[0x6061].raw == 3


def test_csv_over_the_default_pdos_moves_the_motor(master):
    """BaseNode402 in CSV over the file's own mapping (RPDO1 controlword + target velocity,
    TPDO1 statusword + velocity actual value): magnetise, ramp to 100 rad/s at 100 rad/s²,
    hold: the motor follows as the emulator's CSV does, and the velocity actual value is in
    the file's units (4096 increments per revolution, per second)."""
    master.configure("CYCLIC SYNCHRONOUS VELOCITY", 0x60FF, period_us=None)
    T, errors = 1e-3, []
    for k in range(2000):
        t = k * T
        w_ref = min(max(t - 0.5, 0.0), 1.0) * 100.0
        sw = master.cycle(round(w_ref / VELOCITY_UNIT))
        assert sw & 0x6F == 0x27, f"left Operation enabled at {t:.3f} s: 0x{sw:04X}"
        errors.append((t, w_ref - master.value(0x606C) * VELOCITY_UNIT))
    assert max(abs(e) for t, e in errors if 0.7 <= t <= 1.5) < 1.0  # as tests/test_standard_modes
    w = master.value(0x606C) * VELOCITY_UNIT
    assert abs(w - 100.0) < 0.05 and abs(master.dev.drive.state.w_m - w) <= VELOCITY_UNIT
    turns = master.node.sdo[0x6064].raw / INCREMENTS  # position actual value, revolutions
    # 50 rad on the ramp, 50 rad in the 0.5 s at 100 rad/s: the position actual value too
    assert turns * 2 * math.pi == pytest.approx(100.0, rel=0.01)


def test_cst_torque_in_the_files_rated_torque(master):
    """CST with the target written by SDO: 2 N·m is 400 of the file's 5 N·m rated torque;
    the torque actual value (TPDO2) reads it, the current actual value is |i_s| in 1/1000
    of the file's 8 A, and the motor accelerates at T/J."""
    master.configure("CYCLIC SYNCHRONOUS TORQUE", None, period_us=None)
    for _ in range(500):
        master.cycle()
    master.node.sdo[0x6071].raw = round(2.0 / TORQUE_UNIT)
    master.cycle()
    w0 = master.value(0x606C) * VELOCITY_UNIT
    for _ in range(200):
        master.cycle()
    assert master.value(0x6077) == pytest.approx(400, abs=3)
    w1 = master.value(0x606C) * VELOCITY_UNIT
    assert (w1 - w0) / 0.2 == pytest.approx(2.0 / MotorParams().J, rel=0.03)
    i_s = abs(master.dev.drive.state.i_s_ab)
    assert master.node.sdo[0x6078].raw == pytest.approx(i_s / CURRENT_UNIT, abs=2)
    assert master.node.sdo[0x6079].raw == 560000  # the emulated DC link, mV


def test_pv_without_profile_objects_ramps_at_the_emulators_default(master):
    """Profile velocity in a twin whose file has no 0x6083/0x6084: the target (in RPDO1, in
    the file's units) is reached along the emulator's default ramp, 1000 rev/min per s."""
    a = ProfileSettings().acceleration
    master.configure("PROFILED VELOCITY", 0x60FF, period_us=None)
    for _ in range(300):
        master.cycle(0)
    speeds = []
    for _ in range(700):
        sw = master.cycle(round(50.0 / VELOCITY_UNIT))
        speeds.append(master.value(0x606C) * VELOCITY_UNIT)
    lag = a / (math.e * ServoParams().w_bw) + a * 1e-3  # tests/test_profile_modes.py
    for k in (100, 200, 300, 400):  # on the ramp (it ends after 477 periods)
        assert speeds[k] == pytest.approx(a * (k + 1) * 1e-3, abs=lag), k
    assert abs(speeds[-1] - 50.0) < 0.05 and sw & 0x0400  # target reached


def test_plain_storage_reads_back_the_files_values(master):
    sdo = master.node.sdo
    for index, (_, value) in STORAGE.items():
        assert sdo[index].raw == value, hex(index)
    assert sdo[0x2001][1].raw == -12 and sdo[0x2001][2].raw == 1.5
    sdo[0x2000].raw = 5
    assert sdo[0x2000].raw == 5
    with pytest.raises(canopen.SdoAbortedError) as exc:
        sdo[0x2300].raw = 1  # read-only as the file says (the emulator's account index)
    assert exc.value.code == 0x06010002
    with pytest.raises(canopen.SdoAbortedError) as exc:
        sdo[0x2001][1].raw = 101  # its HighLimit
    assert exc.value.code == 0x06090031


def test_start_up_lists_modes_units_and_plain_storage(eds):
    """`hil-plant run --eds FILE --node 23` as a process: the ready line, then what the twin
    offers, assumes and stores."""
    proc = subprocess.Popen([sys.executable, "-m", "plant", "run", "-i", "virtual", "-c", "t",
                             "--eds", str(eds), "--node", str(NODE)],
                            stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True, env=ENV)
    try:
        lines = [proc.stdout.readline()]
        while "0x6073" not in lines[-1]:
            lines.append(proc.stdout.readline())
            assert lines[-1], "".join(lines)
        proc.send_signal(signal.SIGTERM)
        out, err = proc.communicate(timeout=10)
    finally:
        proc.kill()
    assert proc.returncode == 0, err
    text = "".join(lines)
    assert lines[0] == f"hil-plant: node {NODE} ready on virtual:t (PRE-OPERATIONAL)\n"
    assert "twin of 'Std servo 402' by Test Drives" in text
    assert "vendor 0x00ABCDEF, product 0x0000D402, revision 0x00020003" in text
    assert "modes: 3 profile velocity, 8 cyclic synchronous position" in text
    assert "not emulated, refused by 0x6060: 1 profile position, 6 homing" in text
    assert "1/4096 of a shaft revolution (0x6092)" in text and "rated 5 N·m (0x6076)" in text
    listed = [ln.split()[0] for ln in lines if ln.startswith("    0x")]
    assert listed == ["0x2000", "0x2001", "0x2300", "0x605A", "0x6073"]
    assert "0 cycles" in out and "Traceback" not in err


def test_a_dcf_parameter_value_wins_and_names_the_node(tmp_path):
    """A DCF: ParameterValue over DefaultValue, and [DeviceComissioning] NodeID is the node
    when --node is not given."""
    objs = sections()
    objs["2000"]["ParameterValue"] = "9"
    objs["1017"]["ParameterValue"] = "250"
    objs["6083"] = {"ParameterName": "Profile acceleration", "ObjectType": "0x7",
                    "DataType": "0x0007", "AccessType": "rw", "DefaultValue": "1000",
                    "ParameterValue": "20000", "PDOMapping": "1"}
    dcf = write_drive_file(tmp_path / "axis.dcf", objs, node_id=NODE)
    twin = load_twin(dcf)
    assert twin.node_id == NODE and "[DeviceComissioning]" in twin.describe()[0]
    m = twin_master(dcf, node=None)
    try:
        sdo = m.node.sdo
        assert sdo[0x2000].raw == 9 and sdo[0x1017].raw == 250 and sdo[0x6083].raw == 20000
        assert sdo[0x1014].raw == 0x80 + NODE
    finally:
        m.close()
    assert load_twin(dcf, 5).node_id == 5  # --node wins over the DCF's


def test_canopeneditor_empty_keys_are_absent(tmp_path):
    """CANopenEditor writes unset keys with no value (VendorNumber=, DefaultValue=, ...): they
    count as absent."""
    objs = sections()
    objs["2000"]["LowLimit"] = ""
    objs["6073"]["DefaultValue"] = ""
    path = write_drive_file(tmp_path / "editor.eds", objs,
                            device_info={"VendorNumber": "", "OrderCode": "", "Granularity": ""})
    twin = load_twin(path, NODE)
    # python-canopen's own import fails on the empty keys: the master reads it as we do
    m = Master402(lambda bus: DriveDevice(bus, NODE, dictionary=twin.dictionary), NODE,
                  read_eds(path, NODE).od)
    with pytest.raises(ValueError):
        canopen.import_od(str(path), NODE)
    try:
        assert m.node.sdo[0x6073].raw == 0 and m.node.sdo[0x1018][1].raw == VENDOR
    finally:
        m.close()


def _edit(objs: dict, section: str, key: str, value: str | None) -> dict:
    if value is None:
        del objs[section]
    else:
        objs[section][key] = value
    return objs


@pytest.mark.parametrize("edit, words", [
    (lambda o: _edit(o, "6072", "DataType", "zz"),
     r"cannot be read: line \d+, \[6072\] DataType=zz: the data type must be a number"),
    (lambda o: _edit(o, "2000", "AccessType", "rx"),
     r"cannot be read: line \d+, \[2000\] AccessType=rx: not an access type"),
    (lambda o: _edit(o, "6076", "DefaultValue", "five"),
     r"cannot be read: line \d+, \[6076\] DefaultValue=five: not an integer"),
    (lambda o: _edit(o, "6040", "", None), "needs the CiA 301/402 objects 0x6040 controlword"),
    (lambda o: _edit(o, "1A00sub2", "DefaultValue", "0x60770020"),
     r"TPDO1.s mapping 0x1A00 cannot be served: sub-index 2 = 0x60770020: 0x6077 sub 0 "
     "has 16 bits, the entry 32"),
    (lambda o: _edit(o, "1006", "DefaultValue", "50"), "0x1006 communication cycle period 50"),
    (lambda o: {**o, "3000sub1": o["2000"]}, r"\[3000sub1\]: a sub-index of object 3000"),
])
def test_a_bad_file_is_named_with_exit_2(tmp_path, capsys, edit, words):
    import re

    path = write_drive_file(tmp_path / "bad.eds", edit(sections()))
    assert main(["run", "-i", "virtual", "-c", "x", "--eds", str(path), "--node", "23"]) == 2
    err = capsys.readouterr().err
    assert re.search(words, err), err
    assert str(path) in err and "Traceback" not in err and err.count("\n") == 1


@pytest.mark.parametrize("content, words", [
    (None, "does not exist"), (b"\x00\x01binary", "binary file"),
    (b"[FileInfo]\nFileName=x.eds\n", "no object sections"),
    (b"[1000]\nParameterName=a\n[1000]\nParameterName=b\n", "cannot be read as CiA 306"),
])
def test_an_unreadable_file_exits_2(tmp_path, capsys, content, words):
    path = tmp_path / "x.eds"
    if content is not None:
        path.write_bytes(content)
    assert main(["run", "-i", "virtual", "-c", "x", "--eds", str(path)]) == 2
    err = capsys.readouterr().err
    assert words in err and "Traceback" not in err


def test_a_mode_option_with_a_twin_is_refused(eds, capsys):
    assert main(["run", "-i", "virtual", "-c", "x", "--eds", str(eds), "--drive-mode",
                 "velocity"]) == 2
    assert "a twin's modes are its file's" in capsys.readouterr().err


def test_a_twin_of_the_emulators_own_eds_has_its_units():
    """drive.eds states its velocity unit (0x60A9: 0.001 rev/min) and rated torque; its
    position unit is the assumed 65536 increments per revolution: the emulator's units."""
    import dbc
    from plant import od as odm
    from plant.units import EMULATOR, units_from

    twin = load_twin(dbc.EDS_PATH, 3)
    units, _ = units_from(odm.ObjectStore(3, dictionary=twin.dictionary).lookup)
    for name in ("position", "velocity", "acceleration", "torque", "current"):
        assert getattr(units, name) == pytest.approx(getattr(EMULATOR, name), rel=1e-12), name
    assert not {m for m in twin.dictionary.modes if not m.standard}  # no vector modes


@pytest.mark.parametrize("objects, position, velocity", [
    ({}, 2 * math.pi / 65536, 2 * math.pi / 65536),  # CiA 402 defaults, assumed encoder
    ({(0x608F, 1): 10000}, 2 * math.pi / 10000, 2 * math.pi / 10000),
    ({(0x6092, 1): 360, (0x6091, 1): 5, (0x6091, 2): 1}, 2 * math.pi * 5 / 360,
     2 * math.pi * 5 / 360),  # a degree of the shaft behind a 5:1 gear
    ({(0x60A8, 0): 0xFCB40000, (0x60A9, 0): 0x00B44700}, 2 * math.pi * 1e-4,
     2 * math.pi / 60),  # 1e-4 rev, rev/min
    ({(0x60A9, 0): 0xFD100300}, 2 * math.pi / 65536, 1e-3),  # mrad/s
    ({(0x60A9, 0): 0x00010300}, 2 * math.pi / 65536, 2 * math.pi / 65536),  # m/s: not ours
])
def test_units_from_the_files_objects(objects, position, velocity):
    from plant.units import units_from

    units, notes = units_from(lambda index, sub: objects.get((index, sub)))
    assert units.position == pytest.approx(position, rel=1e-12)
    assert units.velocity == pytest.approx(velocity, rel=1e-12)
    assert units.acceleration == units.velocity and len(notes) == 5
