"""The built-in DBCs describe a run's whole bus for third-party tools (dbc/*.dbc,
dbc/busdbc.py, `hil-gateway profile dbc`): one message per id, the CANopen services, value
tables from the CiA 301/402 vocabulary, the ids of any node; the bus log of a run in the
(d, q) frame, in the (a, b) frame and in a standard mode decodes with `cantools decode`
without an unknown frame."""

from __future__ import annotations

import collections
import logging
import re
import subprocess
import sys
from pathlib import Path

import can
import cantools
import pytest
from gw_support import _patient_drive_profile, gateway_run

from dbc import AB_DBC_PATH, DBC_PATH, STANDARD_DBC_PATH, load_codec, signal_specs
from dbc.busdbc import bus_dbc
from dbc.cia301 import Emcy, NmtCommand, NmtState, is_service
from dbc.cia402 import SW_INTERNAL_LIMIT, SW_REMOTE, Controlword, OperationMode, State
from dbc.modes import SetpointFrame
from gateway.buslog import read_log
from gateway.cli import main

BUILTIN = [DBC_PATH, AB_DBC_PATH, STANDARD_DBC_PATH]
SERVICES = {"NMT": 0x000, "SYNC": 0x080, "EMCY": 0x081, "SDO_RESPONSE": 0x581,
            "SDO_REQUEST": 0x601, "HEARTBEAT": 0x701, "GATEWAY_HEARTBEAT": 0x77F}


def _words(text: str) -> str:
    return text.lower().replace("_", " ").replace("-", " ")


@pytest.mark.parametrize("path", BUILTIN, ids=lambda p: p.name)
def test_one_message_per_id_and_every_service(path, caplog) -> None:
    with caplog.at_level(logging.WARNING):
        db = cantools.database.load_file(str(path))
    assert not [r for r in caplog.records if "identical masked frame ids" in r.getMessage()]
    ids = [m.frame_id for m in db.messages]
    assert len(ids) == len(set(ids))
    assert {m.name: m.frame_id for m in db.messages if is_service(m.frame_id)} == SERVICES


@pytest.mark.parametrize("path", BUILTIN, ids=lambda p: p.name)
def test_value_tables_come_from_the_cia301_and_cia402_vocabulary(path) -> None:
    db = cantools.database.load_file(str(path))

    def choices(message: str, signal: str) -> dict[int, str]:
        sig = db.get_message_by_name(message).get_signal_by_name(signal)
        return {int(k): _words(str(v)) for k, v in (sig.choices or {}).items()}

    assert choices("RPDO1", "controlword") == {c.value: _words(c.name) for c in Controlword}
    states = {s.value | SW_REMOTE: _words(s.name) for s in State}
    states[State.OPERATION_ENABLED | SW_REMOTE | SW_INTERNAL_LIMIT] = (
        "operation enabled, internal limit active")
    assert choices("TPDO1", "statusword") == states
    for sw, state in states.items():
        assert _words(State.from_statusword(sw).name) in state
    assert choices("NMT", "nmt_command") == {c.value: _words(c.name) for c in NmtCommand}
    heartbeat = {s.heartbeat: _words(s.name) for s in NmtState}
    heartbeat[NmtState.INITIALISING.heartbeat] = "boot up"
    assert choices("HEARTBEAT", "nmt_state") == heartbeat
    assert choices("GATEWAY_HEARTBEAT", "nmt_state") == heartbeat
    assert choices("EMCY", "emcy_code") == {c.value: _words(c.text) for c in Emcy}
    modes = db.dbc.value_tables["modes_of_operation"]
    assert {int(k): _words(str(v)) for k, v in modes.items()} == {
        m.value: _words(m.name).replace("sync", "synchronous") for m in OperationMode}


def _layout(db: cantools.database.Database) -> dict[int, tuple]:
    return {m.frame_id: (m.name, m.length, m.senders, [
        (s.name, s.start, s.length, s.byte_order, s.is_signed, s.scale, s.offset, s.minimum,
         s.maximum, s.unit, s.choices) for s in m.signals]) for m in db.messages}


def test_the_ab_dbc_is_the_same_bus_with_the_ab_setpoints() -> None:
    dq = _layout(cantools.database.load_file(str(DBC_PATH)))
    ab = _layout(cantools.database.load_file(str(AB_DBC_PATH)))
    rpdo2 = load_codec(1).frame_id("RPDO2")
    assert dq.pop(rpdo2)[0] == "RPDO2" and ab.pop(rpdo2)[0] == "RPDO2_AB"
    assert dq == ab


def test_the_codec_skips_the_service_messages_and_keeps_the_ab_alternative() -> None:
    codec = load_codec(3)
    assert set(codec.names) == {"RPDO1", "RPDO2", "RPDO2_AB", "RPDO3", "TPDO1", "TPDO2",
                                "TPDO3"}
    assert codec.by_frame_id[0x303] == "RPDO2" and codec.frame_id("RPDO2_AB") == 0x303
    assert not {"sdo_index", "nmt_state", "emcy_code", "sync_count"} & set(signal_specs())


def test_bus_dbc_moves_the_node_relative_ids() -> None:
    assert bus_dbc() == DBC_PATH.read_text()
    assert bus_dbc(standard=True) == STANDARD_DBC_PATH.read_text()
    text = bus_dbc(5, SetpointFrame.AB, gateway_node=100)
    db = cantools.database.load_string(text, "dbc")
    ids = {m.name: m.frame_id for m in db.messages}
    assert ids == {"RPDO1": 0x205, "RPDO2_AB": 0x305, "RPDO3": 0x405, "TPDO1": 0x185,
                   "TPDO2": 0x285, "TPDO3": 0x385, "NMT": 0x000, "SYNC": 0x080,
                   "EMCY": 0x085, "SDO_REQUEST": 0x605, "SDO_RESPONSE": 0x585,
                   "HEARTBEAT": 0x705, "GATEWAY_HEARTBEAT": 0x764}
    assert db.get_message_by_name("RPDO1").get_signal_by_name("controlword").choices
    assert "drive node 5, gateway node 100" in text
    # nothing but the ids and the nodes changed
    back = re.sub(r"\b(BO_|SG_|VAL_) (\d+)\b", lambda m: f"{m.group(1)} ID", text)
    ours = re.sub(r"\b(BO_|SG_|VAL_) (\d+)\b", lambda m: f"{m.group(1)} ID",
                  AB_DBC_PATH.read_text())
    assert back == ours.replace("drive node 1, gateway node 127",
                                "drive node 5, gateway node 100")
    for bad in ({"node": 0}, {"node": 128}, {"gateway_node": 0}, {"node": 9, "gateway_node": 9}):
        with pytest.raises(ValueError, match="node"):
            bus_dbc(**bad)


def test_profile_dbc_writes_the_dbc_and_refuses_bad_input(tmp_path, capsys) -> None:
    out = tmp_path / "bus.dbc"
    assert main(["profile", "dbc", "--node", "42", "--setpoint-frame", "ab", "-o",
                 str(out)]) == 0
    assert out.read_text() == bus_dbc(42, SetpointFrame.AB)
    assert "wrote" in capsys.readouterr().out
    assert main(["profile", "dbc", "--drive-mode", "velocity"]) == 0
    assert capsys.readouterr().out == STANDARD_DBC_PATH.read_text()
    for args, words in ((["--node", "127"], "share a COB-ID"),
                        (["--node", "0"], "1..127"),
                        (["--drive-mode", "torque", "--setpoint-frame", "ab"], "standard drive"),
                        (["-o", str(tmp_path / "no" / "x.dbc")], "cannot write")):
        assert main(["profile", "dbc", *args]) == 2
        err = capsys.readouterr().err
        assert words in err and "Traceback" not in err and err.count("\n") == 1, err


# ---------------------------------------------------------- a run's log, decoded by cantools


def _cantools_decode(dbc: Path, blf: Path, tmp_path: Path) -> list[str]:
    """The run's bus log as candump text, decoded by the cantools command line: its lines."""
    log = tmp_path / "bus.log"
    frames = read_log(blf)
    with can.Logger(str(log)) as writer:
        for m in frames:
            writer.on_message_received(m)
    p = subprocess.run([sys.executable, "-m", "cantools", "decode", "--single-line", str(dbc)],
                       input=log.read_text(), capture_output=True, text=True, timeout=120,
                       check=False)
    assert p.returncode == 0, p.stderr
    lines = p.stdout.splitlines()
    assert len(lines) == len(frames) > 0
    return lines


def _decoded(lines: list[str]) -> collections.Counter[str]:
    """Messages by name; every line decoded (no unknown frame, no decoding error)."""
    unknown = [line for line in lines if "Unknown frame" in line]
    assert not unknown, f"{len(unknown)} unknown frames, e.g. {unknown[0]}"
    names = [re.search(r" :: ([A-Z0-9_]+)\(", line) for line in lines]
    assert all(names), [line for line, n in zip(lines, names, strict=True) if not n][:3]
    return collections.Counter(n.group(1) for n in names if n)


def test_a_dq_run_decodes_with_drive_dbc(tmp_path) -> None:
    out = tmp_path / "run"
    assert main(["sim", "--duration", "0.2s", "--out", str(out)]) == 0
    lines = _cantools_decode(DBC_PATH, out / "bus.blf", tmp_path)
    names = _decoded(lines)
    assert names["SYNC"] == names["RPDO2"] == names["TPDO1"] == 200
    assert names["SDO_REQUEST"] == names["SDO_RESPONSE"] > 0
    assert names["NMT"] and names["HEARTBEAT"] and names["GATEWAY_HEARTBEAT"]
    text = "\n".join(lines)
    assert "controlword: enable operation" in text and "statusword: operation enabled" in text
    assert "nmt_state: boot-up" in text and "nmt_command: start" in text


def test_an_ab_run_at_node_5_decodes_with_its_ab_dbc(emulator, tmp_path) -> None:
    text = _patient_drive_profile().read_text()
    ab = tmp_path / "emulator_ab.toml"
    ab.write_text(text.replace('setpoints = "RPDO2"', 'setpoints = "RPDO2_AB"'))
    emu = emulator("ideal", node=5)
    out = tmp_path / "run"
    assert gateway_run(emu, out, "--drive", str(ab), "--node", "5", "--duration", "0.2s") == 0
    dbc = tmp_path / "bus_ab.dbc"
    assert main(["profile", "dbc", "--node", "5", "--setpoint-frame", "ab", "-o",
                 str(dbc)]) == 0
    lines = _cantools_decode(dbc, out / "bus.blf", tmp_path)
    names = _decoded(lines)
    rpdo2 = sum(1 for m in read_log(out / "bus.blf") if m.arbitration_id == 0x305)
    assert names["RPDO2_AB"] == rpdo2 == 200 and "RPDO2" not in names
    assert any("i_sa_ref:" in line for line in lines)
    # the (d, q) DBC reads the same frames as (d, q): why the (a, b) one exists
    dq = tmp_path / "bus_dq.dbc"
    dq.write_text(bus_dbc(5))
    assert _decoded(_cantools_decode(dq, out / "bus.blf", tmp_path))["RPDO2"] == 200


def test_a_standard_mode_run_decodes_with_standard_dbc(tmp_path) -> None:
    out = tmp_path / "run"
    assert main(["sim", "--controller", "stream", "--drive-mode", "velocity", "--duration",
                 "0.2s", "--out", str(out)]) == 0
    names = _decoded(_cantools_decode(STANDARD_DBC_PATH, out / "bus.blf", tmp_path))
    assert names["TPDO1"] == names["RPDO1"] == names["SYNC"] == 200
    assert names["SDO_REQUEST"] and names["NMT"] and names["HEARTBEAT"]
