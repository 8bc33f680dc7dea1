"""``hil-plant run``: ready line, clean stop on SIGTERM/SIGINT with an account, bad input."""

from __future__ import annotations

import os
import signal
import subprocess
import sys

import pytest

from plant.cli import main

ENV = {k: v for k, v in os.environ.items() if not k.startswith("CAN_")}


@pytest.mark.parametrize("sig", [signal.SIGTERM, signal.SIGINT])
def test_run_ready_line_and_clean_stop(sig):
    proc = subprocess.Popen([sys.executable, "-m", "plant", "run", "-i", "virtual", "-c", "t",
                             "--node", "5", "--drive-mode", "ideal"],
                            stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True, env=ENV)
    try:
        line = proc.stdout.readline()
        assert line == "hil-plant: node 5 ready on virtual:t (PRE-OPERATIONAL)\n"
        proc.send_signal(sig)
        out, err = proc.communicate(timeout=10)
    finally:
        proc.kill()
    assert proc.returncode == 0, err
    assert "0 cycles, 0 SYNC gaps, 0 faults" in out
    assert "Traceback" not in err


@pytest.mark.parametrize("argv, words", [
    (["run", "-i", "virtual", "-c", "x", "--node", "200"], "1..127"),
    (["run", "-i", "no-such-interface", "-c", "x"], "unknown CAN interface"),
    (["run", "-i", "virtual"], "no channel"),
    (["run", "-i", "virtual", "-c", "x", "--motor", "/no/such/motor.toml"], "--motor"),
])
def test_bad_input_exits_2_with_one_message(argv, words, capsys, monkeypatch):
    for k in ("CAN_INTERFACE", "CAN_CHANNEL", "CAN_BITRATE"):
        monkeypatch.delenv(k, raising=False)
    assert main(argv) == 2
    err = capsys.readouterr().err
    assert words in err and "Traceback" not in err and err.count("\n") == 1


def test_bad_motor_values(tmp_path, capsys):
    f = tmp_path / "m.toml"
    f.write_text("J = -1.0\n")
    assert main(["run", "-i", "virtual", "-c", "x", "--motor", str(f)]) == 2
    assert "J" in capsys.readouterr().err


def test_nothing_configured(capsys, monkeypatch, tmp_path):
    for k in ("CAN_INTERFACE", "CAN_CHANNEL", "CAN_BITRATE", "CAN_CONFIG"):
        monkeypatch.delenv(k, raising=False)
    monkeypatch.setenv("HOME", str(tmp_path))
    monkeypatch.chdir(tmp_path)
    assert main(["run"]) == 2
    assert "none configured" in capsys.readouterr().err
