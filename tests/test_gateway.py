"""The gateway over CANopen against the emulated drive on python-can's virtual bus
(gateway and emulator in threads of one process)."""

from __future__ import annotations

import json
import re
import time
import warnings
from pathlib import Path

import can
import numpy as np
import pytest
from gw_support import (
    MOTOR,
    assert_disabled,
    assert_lost_to_the_host,
    gateway_run,
    host_losses,
    realtime_run_past,
    run_in_thread,
    wait_cycles,
)

from dbc import load_codec
from dbc.timing import Sampling
from gateway.cli import main
from gateway.errors import UserError
from gateway.reference import paper_profile
from gateway.report import read_csv
from gateway.simulate import run
from gateway.spec import RunSpec
from gateway.stop import StopSignals

#: Columns that cross the bus or come from the controller: equal to the last bit.
EXACT = ("t", "i_sa", "i_sb", "u_sa", "u_sb", "i_sd_ref", "i_sq_ref", "u_sd_ref", "u_sq_ref",
         "eps_0", "w_0", "w_hat", "psi_rd_hat", "psi_rq_hat", "psi_ref", "w_ref", "T_L")


# ------------------------------------------------------------------ bit for bit


@pytest.mark.timing
@pytest.mark.parametrize(
    ("sim_kwargs", "cli_args"),
    [
        ({}, []),
        ({"law": "full-order", "drive_mode": "voltage"}, ["--law", "full-order"]),
        ({"drive_mode": "current-loop", "sampling": Sampling(delay=0)},
         ["--drive-mode", "current-loop", "--delay", "0"]),
        ({"flux": "true", "estimator": "drift-free"}, ["--flux", "true", "--estimator",
                                                      "drift-free"]),
    ],
)
def test_lockstep_equals_simulate_bit_for_bit(emulator, tmp_path, sim_kwargs, cli_args):
    emu = emulator(sim_kwargs.get("drive_mode", "ideal"))
    assert gateway_run(emu, tmp_path, "--duration", "0.6s", *cli_args) == 0
    bus = read_csv(tmp_path / "signals.csv")
    sim = run(paper_profile(), MOTOR, RunSpec(duration=0.6, **sim_kwargs)).arrays()
    assert len(bus["t"]) == len(sim["t"]) == 600
    for col in EXACT:
        np.testing.assert_array_equal(bus[col], sim[col], err_msg=col)
    # the truth travels as INT16 (TPDO3): equal to the resolution
    np.testing.assert_allclose(bus["w_m"], sim["w_m"], atol=0.03125 / 2 + 1e-12)
    assert_disabled(emu)


@pytest.mark.timing
def test_paper_scenario_lockstep_converges_like_simulate(emulator, tmp_path):
    emu = emulator()
    assert gateway_run(emu, tmp_path) == 0
    s = json.loads((tmp_path / "summary.json").read_text())
    ref = run(paper_profile(), MOTOR, RunSpec()).arrays()
    e_ref = ref["w_m"] - ref["w_ref"]
    # same run; the bus carries the truth at 1/32 rad/s, so metrics agree to that
    assert s["speed_error"]["max"] == pytest.approx(np.max(np.abs(e_ref)), abs=0.032)
    assert s["speed_error"]["max"] < 2.0
    assert abs(s["speed_error"]["final"]) < 0.05
    assert abs(s["flux_error"]["final"]) < 2e-3
    assert s["run"]["cycles"] == 2500 and s["run"]["missed_cycles"] == 0
    assert s["run"]["stop_reason"] == "end of the profile"
    assert {"fig1_references.png", "fig2_errors.png"} <= {p.name for p in tmp_path.glob("*.png")}
    assert s["timing"]["reaction"]["median"] > 0.0
    assert_disabled(emu)


def test_bus_log_replays_and_decodes_like_the_csv(emulator, tmp_path):
    emu = emulator()
    assert gateway_run(emu, tmp_path, "--duration", "0.3s", "--log", "bus.asc") == 0
    sig = read_csv(tmp_path / "signals.csv")
    codec = load_codec(1)
    frames = list(can.LogReader(str(tmp_path / "bus.asc")))
    tpdo1 = [codec.decode("TPDO1", m.data) for m in frames
             if m.arbitration_id == codec.frame_id("TPDO1")]
    tpdo2 = [codec.decode("TPDO2", m.data) for m in frames
             if m.arbitration_id == codec.frame_id("TPDO2")]
    rpdo1 = [codec.decode("RPDO1", m.data) for m in frames
             if m.arbitration_id == codec.frame_id("RPDO1")]
    syncs = [m for m in frames if m.arbitration_id == 0x80]
    assert len(syncs) == len(tpdo1) == len(tpdo2) == len(rpdo1) == 300
    np.testing.assert_array_equal([d["i_sa"] for d in tpdo1], sig["i_sa"])
    np.testing.assert_array_equal([d["u_sb"] for d in tpdo2], sig["u_sb"])
    np.testing.assert_allclose([d["w_0"] for d in rpdo1], sig["w_0"], atol=0.03125 / 2)
    # the log holds the whole conversation: boot-up, SDO, NMT, heartbeat
    ids = {m.arbitration_id for m in frames}
    assert {0x000, 0x601, 0x581, 0x701, 0x77F} <= ids


# ------------------------------------------------------------------- real time


#: Real time is paced by the host's clock, so its load decides how many cycles are missed or
#: answered late (BENCHMARKS.md). This test is about pacing and the timing report, so it keeps
#: what load does to control small: a 2 ms period (twice the slack per cycle) and a drive frame
#: that turns slowly (30 rad/s). At 1 ms the paper scenario's 200 rad/s field weakening
#: diverged once in CI with 6 % missed cycles and 10 % late RPDOs (the divergence guard
#: stopped it with exit 1, as it should; that was before late setpoints were withheld and the
#: late TPDOs of a missed cycle kept out of the next, tests/test_faults.py); with two CPU
#: hogs on both cores even this profile diverged at 1 ms (25 % missed, 40 % late) and passed
#: 4 of 4 at 2 ms. Control through missed cycles is tested deterministically in
#: test_sampled.py; one-process 1 ms figures are in BENCHMARKS.md.
SLOW_HOLD = """
[units]
time = "s"
speed = "rad/s"
flux = "Wb"
torque = "N*m"
[profile]
name = "slow-hold"
duration = 3.0
[flux]
initial = 0.001
steps = [{ t = 0.0, value = 1.16, ramp = 0.3 }]
[speed]
initial = 0.0
steps = [{ t = 0.4, value = 30.0, ramp = 0.5 }]
[load]
steps = [{ t = 1.5, value = 2.0, ramp = 0.05 }]
"""


@pytest.mark.timing
def test_realtime_runs_for_seconds_with_timing(emulator, tmp_path, tmp_path_factory):
    emu = emulator()
    ref = tmp_path_factory.mktemp("reference") / "slow-hold.toml"
    ref.write_text(SLOW_HOLD)
    rc = gateway_run(emu, tmp_path, "--timing", "realtime", "--duration", "3s",
                     "--period", "2ms", "--reference", str(ref), "--max-missed", "500",
                     "--max-miss-rate", "1", "--estimator", "drift-free")
    s = json.loads((tmp_path / "summary.json").read_text())
    run_ = s["run"]
    sig = read_csv(tmp_path / "signals.csv")
    # How many cycles a loaded host misses is the host's to say (a quarter under stress-ng on
    # 2 cores; BENCHMARKS.md has the idle figures; a virtual machine that stops for 80 ms
    # missed 41 of 50 in a row, so no miss rate stops this run). What must hold: one row
    # per cycle run, at its cycle's time, with the misses counted so far: the gaps between
    # rows are the misses.
    assert len(sig["t"]) == run_["cycles"] > 0
    steps = np.rint(np.diff(sig["t"]) / 2e-3).astype(int)
    np.testing.assert_array_equal(steps - 1, np.diff(sig["missed"]))
    if rc != 0:
        # A host that loses the loop's rate for long (once in CI: 346 of 807 cycles
        # missed, 159 withheld) can take even this profile out of its envelope: the
        # divergence guard stops it, safely, and says so. A divergence where the host kept
        # its rate (its own losses within 20 % of every 100 ms of the 200 ms before the
        # stop) is a failure, and so is any other stop.
        assert run_["stop"] == "DIVERGED" and s["shutdown"]["safe"], run_
        k = np.rint(sig["t"] / 2e-3).astype(int)
        lost = host_losses(k, sig["withheld"], 50, since=run_["stop_cycle"] - 100)
        assert lost > 0.2 * 50, (lost, run_["stop_reason"])
        assert_disabled(emu)
        return
    assert run_["cycles"] + run_["missed_cycles"] >= 1495
    # the misses after the last row (a host that stalls at the end: 36 of them once under
    # load) are the cycles left in the run after it
    trailing = run_["missed_cycles"] - sig["missed"][-1]
    assert trailing >= 0
    assert sig["t"][-1] + trailing * 2e-3 <= 3.0 + 2e-3 + 1e-9, (sig["t"][-1], trailing)
    assert 2.9 < run_["wall_time_s"] < 8.0  # paced by the clock, not as fast as possible
    t = s["timing"]
    assert t["sync_period"]["median"] == pytest.approx(2e-3, rel=0.05)
    assert {"sync_jitter", "sync_to_tpdo", "reaction"} <= set(t)
    assert_disabled(emu)


# ----------------------------------------------------------------- stop paths


@pytest.mark.timing
def test_stop_request_mid_run_disables_the_drive(emulator, tmp_path):
    """What Ctrl-C and SIGTERM do: a stop request ends the loop and the drive is disabled."""
    cfg = RunSpec(timing="realtime", sampling=Sampling(2e-3, 1), max_missed=1000,
                  max_miss_rate=1.0)
    emu, th, result, signals = realtime_run_past(emulator, tmp_path, cfg, 200)
    signals.requested.set()
    signals.reason = "SIGTERM received"
    assert signals.on_stop is not None
    signals.on_stop(signals.reason)
    th.join(10)
    assert not th.is_alive()
    s = result["summary"]
    assert s["run"]["stop_reason"] == "SIGTERM received"
    # stopped mid-run: after the 200 SYNCs the drive saw, long before the profile's 1250.
    # (Completed cycles can be fewer: in real time on a loaded 2-core host some are missed,
    # which this run allows; once 133 of 203.)
    run = s["run"]
    assert 150 < run["stop_cycle"] < 1250
    assert 0 < run["cycles"] <= run["stop_cycle"]
    assert_disabled(emu)
    # nothing logged is lost: the log is complete and closed
    frames = list(can.LogReader(str(tmp_path / "bus.blf")))
    assert len(frames) == s["run"]["bus_frames_logged"] > 4 * s["run"]["cycles"]


@pytest.mark.timing
def test_drive_fault_stops_the_loop(emulator, tmp_path):
    """The drive faults mid-run (its over-current trip, EMCY 0x2310, statusword fault bit):
    the run stops by that cause and the drive ends disabled."""
    from dbc.cia301 import Emcy

    cfg = RunSpec(timing="realtime", sampling=Sampling(2e-3, 1), max_missed=1000,
                  max_miss_rate=1.0)
    emu, th, result, _ = realtime_run_past(emulator, tmp_path, cfg, 100)
    with emu.device._lock:  # as its own over-current check does, in its own lock
        emu.device._fault(Emcy.OVERCURRENT)
    th.join(10)
    assert not th.is_alive()
    s = result["summary"]
    assert s["run"]["stop"] == "DRIVE_FAULT", s["run"]["stop_reason"]
    assert "0x2310" in s["run"]["stop_reason"] or "Fault" in s["run"]["stop_reason"]
    assert any(f["code"] == 0x2310 for f in s["faults"])
    assert_disabled(emu)


def test_a_foreign_writer_on_the_rpdo_stops_the_loop(emulator, tmp_path):
    """Another node sending on the gateway's RPDO2 COB-ID (here a 2-byte frame, which the
    drive also refuses with EMCY 0x8210): the gateway sees a frame on its COB-ID it did not
    send, in bus order before the drive's EMCY, and stops by that cause."""
    cfg = RunSpec(timing="realtime", sampling=Sampling(2e-3, 1), max_missed=1000,
                  max_miss_rate=1.0)
    emu, th, result, _ = realtime_run_past(emulator, tmp_path, cfg, 100)
    with can.Bus(interface="virtual", channel=emu.channel) as intruder:
        intruder.send(can.Message(arbitration_id=0x301, data=b"\x00\x01", is_extended_id=False))
    th.join(10)
    assert not th.is_alive()
    s = result["summary"]
    assert s["run"]["stop"] == "FOREIGN_WRITER", s["run"]["stop_reason"]
    assert "0x301" in s["run"]["stop_reason"] and "0001" in s["run"]["stop_reason"]
    assert s["run"]["exit_status"] == 1 and s["shutdown"]["safe"]
    assert_disabled(emu)


@pytest.mark.timing
def test_lost_drive_stops_the_loop(emulator, tmp_path):
    emu = emulator()
    signals = StopSignals()
    th, result = run_in_thread(emu, tmp_path, RunSpec(timing="lockstep", duration=30.0),
                                signals)
    wait_cycles(emu.device, 100)
    emu.device.stop()  # the drive goes silent: no TPDOs, no heartbeat
    th.join(15)
    assert not th.is_alive()
    s = result["summary"]
    reason = s["run"]["stop_reason"]
    assert ((s["run"]["stop"] == "DRIVE_FAULT" and "heartbeat" in reason)
            or (s["run"]["stop"] == "DRIVE_LOST" and "without the drive's TPDOs" in reason))
    assert s["run"]["cycles"] < 30000
    # a silent drive cannot confirm its power stage off: said, and never exit 0
    assert s["shutdown"]["safe"] is False and s["run"]["exit_status"] == 1


# ----------------------------------------------------------------- bad input


def test_no_drive_at_node(emulator, tmp_path, capsys):
    emu = emulator(node=1)
    assert gateway_run(emu, tmp_path, "--node", "5") == 2
    err = capsys.readouterr().err
    assert "no drive at node 5" in err and "--node" in err


def test_unknown_interface(tmp_path, capsys):
    assert main(["run", "-i", "nosuchcan", "-c", "x", "--out", str(tmp_path)]) == 2
    err = capsys.readouterr().err
    assert "nosuchcan" in err and "Traceback" not in err


def test_no_interface_configured(tmp_path, capsys, monkeypatch):
    monkeypatch.delenv("CAN_INTERFACE", raising=False)
    monkeypatch.delenv("CAN_CHANNEL", raising=False)
    monkeypatch.setattr(can.util, "CONFIG_FILES", [])
    assert main(["run", "--out", str(tmp_path)]) == 2
    assert "no CAN interface given" in capsys.readouterr().err


def test_sdo_abort_during_configuration(emulator, tmp_path, capsys):
    """A mode of operation the drive refuses (0x6060 below its EDS minimum −2, from a drive
    profile that asks for −3): the abort is reported with the object and its meaning. (A
    period outside 100 µs … 100 ms is refused before anything runs: test_cli_inputs.py.)"""
    emu = emulator()
    prof = _drive_profile_copy(tmp_path, lambda t: t.replace("current = -1", "current = -3"))
    assert gateway_run(emu, tmp_path / "out", "--drive", str(prof)) == 2
    err = capsys.readouterr().err
    assert "0x6060" in err and "refused" in err and "0x06090032" in err
    assert "Traceback" not in err
    assert_disabled(emu)


def _drive_profile_copy(tmp_path: Path, edit=lambda text: text) -> Path:
    """The emulator's drive profile as a file (paths made absolute), edited by ``edit``."""
    dbc_dir = Path(__file__).parents[1] / "dbc"
    text = (Path(__file__).parents[1] / "gateway" / "drives" / "emulator.toml").read_text()
    text = text.replace('"builtin:drive.eds"', f'"{dbc_dir / "drive.eds"}"')
    text = text.replace('"builtin:drive.dbc"', f'"{dbc_dir / "drive.dbc"}"')
    prof = tmp_path / "drive.toml"
    prof.write_text(edit(text))
    return prof


def test_wrong_device_type(emulator, tmp_path, capsys):
    emu = emulator()
    prof = _drive_profile_copy(tmp_path, lambda t: t.replace("0x00010192", "0x00020192"))
    assert gateway_run(emu, tmp_path / "out", "--drive", str(prof)) == 2
    assert "device type" in capsys.readouterr().err


def test_unwritable_out_dir(emulator, capsys):
    emu = emulator()
    assert main(["run", "-i", "virtual", "-c", emu.channel, "--out", "/proc/nope"]) == 2
    assert "cannot write the run directory" in capsys.readouterr().err


def test_bad_log_suffix():
    with pytest.raises(UserError, match="must end in one of"):
        RunSpec(bus_log="bus.txt")


def test_sim_command_is_the_quick_start(tmp_path, capsys):
    assert main(["sim", "--duration", "0.4s", "--out", str(tmp_path)]) == 0
    out = capsys.readouterr().out
    assert "speed error" in out and "TPDO → RPDO" in out
    assert (tmp_path / "bus.blf").stat().st_size > 0


@pytest.mark.timing
def test_ctrl_c_twice_stops_cleanly_and_keeps_the_log(tmp_path):
    """A real SIGINT (and a second one during shutdown) to `hil-gateway sim`. The profile
    is a slow one at 2 ms: the signal comes about 1.5 s into the run, which in the paper's
    profile is its steepest acceleration, where a host that stalls for 70 ms (some virtual
    machines do, when idle) leaves a real speed error beyond the guard's 40 rad/s; at 1 ms
    the drive's and the gateway's threads in this one process take half the interpreter's
    time, and a stall's backlog took a hundred cycles to drain."""
    import signal
    import subprocess
    import sys

    ref = tmp_path / "slow-hold.toml"
    ref.write_text(SLOW_HOLD)
    for attempt in range(1, 4):
        out = tmp_path / f"sigint-{attempt}"
        proc = subprocess.Popen(
            [sys.executable, "-m", "gateway", "sim", "--timing", "realtime", "--period",
             "2ms", "--duration", "60s", "--reference", str(ref), "--max-missed", "100000",
             "--max-miss-rate", "1", "--estimator", "drift-free", "--out", str(out)],
            cwd=Path(__file__).parents[1], stdout=subprocess.PIPE, stderr=subprocess.PIPE,
            text=True)
        try:
            deadline = time.monotonic() + 60
            while not (out / "bus.blf").exists() and time.monotonic() < deadline:
                time.sleep(0.05)
            time.sleep(1.5)
            if proc.poll() is None:
                proc.send_signal(signal.SIGINT)
                time.sleep(0.05)
                proc.send_signal(signal.SIGINT)
            _stdout, stderr = proc.communicate(timeout=60)
        finally:
            proc.kill()
        s = json.loads((out / "summary.json").read_text())
        if s["run"]["stop"] != "DIVERGED":
            break
        # the host lost the loop's rate before the signal (a stall of a hundred cycles: one
        # process holds the drive's and the gateway's threads): a safe stop that names the
        # lost cycles, then a fresh run (gw_support.realtime_run_past does the same)
        assert_lost_to_the_host(s)
        assert proc.returncode == 1, s["run"]
        warnings.warn(f"attempt {attempt}: the host lost the real-time run before the "
                      f"signal: {s['run']['stop_reason']}", stacklevel=1)
    assert "Traceback" not in stderr
    s = json.loads((out / "summary.json").read_text())
    assert s["run"]["stop_reason"] == "SIGINT received"
    assert proc.returncode == 130
    assert 150 < s["run"]["cycles"] < 30000
    frames = list(can.LogReader(str(out / "bus.blf")))
    assert len(frames) == s["run"]["bus_frames_logged"]
    # the last things on the bus: controlword "disable voltage" by SDO, then NMT pre-op
    sdo_writes = [m for m in frames if m.arbitration_id == 0x601 and m.data[0] == 0x2B
                  and m.data[1:3] == b"\x40\x60"]
    assert sdo_writes and sdo_writes[-1].data[4:6] == b"\x00\x00"
    nmt = [m for m in frames if m.arbitration_id == 0x000]
    assert nmt[-1].data[0] == 0x80  # enter PRE-OPERATIONAL
    assert "stopped early" in stderr or "SIGINT" in stderr


def _real_drive_profile(tmp_path: Path) -> Path:
    """The emulator's profile, described as a real drive would be (no truth, no dynamometer).

    A real drive watches the gateway's heartbeat by the wall clock (only the emulator's own
    profile sets its SYNC time base), and gateway, drive and test share one interpreter
    here: on a loaded host a 300 ms watch tripped before cycle 1. These tests are not about
    that watch (tests/test_faults.py is), so it is given 5 s."""

    def as_real(text: str) -> str:
        text = text.replace("emulator = true", "emulator = false")
        text = re.sub(r"(?m)^heartbeat_timeout_ms = \d+", "heartbeat_timeout_ms = 5000", text)
        return "\n".join(line for line in text.splitlines()
                         if not line.startswith(("truth =", "load =")))

    return _drive_profile_copy(tmp_path, as_real)


def test_real_drive_profile_runs_without_truth(emulator, tmp_path):
    """A drive described without the emulator's extras: the loop runs on its current loop and
    the summary has timing but no tracking errors."""
    emu = emulator("current-loop")
    prof = _real_drive_profile(tmp_path)
    assert gateway_run(emu, tmp_path / "out", "--drive", str(prof), "--duration", "0.3s") == 0
    s = json.loads((tmp_path / "out" / "summary.json").read_text())
    assert "speed_error" not in s and s["run"]["cycles"] == 300
    assert s["configuration"]["drive_mode"] == "current-loop"
    assert_disabled(emu)


@pytest.mark.parametrize(("args", "needle"), [
    (["--flux", "true"], "--flux true needs the drive's true rotor flux"),
    (["--drive-mode", "ideal"], "exists only on the emulator"),
    (["--law", "full-order", "--drive-mode", "current-loop", "--flux", "true"], "--flux true"),
])
def test_real_drive_refuses_emulator_options(emulator, tmp_path, capsys, args, needle):
    emu = emulator()
    prof = _real_drive_profile(tmp_path)
    assert gateway_run(emu, tmp_path / "out", "--drive", str(prof), *args) == 2
    assert needle in capsys.readouterr().err
