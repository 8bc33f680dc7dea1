"""The lean process data (`--mapping lean`, gateway/drives/emulator-lean.toml): a cycle that
fits 500 us on 1 Mbit/s, configured by SDO from the profile, run in lockstep at 2 kHz."""

from __future__ import annotations

import json
from importlib import resources
from pathlib import Path

import can
import numpy as np
import pytest
from gw_support import _patient_drive_profile, assert_disabled, gateway_run

from dbc.busload import LOAD_LIMIT
from dbc.modes import DriveMode
from gateway.bustime import check_bus_time, profile_load
from gateway.cli import main
from gateway.drive_profile import (
    EMULATOR,
    EMULATOR_LEAN,
    Mapping,
    emulator_profile,
    load_drive_profile,
)
from gateway.errors import UserError
from gateway.process_data import process_data
from gateway.profilecheck import check_drive_profile, render
from gateway.report import read_csv

LEAN_TOML = Path(str(resources.files("gateway").joinpath("drives/emulator-lean.toml")))
DEFAULT_TOML = Path(str(resources.files("gateway").joinpath("drives/emulator.toml")))
#: measured: 1.64 mrad/s speed error RMS (paper profile, 500 us, no load applied)
RMS_MARGIN = 5e-3


def lean():
    return load_drive_profile(None, EMULATOR_LEAN)


def test_lean_profile_passes_profile_check_and_fits_500us() -> None:
    report = check_drive_profile(LEAN_TOML)
    assert report.ok
    assert report.modes[DriveMode.CURRENT_LOOP] == []
    text = render(report, 500e-6)
    assert "410 bits = 410 us at 1 Mbit/s" in text and "82.0% of the 500 us period" in text
    assert "the cycle fits" in text


def test_lean_bus_time_is_four_frames_of_410_bits() -> None:
    load = profile_load(lean())
    assert [(f.name, f.n_bytes) for f in load.frames] == [
        ("SYNC", 1), ("TPDO1", 6), ("TPDO2", 4), ("RPDO1", 8)]
    assert load.busiest_bits == 65 + 115 + 95 + 135 == 410
    assert load.fits(500e-6) and load.load(500e-6) == pytest.approx(0.82)
    assert load.load(500e-6) <= LOAD_LIMIT
    check_bus_time(lean(), 500e-6)  # not refused


def test_lean_carries_the_default_scalings() -> None:
    """The emulator encodes its objects with drive.dbc's scalings: the lean DBC must agree."""
    full = {p.name: p for p in process_data(load_drive_profile(None)).pdos}
    by_role = {s.name: s for p in full.values() for s in p.codec.signals}
    for p in process_data(lean()).pdos:
        for s in p.codec.signals:
            d = by_role[s.name]
            assert (s.factor, s.bits, s.signed) == (d.factor, d.bits, d.signed), s.name


def test_mapping_chooses_the_builtin_profile() -> None:
    assert emulator_profile(DriveMode.CURRENT_LOOP) == EMULATOR
    assert emulator_profile(DriveMode.CURRENT_LOOP, Mapping.DEFAULT) == EMULATOR
    assert emulator_profile(DriveMode.IDEAL, Mapping.LEAN) == EMULATOR_LEAN
    assert lean().mapping is Mapping.LEAN
    assert load_drive_profile(None).mapping is Mapping.DEFAULT
    with pytest.raises(UserError, match="--mapping lean"):
        emulator_profile(DriveMode.VELOCITY, Mapping.LEAN)
    with pytest.raises(UserError, match="current setpoints only"):
        emulator_profile(DriveMode.VOLTAGE, Mapping.LEAN)


def test_run_refuses_a_profile_of_another_mapping(tmp_path, capsys) -> None:
    out = tmp_path / "run"
    assert main(["run", "--drive", str(DEFAULT_TOML), "--mapping", "lean",
                 "--out", str(out)]) == 2
    err = capsys.readouterr().err
    assert "[pdo].mapping" in err and "Traceback" not in err
    assert not out.exists()


def test_transmission_type_must_be_every_sync_to_run(tmp_path) -> None:
    text = LEAN_TOML.read_text().replace('eds = "builtin:drive.eds"',
                                         f'eds = "{LEAN_TOML.parents[2]}/dbc/drive.eds"')
    text = text.replace('dbc = "builtin:drive_lean.dbc"',
                        f'dbc = "{LEAN_TOML.parents[2]}/dbc/drive_lean.dbc"')
    p = tmp_path / "tt.toml"
    p.write_text(text.replace("transmission_type = 1", "transmission_type = 2"))
    drive = load_drive_profile(p)
    assert drive.transmission_type == 2
    assert profile_load(drive).average_bits == pytest.approx(65 + 135 + (115 + 95) / 2)
    with pytest.raises(UserError, match="every SYNC"):
        check_bus_time(drive, 1e-3)
    p.write_text(text.replace("transmission_type = 1", "transmission_type = 241"))
    with pytest.raises(UserError, match=r"1\.\.240"):
        load_drive_profile(p)


def test_sim_lean_at_500us_runs_lockstep_with_none_missed(tmp_path, capsys) -> None:
    out = tmp_path / "lean"
    paper = LEAN_TOML.parents[2] / "profiles" / "paper.toml"
    assert main(["sim", "--period", "500us", "--mapping", "lean", "--reference", str(paper),
                 "--no-figures", "--out", str(out)]) == 0
    assert "bus time per cycle 410 bits" in capsys.readouterr().out
    s = json.loads((out / "summary.json").read_text())
    assert s["run"]["stop"] == "END_OF_PROFILE" and s["run"]["cycles"] == 5000
    assert s["run"]["missed_cycles"] == 0
    assert s["truth"] == "emulator, full resolution"
    assert s["speed_error"]["rms"] < RMS_MARGIN
    # on the bus: SYNC, TPDO1, TPDO2, RPDO1 every cycle; the PDOs it does not use disabled
    ids: dict[int, int] = {}
    with can.BLFReader(str(out / "bus.blf")) as log:
        for msg in log:
            ids[msg.arbitration_id] = ids.get(msg.arbitration_id, 0) + 1
    n = ids[0x080]
    assert n == 5000 and ids[0x181] == ids[0x281] == ids[0x201] == n
    assert not {0x301, 0x401, 0x381} & set(ids)


def test_sim_lean_equals_simulate_bit_for_bit(tmp_path) -> None:
    """With the dynamometer following the profile in the plant (RPDO3's load not needed)
    and the laws told the load, the lean mapping carries what `simulate` quantises."""
    a, b = tmp_path / "simulate", tmp_path / "sim"
    common = ["--period", "500us", "--plant", "continuous-load", "--duration", "0.7s",
              "--no-figures"]
    assert main(["simulate", *common, "--out", str(a)]) == 0
    assert main(["sim", *common, "--mapping", "lean", "--load", "known", "--out", str(b)]) == 0
    sa, sb = read_csv(a / "signals.csv"), read_csv(b / "signals.csv")
    assert len(sa["t"]) == len(sb["t"]) == 1400
    for col in ("t", "i_sa", "i_sb", "u_sa", "u_sb", "i_sd_ref", "i_sq_ref", "eps_0", "w_0",
                "w_hat", "w_m", "psi_r_mod", "T_e", "T_L"):
        np.testing.assert_array_equal(sa[col], sb[col], err_msg=col)


def test_run_lean_against_the_emulator_on_a_virtual_bus(emulator, tmp_path) -> None:
    """`run --mapping lean` configures a drive of the default dictionary by SDO from the
    lean profile (its unused PDOs disabled), runs 500 us and leaves the drive safe."""
    emu = emulator()
    out = tmp_path / "run"
    rc = gateway_run(emu, out, "--drive", str(_patient_drive_profile("emulator-lean")),
                     "--mapping", "lean", "--period", "500us", "--duration", "0.4s",
                     "--no-figures")
    assert rc == 0
    s = json.loads((out / "summary.json").read_text())
    assert s["run"]["cycles"] == 800 and s["run"]["missed_cycles"] == 0
    assert_disabled(emu)
    # the emulator's dictionary: RPDO2, RPDO3, TPDO3 not valid; TPDO1, TPDO2 synchronous (1)
    values = emu.device._store.values
    for index in (0x1401, 0x1402, 0x1802):
        assert values[(index, 1)] & (1 << 31), hex(index)
    for index in (0x1400, 0x1800, 0x1801):
        assert not values[(index, 1)] & (1 << 31) and values[(index, 2)] == 1, hex(index)
