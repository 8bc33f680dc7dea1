"""`hil-gateway log --drive PROFILE`: decoding with the drive's process data (its DBC, its
roles, its scalings and setpoint layout); wrong-length frames counted, not decoded."""

from __future__ import annotations

import itertools
import struct
import threading
import time
from collections import Counter
from pathlib import Path

import can
import pytest
from foreign_drive import write_files

from gateway.buslog import LOG_SUFFIXES, LogOptions, decode_frames, read_log, run_log
from gateway.cli import main
from gateway.drive_profile import load_drive_profile
from gateway.process_data import process_data

_channels = itertools.count()
NODE = 42
TX1, TX2, RX2 = 0x180 + NODE, 0x280 + NODE, 0x300 + NODE


def _frames() -> list[can.Message]:
    """Foreign drive frames: TX1 = (Ib, Ia, Status) at 2 mA/bit, TX2 = (Ualpha, Ubeta, Udc)
    at 50 mV/bit, RX2 = (Id, Iq, Ud, Uq) setpoints; one TX1 of the wrong length."""
    def m(cob: int, data: bytes, t: float) -> can.Message:
        return can.Message(timestamp=t, arbitration_id=cob, data=data, is_extended_id=False)

    return [m(TX1, struct.pack("<hhH", -500, 1000, 0x0237), 1.0),
            m(TX2, struct.pack("<hhH", 2000, -40, 11200), 1.001),
            m(RX2, struct.pack("<hhhh", 1500, -2500, 0, 100), 1.002),
            m(TX1, b"\x01\x02\x03", 1.003),  # wrong length
            m(0x080, b"", 1.004)]  # SYNC: not a PDO


@pytest.fixture
def foreign_profile(tmp_path) -> Path:
    return write_files(tmp_path, NODE)


def _check_rows(rows: list[dict], errors: Counter) -> None:
    assert [r["name"] for r in rows] == ["TX1", "TX2", "RX2"]
    tx1, tx2, rx2 = rows
    assert tx1["i_sa"] == pytest.approx(2.0) and tx1["i_sb"] == pytest.approx(-1.0)
    assert tx1["statusword"] == 0x0237
    assert tx2["u_sa"] == pytest.approx(100.0) and tx2["u_sb"] == pytest.approx(-2.0)
    assert tx2["u_dc"] == pytest.approx(560.0)
    assert rx2["i_sd_ref"] == pytest.approx(3.0) and rx2["i_sq_ref"] == pytest.approx(-5.0)
    assert rx2["u_sq_ref"] == pytest.approx(5.0)
    assert errors == Counter({"TX1": 1})


def test_decode_frames_with_the_foreign_profile(foreign_profile) -> None:
    errors: Counter[str] = Counter()
    rows = decode_frames(_frames(), drive=load_drive_profile(foreign_profile), errors=errors)
    _check_rows(rows, errors)


@pytest.mark.parametrize("suffix", list(LOG_SUFFIXES))
def test_log_with_the_drive_profile_every_format(suffix: str, foreign_profile, tmp_path,
                                                 ) -> None:
    channel = f"logdrive-{next(_channels)}-{time.monotonic_ns()}"
    rx = can.Bus(interface="virtual", channel=channel)
    tx = can.Bus(interface="virtual", channel=channel)
    result = {}
    path = tmp_path / f"run{suffix}"
    csv_path = tmp_path / "decoded.csv"
    stop = threading.Event()

    def target() -> None:
        options = LogOptions(decode=True, csv_path=csv_path,
                             drive=load_drive_profile(foreign_profile))
        result["r"] = run_log(rx, path, options, stop=stop, quiet=True)

    th = threading.Thread(target=target)
    th.start()
    try:
        time.sleep(0.3)
        for msg in _frames():
            tx.send(msg)
        time.sleep(0.3)
    finally:
        stop.set()
        th.join(5)
        rx.shutdown()
        tx.shutdown()
    r = result["r"]
    assert r.frames == 5 == len(read_log(path))  # the account is what the file holds
    assert r.decoded == 3 and r.decode_errors == Counter({"TX1": 1})
    assert "not decoded" in r.account() and "TX1 1" in r.account()
    _check_rows(decode_frames(read_log(path), drive=load_drive_profile(foreign_profile),
                              errors=(errs := Counter())), errs)
    header = csv_path.read_text().splitlines()[0].split(",")
    assert {"i_sa", "u_dc", "i_sd_ref"} <= set(header)


def test_ab_setpoints_decode_as_ab_by_the_profile(tmp_path) -> None:
    """An emulator profile whose setpoint message is RPDO2_AB: its RPDO2 frames are (a, b)."""
    text = (Path(__file__).parents[1] / "gateway/drives/emulator.toml").read_text()
    ab = tmp_path / "emulator_ab.toml"
    ab.write_text(text.replace('setpoints = "RPDO2"', 'setpoints = "RPDO2_AB"'))
    profile = load_drive_profile(ab)
    pd = process_data(profile)
    values = {r: 0.0 for r in pd.roles}
    values.update(i_sa_ref=1.5, i_sb_ref=-2.0, controlword=0x0F)
    frames = [can.Message(arbitration_id=c, data=d, is_extended_id=False)
              for c, _, d in pd.encode(values)]
    rows = decode_frames(frames, drive=profile)
    sp = next(r for r in rows if r["name"] == "RPDO2_AB")
    assert sp["i_sa_ref"] == pytest.approx(1.5, abs=0.01)
    assert sp["i_sb_ref"] == pytest.approx(-2.0, abs=0.01)
    assert "i_sd_ref" not in sp
    # the built-in emulator profile (no --drive) reads the same bytes as (d, q)
    dq = next(r for r in decode_frames(frames, drive=load_drive_profile(None))
              if r["name"] == "RPDO2")
    assert dq["i_sd_ref"] == pytest.approx(1.5, abs=0.01)


def test_cli_log_drive_bad_profile(tmp_path, capsys) -> None:
    rc = main(["log", "-i", "virtual", "-c", "x", "-o", str(tmp_path / "a.blf"),
               "--drive", str(tmp_path / "missing.toml"), "--decode"])
    assert rc == 2 and "cannot read the drive profile" in capsys.readouterr().err


def test_an_ab_emulator_run_log_decodes_as_ab(emulator, tmp_path) -> None:
    """The bus log of a real (a, b) run on the emulator: RPDO2 decoded by the profile as
    RPDO2_AB, every frame of the log accounted for, no wrong-length frames."""
    text = (Path(__file__).parents[1] / "gateway/drives/emulator.toml").read_text()
    ab = tmp_path / "emulator_ab.toml"
    ab.write_text(text.replace('setpoints = "RPDO2"', 'setpoints = "RPDO2_AB"'))
    emu = emulator("ideal")
    out = tmp_path / "run"
    rc = main(["run", "-i", "virtual", "-c", emu.channel, "--drive", str(ab),
               "--reference", "profiles/quick.toml", "--out", str(out)])
    assert rc == 0
    frames = read_log(out / "bus.blf")
    errors: Counter[str] = Counter()
    rows = decode_frames(frames, drive=load_drive_profile(ab), errors=errors)
    names = Counter(r["name"] for r in rows)
    assert names["RPDO2_AB"] >= 400 and "RPDO2" not in names and not errors
    sp = [r for r in rows if r["name"] == "RPDO2_AB"]
    peak = max(abs(complex(r["i_sa_ref"], r["i_sb_ref"])) for r in sp)
    assert 0.5 < peak < 30.0  # currents in A, in the fixed frame
