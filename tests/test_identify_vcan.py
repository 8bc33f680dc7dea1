"""`hil-gateway identify --on run` against `hil-plant run --plant SCENARIO` in its own
process over SocketCAN vcan0: the motor file is the plant's. Run it where vcan0 exists,
e.g. ``scripts/vcan-run -- .venv/bin/pytest -m vcan tests/test_identify_vcan.py``."""

from __future__ import annotations

import pytest
from twoproc_support import gateway_cmd, plant, run

from dbc.motor import MotorParams, commissioning

pytestmark = pytest.mark.vcan


def test_identify_a_drive_in_its_own_process(vcan_channel, tmp_path):
    motor = tmp_path / "motor.toml"
    with plant(vcan_channel, tmp_path, "--plant", "offset10mA-rs+10"):
        gw = run([*gateway_cmd(), "identify", "--on", "run", "-i", "socketcan", "-c",
                  vcan_channel, "-o", str(motor), "--out", str(tmp_path / "run"),
                  "--no-figures"], tmp_path, "gateway", 600)
    assert gw.popen.returncode == 0, gw.describe()
    found = MotorParams.from_toml(motor)
    assert found.R_s == pytest.approx(1.1 * 5.3, rel=0.02)
    for name in ("R_r", "L_s", "L_r", "M"):
        assert getattr(found, name) == pytest.approx(getattr(MotorParams.paper(), name),
                                                     rel=0.02), name
    extra = commissioning(motor)
    assert extra["offset_a"] == pytest.approx(0.010, abs=1e-3)
    assert extra["offset_b"] == pytest.approx(0.0, abs=1e-3)
    assert "R_s, Ω" in gw.stdout() and "+10.0 %" in gw.stdout()
