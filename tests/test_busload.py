"""Bus time of a cycle: worst-case bits of CAN 2.0A frames, summed over a drive profile's
cycle, and the refusal of a period the cycle does not fit."""

from __future__ import annotations

import pytest

from dbc.busload import LOAD_LIMIT, CycleFrame, cycle_load, frame_bits
from gateway.bustime import check_bus_time, profile_load
from gateway.cli import main
from gateway.drive_profile import load_drive_profile
from gateway.errors import UserError
from gateway.profilecheck import check_drive_profile, render


@pytest.mark.parametrize(("n", "bits"), [(0, 55), (1, 65), (2, 75), (3, 85), (4, 95),
                                         (5, 105), (6, 115), (7, 125), (8, 135)])
def test_frame_bits_worst_case(n: int, bits: int) -> None:
    # 47 + 8n + floor((33 + 8n)/4): Davis et al. 2007, 135 bits for 8 bytes (IFS included)
    assert frame_bits(n) == bits


@pytest.mark.parametrize("n", [-1, 9, 1.0, True])
def test_frame_bits_refuses_bad_lengths(n: object) -> None:
    with pytest.raises(ValueError):
        frame_bits(n)  # type: ignore[arg-type]


def test_cycle_load_busiest_average_and_load() -> None:
    load = cycle_load([CycleFrame("SYNC", 1), CycleFrame("A", 8), CycleFrame("B", 2, 10)],
                      bitrate=500_000)
    assert load.busiest_bits == 65 + 135 + 75
    assert load.average_bits == pytest.approx(65 + 135 + 7.5)
    assert load.busiest_time == pytest.approx(275 / 500_000)
    assert load.load(1e-3) == pytest.approx(0.55)
    assert load.fits(1e-3) and not load.fits(600e-6)
    assert load.min_period() == pytest.approx(648e-6)  # 550 us / 0.85, whole us up
    assert load.fits(load.min_period()) and not load.fits(load.min_period() - 1e-6)


def test_default_profile_bus_time() -> None:
    load = profile_load(load_drive_profile(None))
    # SYNC 1 B, TPDO1 7, TPDO2 6, TPDO3 8, RPDO1 6, RPDO2 8, RPDO3 2
    assert [f.n_bytes for f in load.frames] == [1, 7, 6, 8, 6, 8, 2]
    assert load.busiest_bits == 65 + 125 + 115 + 135 + 115 + 135 + 75 == 765
    assert load.busiest_time == pytest.approx(765e-6)
    assert load.fits(1e-3) and not load.fits(500e-6)


def test_refusal_names_bus_time_period_and_load() -> None:
    drive = load_drive_profile(None)
    check_bus_time(drive, 1e-3)
    with pytest.raises(UserError) as exc:
        check_bus_time(drive, 500e-6)
    text = str(exc.value)
    for part in ("765 bits", "765 us", "500 us", "153%", f"{LOAD_LIMIT:.0%}", "900 us",
                 "--mapping lean"):
        assert part in text


def test_profile_check_prints_bus_time() -> None:
    from importlib import resources

    path = resources.files("gateway").joinpath("drives/emulator.toml")
    text = render(check_drive_profile(str(path)), 500e-6)
    assert "bus time per cycle 765 bits = 765 us at 1 Mbit/s" in text
    assert "153.0% of the 500 us period" in text and "does NOT fit" in text


def test_sim_refuses_a_period_the_cycle_cannot_fit(tmp_path, capsys) -> None:
    out = tmp_path / "runs"
    assert main(["sim", "--period", "500us", "--out", str(out)]) == 2
    err = capsys.readouterr().err
    assert "765 us of bus time" in err and "153%" in err and "Traceback" not in err
    assert not out.exists()


def test_allow_bus_overload_runs_it_anyway(tmp_path) -> None:
    out = tmp_path / "run"
    assert main(["sim", "--period", "500us", "--allow-bus-overload", "--duration", "20ms",
                 "--out", str(out)]) == 0
    assert (out / "summary.json").is_file()
