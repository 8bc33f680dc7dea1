"""The emulator and the gateway as two real processes on SocketCAN vcan0.

`hil-plant run -i socketcan -c vcan0` and `hil-gateway run -i socketcan -c vcan0 ...` are
started as subprocesses, with `candump -L vcan0` (can-utils) as a third-party logger where
a test needs it: the two-process twins of tests/test_gateway.py. Run them where vcan0
exists, e.g. ``scripts/vcan-run -- .venv/bin/pytest -m vcan tests/test_two_process.py``;
without vcan0 they skip (fail under CI=true, see tests/conftest.py).
"""

from __future__ import annotations

import itertools
import json
import math
import re
import signal
import time
from pathlib import Path
from types import SimpleNamespace

import can
import numpy as np
import pytest
from conftest import require_vcan
from twoproc_support import (
    IN_QEMU,
    PROBE_ID,
    Proc,
    bcm_tx_ops,
    candump,
    candump_lines,
    find_stretch,
    find_stretch_concurrent,
    frame_key,
    frames_without_probes,
    gateway_cmd,
    plant,
    run,
    sdo_upload,
    stop_plant,
    stretch_mismatch,
    wait_for,
)

from dbc.timing import LOCKSTEP_BACKSTOP_S

pytestmark = [pytest.mark.vcan, pytest.mark.timing]  # timing: repeated under load (scripts/test)

NODE = 1
SYNC, EMCY, HB_DRIVE, HB_GATEWAY = 0x080, 0x080 + NODE, 0x700 + NODE, 0x77F
#: The emulator's drive profile (gateway/drives/emulator.toml): the drive's consumer
#: heartbeat timeout for the gateway.
HB_CONSUMER_TIMEOUT = 0.300
#: Per-cycle wall-clock columns of signals.csv; every other column is deterministic.
TIMING_COLUMNS = ("sync_period", "sync_to_tpdo", "reaction")
PAPER = "profiles/paper.toml"
SW_FAULT = 0x0008
SW_STATE_MASK = 0x006F
SW_OPERATION_ENABLED = 0x0027


def gateway_run(channel: str, out: Path, *args: str) -> list[str]:
    return [*gateway_cmd(), "run", "-i", "socketcan", "-c", channel, "--node", str(NODE),
            "--out", str(out), *args]


def summary(run_dir: Path) -> dict:
    return json.loads((run_dir / "summary.json").read_text())


def read_signals(path: Path) -> tuple[list[str], np.ndarray]:
    from gateway.report import read_csv

    sig = read_csv(path)
    return list(sig), sig


# ------------------------------------------------------------------ the paper run


@pytest.fixture(scope="module")
def paper_run(tmp_path_factory):
    """The paper profile in lockstep over vcan0 against `hil-plant run`, with candump -L
    recording the bus from before the gateway starts until after it has ended."""
    channel = require_vcan("vcan0", need_candump=True)
    d = tmp_path_factory.mktemp("paper")
    out = d / "run"
    with candump(channel, d) as dump, plant(channel, d) as pl:
        t0 = time.monotonic()
        gw = run(gateway_run(channel, out, "--timing", "lockstep", "--profile", PAPER,
                             "--log", "bus.log"), d, "gateway", timeout=240)
        wall = time.monotonic() - t0
    return SimpleNamespace(dir=d, out=out, gw=gw, plant=pl, candump=dump.path, wall=wall)


def test_paper_run_converges_and_equals_in_process_sim(candump_channel, paper_run, tmp_path):
    """Lockstep over vcan is deterministic: signals.csv and the metrics equal `hil-gateway
    sim` (emulator in process) bit for bit, except the wall-clock timing columns; the bus log
    decodes with the DBC to the CSV's values."""
    from gateway.buslog import decode_frames, read_log

    gw = paper_run.gw
    assert gw.popen.returncode == 0, gw.describe()
    s = summary(paper_run.out)
    assert s["run"]["stop_reason"] == "end of the profile"
    assert s["run"]["cycles"] == 2500 and s["run"]["missed_cycles"] == 0
    assert s["faults"] == []
    assert s["configuration"]["bus"].startswith("socketcan")
    assert s["speed_error"]["max"] < 2.0
    assert abs(s["speed_error"]["final"]) < 0.05
    assert abs(s["flux_error"]["final"]) < 2e-3

    # the same configuration in one process
    sim_out = tmp_path / "sim"
    sim = run([*gateway_cmd(), "sim", "--timing", "lockstep", "--profile", PAPER, "--log",
               "bus.log", "--out", str(sim_out)], tmp_path, "sim", timeout=240)
    assert sim.popen.returncode == 0, sim.describe()
    s_sim = summary(sim_out)
    # in one process `sim` reads the emulator's truth at full resolution; over vcan the truth
    # crosses the bus in TPDO3 (INT16): the truth columns and the error metrics agree to
    # that resolution, everything the controller saw and sent to the last bit
    assert s["truth"].startswith("TPDO3") and s_sim["truth"].startswith("emulator")
    truth_lsb = {"w_m": 0.03125, "psi_r_mod": 1.5e-4, "T_e": 0.01}
    for key, lsb in (("speed_error", 0.03125), ("flux_error", 1.5e-4),
                     ("estimation_error", 0.03125)):
        for stat in ("max", "rms"):
            assert abs(s[key][stat] - s_sim[key][stat]) <= lsb, (key, stat)
    for key in ("peak_current", "peak_voltage"):
        assert s[key] == s_sim[key], key
    assert s_sim["run"]["cycles"] == 2500
    cols, sig = read_signals(paper_run.out / "signals.csv")
    cols_sim, sig_sim = read_signals(sim_out / "signals.csv")
    assert cols == cols_sim
    assert len(sig["t"]) == 2500
    assert set(TIMING_COLUMNS) <= set(cols)
    for col in cols:
        if col in truth_lsb:
            np.testing.assert_allclose(sig[col], sig_sim[col], rtol=0,
                                       atol=truth_lsb[col] / 2 + 1e-9, err_msg=col)
        elif col not in TIMING_COLUMNS:
            np.testing.assert_array_equal(sig[col], sig_sim[col], err_msg=col)
    # the timing columns are real measurements over vcan: positive, finite
    assert np.all(sig["reaction"] > 0) and np.all(sig["sync_to_tpdo"][1:] > 0)

    # the raw log (candump format) decodes with the DBC to what the CSV holds
    frames = read_log(paper_run.out / "bus.log")
    rows = decode_frames(frames, node_id=NODE)
    by = {name: [r for r in rows if r["name"] == name]
          for name in ("TPDO1", "TPDO2", "TPDO3", "RPDO1", "RPDO2")}
    syncs = [m for m in frames if m.arbitration_id == SYNC]
    assert len(syncs) == 2500
    assert [m.data[0] for m in syncs] == [(k - 1) % 240 + 1 for k in range(1, 2501)]
    for name in ("TPDO1", "TPDO2", "TPDO3", "RPDO1", "RPDO2"):
        assert len(by[name]) == 2500, name
    for name, col in (("TPDO1", "i_sa"), ("TPDO1", "i_sb"), ("TPDO1", "statusword"),
                      ("TPDO1", "sync_counter"), ("TPDO2", "u_sa"), ("TPDO2", "u_sb"),
                      ("TPDO3", "w_m")):
        np.testing.assert_array_equal([r[col] for r in by[name]], sig[col], err_msg=col)
    np.testing.assert_array_equal([abs(complex(r["psi_ra"], r["psi_rb"])) for r in by["TPDO3"]],
                                  sig["psi_r_mod"])
    # setpoints: the controller's values, quantised on the bus (to half a bit)
    from dbc import scaling

    for name, col in (("RPDO1", "w_0"), ("RPDO2", "i_sd_ref"), ("RPDO2", "i_sq_ref")):
        lsb = scaling(col)[0]
        np.testing.assert_allclose([r[col] for r in by[name]], sig[col], rtol=0,
                                   atol=lsb / 2 + 1e-12, err_msg=col)
    lsb = scaling("eps_0")[0]
    d_eps = np.array([r["eps_0"] for r in by["RPDO1"]]) - sig["eps_0"]
    d_eps = (d_eps + math.pi) % (2 * math.pi) - math.pi  # the angle wraps on the bus
    assert np.max(np.abs(d_eps)) <= lsb / 2 + 1e-9


def test_candump_sees_exactly_the_gateways_log(candump_channel, paper_run):
    """A third-party logger on the same bus: the gateway's raw log is one contiguous stretch
    of what `candump -L` recorded — same frames in the same order, none missing or added."""
    from gateway.buslog import read_log

    assert paper_run.gw.popen.returncode == 0, paper_run.gw.describe()
    dumped = frames_without_probes(read_log(paper_run.candump))
    logged = read_log(paper_run.out / "bus.log")
    assert len(logged) == summary(paper_run.out)["run"]["bus_frames_logged"]
    assert len(logged) > 5 * 2500
    assert all(m.arbitration_id != PROBE_ID for m in logged)
    keys_dump = [frame_key(m) for m in dumped]
    keys_log = [frame_key(m) for m in logged]
    # In order on one CPU (UML); on an SMP kernel (native, QEMU) frames that two processes put
    # on the bus at the same moment may reach two sockets in either order, every sender's own
    # frames still in order (find_stretch_concurrent).
    starts = find_stretch(keys_dump, keys_log) or find_stretch_concurrent(keys_dump, keys_log)
    assert len(starts) == 1, (f"the gateway's {len(keys_log)} frames are not one stretch of "
                              f"candump's {len(keys_dump)}: "
                              f"{stretch_mismatch(keys_dump, keys_log)}")
    i = starts[0]
    # candump saw more: the emulator's boot-up before, its heartbeats after the run
    assert i > 0 and (HB_DRIVE, False, False, False, 1, b"\x00") in keys_dump[:i]
    assert i + len(keys_log) < len(keys_dump)
    # the whole conversation is in the log: NMT, SDO both ways, heartbeats, SYNC, PDOs
    ids = {k[0] for k in keys_log}
    assert {0x000, 0x600 + NODE, 0x580 + NODE, HB_DRIVE, HB_GATEWAY, SYNC,
            0x180 + NODE, 0x200 + NODE} <= ids


# --------------------------------------------------------------------------- scan


def test_scan_finds_the_emulator(vcan_channel, tmp_path):
    with plant(vcan_channel, tmp_path):
        sc = run([*gateway_cmd(), "scan", "-i", "socketcan", "-c", vcan_channel], tmp_path,
                 "scan", timeout=120)
    assert sc.popen.returncode == 0, sc.describe()
    out = sc.stdout()
    table = out.splitlines()
    head = next(k for k, ln in enumerate(table) if ln.split()[:1] == ["node"])
    rows = [ln.split() for ln in table[head + 1:] if re.match(r"^\d+\s{2,}", ln)]
    assert [r[0] for r in rows] == [str(NODE)], out
    row = rows[0]
    assert "0x00010192" in row, out  # device type 0x1000: CiA 402 frequency converter
    assert row[-1] == "yes", out  # matches the emulator's drive profile
    assert "no node matching" not in out


# ------------------------------------------------------- the gateway dies: safe stop


def test_sigkill_gateway_emcy_power_off_then_restart(candump_channel, tmp_path):
    """SIGKILL the gateway mid-run: its heartbeat and its SYNCs stop (the kernel drops its BCM
    task), the emulator raises EMCY 0x8130 and turns its power stage off (CiA 402 Fault). In
    lockstep the emulator counts the consumer time in simulated time, which stops with the
    SYNCs: the wall-clock backstop trips it, :data:`dbc.timing.LOCKSTEP_BACKSTOP_S` after the
    last heartbeat or SYNC. A new gateway resets the fault while enabling and runs to the
    end."""
    ch = candump_channel
    # magnetised at standstill for 20 s: killed after its log has been flushed, the motor is
    # still at rest for the second run
    standstill = tmp_path / "standstill.toml"
    standstill.write_text('[units]\ntime = "s"\nspeed = "rad/s"\nflux = "Wb"\n'
                          '[profile]\nname = "standstill"\nduration = 20.0\n'
                          '[flux]\ninitial = 0.001\nsteps = [{ t = 0.0, value = 1.16, '
                          'ramp = 0.3 }]\n[speed]\ninitial = 0.0\n')
    with candump(ch, tmp_path) as dump, plant(ch, tmp_path) as pl:
        gw = Proc.start(gateway_run(ch, tmp_path / "run1", "--timing", "lockstep",
                                    "--profile", str(standstill)), tmp_path, "gateway1")
        try:
            # long enough for the bus log's flushes (every second) to have run
            wait_for(lambda: dump.count(" 080#") >= 3000, 120, "3000 SYNCs", gw)
            t_kill = time.time()
            gw.signal(signal.SIGKILL)
            assert gw.wait(10) == -signal.SIGKILL
            # the process is gone, its sockets (and their BCM tasks) closed: on a loaded
            # host that can come well after the signal (once more than 50 ms under stress-ng)
            t_dead = time.time()
        finally:
            gw.kill()
        n_before = len([f for f in candump_lines(dump.text()) if f[0] <= t_kill])
        n_sync_run1 = dump.count(" 080#")

        def emcy_after_kill():
            return [f for f in candump_lines(dump.text())[n_before:] if f[1] == EMCY]

        wait_for(lambda: emcy_after_kill(), 10, "the heartbeat-lost EMCY", pl)
        after = candump_lines(dump.text())[n_before:]
        t_emcy, _, data = emcy_after_kill()[0]
        assert data[:2] == b"\x30\x81", data.hex()  # 0x8130 little-endian
        assert len(data) == 8 and data[2] & 0x10  # error register: communication
        hb = [t for t, cob, _ in candump_lines(dump.text())
              if cob in (HB_GATEWAY, SYNC) and t < t_emcy]
        assert hb, "no gateway heartbeat before the EMCY"
        silent = t_emcy - hb[-1]
        backstop = max(HB_CONSUMER_TIMEOUT, LOCKSTEP_BACKSTOP_S)
        assert backstop - 0.005 <= silent <= backstop + 0.2, silent
        assert t_emcy - t_kill <= backstop + 0.2
        assert not [f for f in after if f[1] in (SYNC, HB_GATEWAY) and f[0] > t_dead]
        assert 3000 <= n_sync_run1 < 20000  # killed mid-run

        # nothing lost: the killed run's bus log is readable up to the last flush (1 s), and
        # its marker says it was running
        from gateway.buslog import read_log

        logged = read_log(tmp_path / "run1" / "bus.blf")
        assert logged, "nothing readable in the killed run's bus log"
        # every frame candump saw from the gateway's first logged frame to 1.5 s before the
        # kill (a flush period and a margin) is in the log
        t_first = logged[0].timestamp
        seen = [f for f in candump_lines(dump.text()) if t_first <= f[0] <= t_kill - 1.5]
        assert len(logged) >= len(seen), (len(logged), len(seen))
        marker = json.loads((tmp_path / "run1" / "running.json").read_text())
        assert marker["run"]["status"] == "running"
        assert not (tmp_path / "run1" / "summary.json").exists()

        # the power stage is off: CiA 402 Fault, seen by a third-party SDO client
        sw = int.from_bytes(sdo_upload(ch, NODE, 0x6041), "little")
        assert sw & SW_FAULT and (sw & 0x004F) == 0x0008, hex(sw)
        assert int.from_bytes(sdo_upload(ch, NODE, 0x603F), "little") == 0x8130

        # a new gateway brings the drive back up (fault reset during enable) and runs
        n_before = len(candump_lines(dump.text()))
        gw2 = run(gateway_run(ch, tmp_path / "run2", "--timing", "lockstep", "--duration",
                              "0.5s"), tmp_path, "gateway2", timeout=120)
        assert gw2.popen.returncode == 0, gw2.describe()
        s = summary(tmp_path / "run2")
        assert s["run"]["stop_reason"] == "end of the profile"
        assert s["run"]["cycles"] == 500 and s["run"]["missed_cycles"] == 0
        assert s["faults"] == []
        emcys = [d for _, cob, d in candump_lines(dump.text())[n_before:] if cob == EMCY]
        assert emcys and emcys[0][:2] == b"\x00\x00"  # the fault reset's "no error" EMCY
        sw = int.from_bytes(sdo_upload(ch, NODE, 0x6041), "little")
        assert not sw & SW_FAULT and (sw & SW_STATE_MASK) != SW_OPERATION_ENABLED, hex(sw)
        assert stop_plant(pl) == 0, pl.describe()
    # its account: the cycles of both runs, the heartbeat-lost fault among its faults
    account = pl.stdout().splitlines()[-1]
    m = re.search(r"(\d+) cycles, (\d+) SYNC gaps, (\d+) faults \(([^)]*)\)", account)
    assert m, pl.describe()
    assert int(m[1]) >= n_sync_run1 + 500 and int(m[2]) == 0
    assert int(m[3]) >= 1 and "0x8130" in m[4], account


# ---------------------------------------------------------------------- real time


def test_realtime_10ms_records_its_timing(candump_channel, tmp_path):
    """Real-time timing at 10 ms for 2 s: SYNC from the kernel's broadcast manager (a BCM
    tx_op of the 240 SYNC frames every 10 ms in /proc/net/can-bcm while the run lasts), timing
    statistics in the summary, and the missed cycles it counts are those candump saw: SYNCs
    whose answer was not complete before the next SYNC."""
    if IN_QEMU:
        pytest.skip("QEMU under TCG (vcan-run's last resort) emulates every instruction: the "
                    "emulated motor, 40-65x faster than real time natively (BENCHMARKS.md), "
                    "runs at about real time there, so no period keeps real time; the "
                    "real-time figures come from native vcan or UML")
    ch = candump_channel
    with candump(ch, tmp_path) as dump, plant(ch, tmp_path):
        # A stalled host costs cycles, not the run: neither the consecutive-miss limit nor
        # the rate limit (3 of any 10 cycles stopped a CI run at 0.93 s) applies; the whole
        # run's miss count is checked below.
        gw = Proc.start(gateway_run(ch, tmp_path / "run", "--timing", "realtime", "--period",
                                    "10ms", "--duration", "2s", "--max-missed", "200",
                                    "--max-miss-rate", "1"),
                        tmp_path, "gateway")
        bcm = None
        bcm_sync = re.compile(r"tx_op: \S+ \S+ \[240\] t2=10000 # sent (\d+)")
        try:
            deadline = time.monotonic() + 120
            while gw.popen.poll() is None and time.monotonic() < deadline:
                # a tx_op of 240 frames (SYNC counter 1..240) every 10 000 us
                if bcm is None:
                    bcm = bcm_sync.search(bcm_tx_ops())
                time.sleep(0.1)
            rc = gw.wait(10)
        finally:
            gw.kill()
    assert bcm, "no broadcast-manager task sending the SYNC sequence during the run"
    s = summary(tmp_path / "run")
    r, t = s["run"], s.get("timing", {})
    if rc != 0 and _host_could_not_keep_10ms(r, t):
        # The host could not keep a 10 ms real-time loop (measured, e.g. under the load stage's
        # stress-ng in UML: the emulator's process held for 30 periods processes the kernel's
        # queued SYNCs in a burst, and its RPDO deadline, counted in SYNCs, expires). What must
        # hold then: a named safe stop, the drive confirmed off, the files complete. The
        # stops seen: the drive's RPDO deadline (0x8250), the loop's miss limit, and the
        # divergence guard (the late cycles cost the sensorless estimate its accuracy: the
        # controller does not yet account for the time a late cycle lost).
        assert r["stop"] in ("DRIVE_FAULT", "DRIVE_LOST", "DIVERGED") and \
            r["exit_status"] == 1, r
        # the cause named: the drive's fault by its EMCY code (its RPDO deadline 0x8250, or
        # the gateway's heartbeat 0x8130 when the gateway's process was the one held), the
        # loop's miss limit, or any of the guard's reasons (a bound crossed, field
        # orientation lost, a flux deficit)
        why = r["stop_reason"]
        assert {"DRIVE_FAULT": "0x" in why, "DRIVE_LOST": "cycles" in why,
                "DIVERGED": bool(why)}[r["stop"]], r
        assert s["shutdown"]["safe"], s["shutdown"]
        assert (tmp_path / "run" / "signals.csv").is_file()
        return
    assert rc == 0, gw.describe()
    assert r["stop_reason"] == "end of the profile"
    # A stalled emulator costs cycles, not the run. How many is the host's to say (43 of 200
    # in UML under the load stage's stress-ng): what must hold is that every SYNC is counted,
    # and that the cycles counted missed are the SYNCs whose answer candump saw incomplete.
    assert r["cycles"] + r["missed_cycles"] == 200 and r["cycles"] > 0
    on_wire = _missed_on_the_wire(candump_lines(dump.text()), 200)
    assert abs(r["missed_cycles"] - on_wire) <= 1, (r, on_wire)
    assert 1.9 < r["wall_time_s"] < 3.0  # paced by the clock
    t = s["timing"]
    assert {"sync_period", "sync_jitter", "sync_to_tpdo", "reaction"} <= set(t)
    assert t["sync_period"]["median"] == pytest.approx(0.010, rel=0.1)
    assert t["sync_jitter"]["median"] < 0.001
    assert 0 < t["sync_to_tpdo"]["median"] < 0.010  # the drive answers within the cycle
    assert 0 < t["reaction"]["median"] < 0.010


def _missed_on_the_wire(lines: list[tuple[float, int, bytes]], n: int) -> int:
    """Of the first ``n`` SYNCs on the wire, those not followed, before the next SYNC, by
    the drive's TPDO1 echoing their counter and then each of its other TPDOs (the emulator
    sends TPDO1, 2, 3 in this order for each SYNC). The last window counts only if closed
    by a SYNC."""
    from gateway.buslog import decode_frames

    tpdo1 = 0x180 + NODE
    others = {cob for _, cob, _ in lines if cob in (0x280 + NODE, 0x380 + NODE)}
    syncs = [i for i, (_, cob, _) in enumerate(lines) if cob == SYNC]
    missed = 0
    for k, (start, end) in enumerate(itertools.pairwise(syncs), 1):
        if k > n:
            break
        counter = lines[start][2][0]
        seen: set[int] | None = None  # None until the echo of this SYNC
        for t, cob, data in lines[start + 1:end]:
            if cob == tpdo1:
                msg = can.Message(timestamp=t, arbitration_id=cob, data=data,
                                  is_extended_id=False)
                rows = decode_frames([msg], node_id=NODE)
                if rows and rows[0]["sync_counter"] == counter:
                    seen = set()
            elif seen is not None and cob in others:
                seen.add(cob)
        missed += seen != others
    return missed


def _host_could_not_keep_10ms(run: dict, timing: dict) -> bool:
    """What the run measured says the host held the loop beyond a period: missed or
    withheld cycles, and the longest SYNC → TPDO and TPDO → RPDO times adding up to more
    than the 10 ms period (each alone may stay below it: seen on a CI host at 9.5 and
    5.7 ms, 32 of 57 cycles' RPDOs late)."""
    late = (timing.get("reaction", {}).get("max", 0.0)
            + timing.get("sync_to_tpdo", {}).get("max", 0.0))
    return (run.get("missed_cycles", 0) + run.get("late_rpdo", 0) > 0) and late > 0.010


def test_foreign_drive_runs_from_its_profile_over_vcan(vcan_channel, tmp_path):
    """A drive that shares nothing with the emulator but the standard (tests/foreign_drive.py)
    in its own process at node 127, described by a profile file alone."""
    import sys

    ch = vcan_channel
    drive = Proc.start([sys.executable, str(Path(__file__).with_name("foreign_drive.py")), ch,
                        "127", str(tmp_path)], tmp_path, "foreign")
    try:
        wait_for(lambda: "ready" in drive.stdout(), 60, "the foreign drive's ready line", drive)
        text = (tmp_path / "foreign.toml").read_text().replace("gateway_node = 127",
                                                                "gateway_node = 100")
        (tmp_path / "foreign.toml").write_text(text)
        gw = run([*gateway_cmd(), "run", "-i", "socketcan", "-c", ch, "--drive",
                  str(tmp_path / "foreign.toml"), "--reference", "profiles/quick.toml",
                  "--out", str(tmp_path / "run")], tmp_path, "gateway", 600)
        assert gw.popen.returncode == 0, gw.describe()
    finally:
        drive.signal(signal.SIGTERM)
        drive.kill()
    s = summary(tmp_path / "run")
    assert s["run"]["cycles"] == 500 and s["run"]["stop"] == "END_OF_PROFILE"
    assert abs(s["speed_error"]["final"]) < 0.1 and s["shutdown"]["safe"]


def test_a_users_controller_runs_over_vcan(vcan_channel, tmp_path, monkeypatch):
    """The example controller of examples/pi_foc, not installed, named module:Class (its
    source on PYTHONPATH), runs `run` in lockstep against `hil-plant run` in another process,
    with its own signals in signals.csv and its figure (docs/controllers.md)."""
    root = Path(__file__).resolve().parents[1]
    monkeypatch.setenv("PYTHONPATH", str(root / "examples" / "pi_foc" / "src"))
    ch = vcan_channel
    with plant(ch, tmp_path):
        gw = run(gateway_run(ch, tmp_path / "run", "--timing", "lockstep", "--controller",
                             "pi_foc:PiSpeedFoc", "--reference", str(root / "profiles" /
                                                                      "quick.toml")),
                 tmp_path, "gateway", timeout=120)
    assert gw.popen.returncode == 0, gw.describe()
    s = summary(tmp_path / "run")
    assert s["run"]["stop_reason"] == "end of the profile" and s["run"]["cycles"] == 500
    assert s["configuration"]["controller"]["name"] == "pi_foc:PiSpeedFoc"
    names, sig = read_signals(tmp_path / "run" / "signals.csv")
    assert "torque_demand" in names and "flux_model" in names
    assert abs(sig["flux_model"][-1] - sig["psi_ref"][-1]) < 0.05
    assert (tmp_path / "run" / "fig4_controller.png").is_file()
    assert abs(s["speed_error"]["final"]) < 0.5


@pytest.mark.parametrize("mode, controller", [("velocity", "stream"), ("torque", "stream"),
                                              ("torque", "speed-pi")])
def test_a_standard_drive_streams_the_paper_profile_over_vcan(vcan_channel, tmp_path, mode,
                                                              controller):
    """`run` against `hil-plant run` in another process as a standard CiA 402 drive: the
    paper profile's speed streamed in CSV, its torque in CST (README, "Standard CiA 402
    drives"), and the speed PI over CST; figures of target against actual."""
    ch = vcan_channel
    with plant(ch, tmp_path):
        gw = run(gateway_run(ch, tmp_path / "run", "--timing", "lockstep", "--drive-mode",
                             mode, "--controller", controller, "--profile", PAPER),
                 tmp_path, "gateway", timeout=240)
    assert gw.popen.returncode == 0, gw.describe()
    s = summary(tmp_path / "run")
    assert s["run"]["stop_reason"] == "end of the profile" and s["run"]["cycles"] == 2500
    assert s["configuration"]["drive_mode"] == mode
    assert s["configuration"]["drive_profile"] == "<emulator-standard>"
    assert s["speed_error"]["rms"] < 1.5, s["speed_error"]
    assert (tmp_path / "run" / "fig1_references.png").is_file()
    assert (tmp_path / "run" / "fig4_controller.png").is_file()  # the target sent
