"""Bus faults injected on purpose between the gateway and the emulated drive
(dbc/busfaults.py): over the in-process bus of `sim` (gateway/faultbus.py) and on the PDO
link of `simulate` (gateway/faultlink.py). Each shipped scenario's reaction, stop reason,
exit status and run directory, in both; `simulate` equals `sim` in lockstep cycle by cycle
but for the wall-clock columns (and, where the bus counts wall time, what that changes);
seeded lockstep runs are reproducible bit for bit; the faults column marks each injected
fault."""

from __future__ import annotations

import json
import math
from pathlib import Path

import numpy as np
import pytest

from dbc.busfaults import (
    BusFault,
    BusFaultError,
    FaultKind,
    FaultSchedule,
    Frame,
    FrameFaults,
    Lane,
    parse_bus_faults,
)
from gateway.cli import main
from gateway.report import read_csv
from plant.scenario import ScenarioError, parse_scenario

ROOT = Path(__file__).resolve().parents[1]
#: what a complete run directory holds, whatever the ending
RUN_FILES = {"sim": ("summary.json", "signals.csv", "bus.blf"),
             "simulate": ("summary.json", "signals.csv", "fig2_errors.png")}
COMMANDS = ("sim", "simulate")
SHIPPED = sorted(p.stem for p in (ROOT / "plant/scenarios").glob("bus-*.toml"))
#: the loop's wall-clock columns
TIMING = {"sync_period", "sync_to_tpdo", "reaction"}


def _run(out: Path, command: str, scenario: str, *args: str) -> tuple[int, dict, dict]:
    rc = main([command, "--reference", "profiles/quick.toml", "--plant", scenario, "--out",
               str(out), *args])
    for name in RUN_FILES[command]:  # a complete run directory, whatever the ending
        assert (out / name).is_file() or (name.endswith(".png") and "--no-figures" in args), name
    assert not (out / "running.json").exists()
    summary = json.loads((out / "summary.json").read_text())
    return rc, summary, read_csv(out / "signals.csv")


def _sim(tmp_path, scenario: str, *args: str) -> tuple[int, dict, dict]:
    return _run(tmp_path / scenario, "sim", scenario, *args)


@pytest.fixture(scope="module")
def runs(tmp_path_factory):
    """Each (command, scenario) run once for the module's tests."""
    done: dict[tuple[str, str], tuple[int, dict, dict]] = {}

    def run(command: str, scenario: str) -> tuple[int, dict, dict]:
        if (command, scenario) not in done:
            out = tmp_path_factory.mktemp(command) / scenario
            done[command, scenario] = _run(out, command, scenario)
        return done[command, scenario]
    return run


def _marked(sig: dict, kind: FaultKind) -> np.ndarray:
    """The cycles (t) whose faults column has ``kind``'s bit."""
    bits = sig["faults"].astype(int)
    return sig["t"][(bits & kind.bit) != 0]


# --------------------------------------------------------------- ride through: exit 0


@pytest.mark.parametrize("command", COMMANDS)
@pytest.mark.parametrize("scenario, kind, check", [
    ("bus-drop", FaultKind.DROP,
     lambda r: r["missed_cycles"] == 1 and r["max_consecutive_missed"] == 1),
    ("bus-delay", FaultKind.DELAY,
     lambda r: r["missed_cycles"] >= 1 and r["tpdo_events"].get("TPDO2 late", 0) >= 1),
    ("bus-duplicate", FaultKind.DUPLICATE,
     lambda r: r["missed_cycles"] == 0 and r["tpdo_events"]["TPDO2 duplicate"] >= 5),
    ("bus-reorder", FaultKind.REORDER, lambda r: r["missed_cycles"] == 0),
    ("bus-corrupt", FaultKind.CORRUPT, lambda r: r["missed_cycles"] == 0),
    ("bus-sync-late", FaultKind.SYNC_LATE, lambda r: r["missed_cycles"] == 0),
    ("bus-sync-jitter", FaultKind.SYNC_JITTER, lambda r: r["missed_cycles"] == 0),
    ("bus-sync-missing", FaultKind.SYNC_MISSING, lambda r: r["missed_cycles"] == 1),
    ("bus-heartbeat-stop", FaultKind.HEARTBEAT_STOP, lambda r: r["missed_cycles"] == 0),
])
def test_faults_the_loop_rides_through(runs, command, scenario, kind, check):
    rc, s, sig = runs(command, scenario)
    run = s["run"]
    assert rc == 0 and run["stop"] == "END_OF_PROFILE", run["stop_reason"]
    assert check(run), run
    assert s["bus_faults"][0]["kind"] == kind.value and s["bus_faults"][0]["acted"] >= 1
    if command == "sim":
        assert s["shutdown"]["safe"]
    assert s["speed_error"]["rms"] < 0.5  # it costs accuracy, never stability
    if kind not in (FaultKind.DROP, FaultKind.SYNC_MISSING, FaultKind.DELAY,
                    FaultKind.HEARTBEAT_STOP):
        # a cycle that completed carries its mark (a missed cycle has no row)
        assert len(_marked(sig, kind)) >= 1
    if run["missed_cycles"]:  # a missed cycle has no row: the controller coasted
        assert len(sig["t"]) == run["cycles"] < round(0.5 / 1e-3)


# --------------------------------------------------------------- stop safe: exit 1


@pytest.mark.parametrize("command", COMMANDS)
@pytest.mark.parametrize("scenario, stop, words", [
    ("bus-dlc", "BAD_FRAME", "of 6 bytes, expected 7"),
    ("bus-off", "BUS_OFF", "could not send"),
    ("bus-error-frames", "BUS_ERRORS", "error frames within"),
    ("bus-babble", "FOREIGN_WRITER", "0x301"),
    ("bus-second-master", "FOREIGN_SYNC", "SYNC the gateway did not send"),
])
def test_faults_that_stop_the_run_safely_by_name(runs, command, scenario, stop, words):
    rc, s, sig = runs(command, scenario)
    run = s["run"]
    assert rc == 1 and run["stop"] == stop, run["stop_reason"]
    assert words in run["stop_reason"]
    assert run["stop"] != "CONTROL_ERROR"
    assert s["bus_faults"][0]["acted"] >= 1
    assert run["frames_before_stop"]  # what the bus carried last
    assert len(sig["t"]) == run["cycles"] < round(0.5 / 1e-3)  # the run up to the stop
    if command == "sim":
        assert s["shutdown"]["safe"], s["shutdown"]  # the power stage confirmed off


#: Where `simulate` cannot equal `sim`: the drive's heartbeat goes by the wall clock on a
#: bus, by the drive's cycles on the link (the faults column and the count of a
#: heartbeat-stop differ; nothing else does); a bus-off's recovery counts wall time (the
#: controller may leave the bus at a heartbeat the master's thread sends, a frame earlier
#: within the cycle: the same cycles, the same stop, other words).
WALL_CLOCK_MARKS = {"bus-heartbeat-stop"}
WALL_CLOCK_WORDS = {"bus-off"}
ACCOUNT = ("stop", "exit_status", "cycles", "last_good_cycle", "stop_cycle", "missed_cycles",
           "tpdo_events", "max_consecutive_missed", "error_frames")


@pytest.mark.parametrize("scenario", SHIPPED)
def test_simulate_equals_sim_in_lockstep(runs, scenario):
    """Every shipped scenario: `simulate` (its PDO link) and `sim` (the in-process bus,
    lockstep) give the same signals.csv but for the wall-clock columns, the same stop, exit
    status and loop account, and the same faults acting as often."""
    rc_a, a, sa = runs("simulate", scenario)
    rc_b, b, sb = runs("sim", scenario)
    assert rc_a == rc_b
    ra, rb = a["run"], b["run"]
    account = [k for k in ACCOUNT
               if not (scenario in WALL_CLOCK_WORDS and k in ("missed_cycles",
                                                               "max_consecutive_missed"))]
    assert {k: ra[k] for k in account} == {k: rb[k] for k in account}
    if scenario not in WALL_CLOCK_WORDS:
        assert ra["stop_reason"] == rb["stop_reason"]
    assert list(sa) == list(sb)  # the bus loop's columns
    same = [c for c in sb if c not in TIMING
            and not (scenario in WALL_CLOCK_MARKS and c == "faults")]
    for c in same:
        np.testing.assert_array_equal(sa[c], sb[c], err_msg=c)
    if scenario in WALL_CLOCK_MARKS:
        assert [f["kind"] for f in a["bus_faults"]] == [f["kind"] for f in b["bus_faults"]]
    else:
        assert a["bus_faults"] == b["bus_faults"]


def test_the_shutdown_retries_across_a_bus_off(tmp_path):
    _, s, _ = _sim(tmp_path, "bus-off")
    steps = " ".join(s["shutdown"]["steps"])
    assert "the bus refused the SDO request" in steps
    assert "bus-off recovered" in steps and "statusword confirms" in steps


def test_a_cyclic_send_goes_on_across_refused_sends():
    """The gateway's heartbeat on a bus whose cyclic sends are python-can's thread (not the
    kernel's): the sends refused during a bus-off are counted and the heartbeat goes on
    (python-can's thread would stop at the first)."""
    import threading
    import time

    import can

    from gateway.master import keep_sending

    class Flaky(can.BusABC):
        def __init__(self):
            super().__init__(channel="flaky")
            self.off = threading.Event()
            self.sent: list[float] = []

        def send(self, msg, timeout=None):
            if self.off.is_set():
                raise can.CanOperationError("bus-off")
            self.sent.append(time.monotonic())

        def _recv_internal(self, timeout):
            return None, False

    bus = Flaky()
    refused: list[Exception] = []
    task = keep_sending(bus.send_periodic(can.Message(arbitration_id=0x77F, data=[5]), 0.005),
                        lambda exc: refused.append(exc) or True)
    try:
        assert isinstance(task, can.broadcastmanager.ThreadBasedCyclicSendTask)
        deadline = time.monotonic() + 30
        while len(bus.sent) < 2 and time.monotonic() < deadline:
            time.sleep(0.005)
        bus.off.set()
        while not refused and time.monotonic() < deadline:
            time.sleep(0.005)
        bus.off.clear()
        before = len(bus.sent)
        while len(bus.sent) < before + 2 and time.monotonic() < deadline:
            time.sleep(0.005)
        assert refused and len(bus.sent) >= before + 2  # refused, then sent again
    finally:
        task.stop()
        bus.shutdown()


def test_a_seeded_run_is_reproducible_bit_for_bit(tmp_path):
    """Probability draws come from the fault's own seed, per frame it may act on, on the
    loop's cycles: two lockstep runs give the same signals and the same marks."""
    _, s1, a = _sim(tmp_path / "1", "bus-duplicate")
    _, s2, b = _sim(tmp_path / "2", "bus-duplicate")
    timing = {"sync_period", "sync_to_tpdo", "reaction"}
    for name in a:
        if name not in timing:
            assert np.array_equal(a[name], b[name], equal_nan=True), name
    assert s1["bus_faults"] == s2["bus_faults"]
    assert s1["run"]["tpdo_events"] == s2["run"]["tpdo_events"]
    marked = _marked(a, FaultKind.DUPLICATE)
    assert len(marked) == s1["bus_faults"][0]["acted"]  # one duplicate per marked cycle
    assert marked.min() >= 0.1 - 1e-9 and marked.max() < 0.15 + 1e-9  # its window


@pytest.mark.parametrize("fault, stop", [
    ('kind = "drop"\nmessage = "RPDO1"\ncycle = 300\nduration = 0.002', "END_OF_PROFILE"),
    ('kind = "drop"\nmessage = "RPDO3"\nstart = 0.3\nduration = 0.01', "END_OF_PROFILE"),
    ('kind = "dlc"\nmessage = "RPDO2"\ncycle = 100\nduration = 0.001', "DRIVE_FAULT"),
    ('kind = "corrupt"\nmessage = "TPDO1"\nstart = 0.3\nprobability = 0.1\nseed = 4',
     "IMPLAUSIBLE"),
], ids=["rpdo1-drop", "rpdo3-drop", "rpdo2-dlc", "tpdo1-corrupt"])
def test_simulate_equals_sim_where_the_drive_takes_the_fault(tmp_path, fault, stop):
    """The drive's side: the references without their frame (the frame runs on), the load
    torque held, an RPDO of the wrong length (the drive faults), corrupted measurements
    (the plausibility guard): the same as the emulated device on the bus."""
    path = tmp_path / "fault.toml"
    path.write_text(f"[[bus.fault]]\n{fault}\n")
    rc_a, a, sa = _run(tmp_path / "a", "simulate", str(path), "--no-figures")
    rc_b, b, sb = _run(tmp_path / "b", "sim", str(path), "--no-figures")
    assert rc_a == rc_b == (0 if stop == "END_OF_PROFILE" else 1)
    assert a["run"]["stop"] == b["run"]["stop"] == stop
    assert {k: a["run"][k] for k in ACCOUNT} == {k: b["run"][k] for k in ACCOUNT}
    assert a["run"]["stop_reason"] == b["run"]["stop_reason"]
    assert a["bus_faults"] == b["bus_faults"]
    for c in sb:
        if c not in TIMING:
            np.testing.assert_array_equal(sa[c], sb[c], err_msg=c)


def test_a_seeded_simulation_is_reproducible_and_marks_each_fault(tmp_path):
    _, s1, a = _run(tmp_path / "1", "simulate", "bus-duplicate", "--no-figures")
    _, s2, b = _run(tmp_path / "2", "simulate", "bus-duplicate", "--no-figures")
    for name in a:
        if name not in TIMING:
            assert np.array_equal(a[name], b[name], equal_nan=True), name
    assert s1["bus_faults"] == s2["bus_faults"]
    marked = _marked(a, FaultKind.DUPLICATE)
    assert len(marked) == s1["bus_faults"][0]["acted"]


def test_without_faults_simulate_keeps_its_own_columns(tmp_path):
    """No bus faults: the sampled loop as before (no bus columns); with them, the bus
    loop's columns."""
    out = tmp_path / "nominal"
    assert main(["simulate", "--duration", "20ms", "--no-figures", "--out", str(out)]) == 0
    sig = read_csv(out / "signals.csv")
    assert "faults" not in sig and "bus_faults" not in json.loads(
        (out / "summary.json").read_text())


@pytest.mark.parametrize("args, words", [
    (["--period", "continuous"], "choose a --period such as 1ms"),
    (["--no-quantize"], "drop --no-quantize"),
])
def test_simulate_names_what_bus_faults_need(capsys, args, words):
    assert main(["simulate", "--plant", "bus-drop", *args]) == 2
    assert words in capsys.readouterr().err


def test_simulate_names_a_fault_it_cannot_carry_and_the_command_that_can(tmp_path, capsys):
    path = tmp_path / "hb.toml"
    path.write_text('[[bus.fault]]\nkind = "heartbeat-stop"\nmessage = "gateway"\n')
    assert main(["simulate", "--plant", str(path), "--out", str(tmp_path / "o")]) == 2
    err = capsys.readouterr().err
    assert "hil-gateway sim --plant" in err and "Traceback" not in err


def test_simulate_names_a_fault_on_a_message_the_drive_has_not(tmp_path, capsys):
    path = tmp_path / "x.toml"
    path.write_text('[[bus.fault]]\nkind = "drop"\nmessage = "TPDO9"\n')
    assert main(["simulate", "--plant", str(path), "--out", str(tmp_path / "o")]) == 2
    assert "TPDO9" in capsys.readouterr().err


def test_frame_faults_act_frame_by_frame_whatever_carries_the_frames():
    """The pure actions both carriers use: a drop, a one-cycle delay released at the next
    cycle, a reorder behind the next frame, a corrupted bit."""
    faults = (BusFault(FaultKind.DROP, "TPDO1", cycle=2, duration=1e-3),
              BusFault(FaultKind.DELAY, "TPDO2", cycle=2, duration=1e-3, delay=1e-3),
              BusFault(FaultKind.REORDER, "TPDO3", cycle=3, duration=1e-3),
              BusFault(FaultKind.CORRUPT, "RPDO2", cycle=4, duration=1e-3, seed=7))
    ff = FrameFaults(FaultSchedule(faults, 1e-3),
                     {"TPDO1": 0x181, "TPDO2": 0x281, "TPDO3": 0x381, "RPDO2": 0x301})
    lane = Lane()
    t1, t2, t3 = Frame(0x181, b"\x01"), Frame(0x281, b"\x02"), Frame(0x381, b"\x03")
    assert [lane.pass_on(ff.on_frame(f, 1), 1) for f in (t1, t2, t3)] == [[t1], [t2], [t3]]
    assert [lane.pass_on(ff.on_frame(f, 2), 2) for f in (t1, t2)] == [[], []]
    assert lane.release(2) == [] and lane.release(3) == [t2]
    assert [lane.pass_on(ff.on_frame(f, 3), 3) for f in (t3, t1)] == [[], [t1, t3]]
    r = Frame(0x301, bytes(8))
    (hit,) = ff.on_frame(r, 4).now
    assert bin(int.from_bytes(hit.data, "little")).count("1") == 1  # one bit flipped
    assert ff.schedule.marks(4) == FaultKind.CORRUPT.bit


# --------------------------------------------------------------- the schedule, pure


def test_the_schedule_acts_in_its_cycles_with_its_probability():
    f = BusFault(FaultKind.DROP, "TPDO1", start=0.01, duration=0.1, probability=0.5,
                 seed=4)
    s = FaultSchedule((f,), 1e-3)
    assert (f.first_cycle(1e-3), f.last_cycle(1e-3)) == (11, 110)
    acted = [k for k in range(1, 200) if s.acts(0, k)]
    again = FaultSchedule((f,), 1e-3)
    assert acted == [k for k in range(1, 200) if again.acts(0, k)]  # same seed, same draws
    assert all(11 <= k <= 110 for k in acted) and 30 < len(acted) < 70
    assert s.marks(acted[0]) == FaultKind.DROP.bit and s.marks(1) == 0
    assert math.isinf(BusFault(FaultKind.DROP, "TPDO1").last_cycle(1e-3))


@pytest.mark.parametrize("entry, words", [
    ({"kind": "explode"}, "the kinds are"),
    ({"kind": "drop"}, "needs message"),
    ({"kind": "drop", "message": "TPDO1", "probability": 0}, "probability"),
    ({"kind": "babble", "rate": 10}, "babble needs id"),
    ({"kind": "bus-off"}, "needs duration"),
    ({"kind": "delay", "message": "TPDO1"}, "needs delay > 0"),
    ({"kind": "heartbeat-stop", "message": "TPDO1"}, "\"drive\" or \"gateway\""),
    ({"kind": "drop", "message": "TPDO1", "when": 1}, "unknown key 'when'"),
])
def test_bad_fault_entries_are_named(entry, words):
    with pytest.raises(BusFaultError, match=words):
        parse_bus_faults([entry], "x.toml")


def test_a_scenario_carries_its_faults_and_names_bad_ones():
    sc = parse_scenario('[[bus.fault]]\nkind = "drop"\nmessage = "TPDO1"\ncycle = 3\n')
    assert sc.bus_faults == (BusFault(FaultKind.DROP, "TPDO1", cycle=3),)
    with pytest.raises(ScenarioError, match="entry 1: kind"):
        parse_scenario('[[bus.fault]]\nkind = "nope"\n')


def test_a_fault_on_a_message_the_drive_has_not_is_named(tmp_path, capsys):
    path = tmp_path / "x.toml"
    path.write_text('[[bus.fault]]\nkind = "drop"\nmessage = "TPDO9"\n')
    assert main(["sim", "--plant", str(path), "--out", str(tmp_path / "o")]) == 2
    assert "TPDO9" in capsys.readouterr().err


def test_the_bridge_acts_through_the_same_frame_faults():
    """`hil-gateway bridge` (gateway/faultbus.py's bridge mode) between two virtual buses:
    a TPDO delayed to the next cycle comes after that cycle's SYNC, a dropped one never."""
    import threading

    import can

    from gateway.drive_profile import load_drive_profile
    from gateway.faultbus import run_bridge
    from gateway.process_data import process_data

    def bus(channel: str) -> can.BusABC:
        return can.Bus(interface="virtual", channel=channel)

    gateway_side, gateway = bus("bridge-test-gw"), bus("bridge-test-gw")
    drive_side, drive = bus("bridge-test-drive"), bus("bridge-test-drive")
    faults = (BusFault(FaultKind.DELAY, "TPDO2", cycle=1, duration=1e-3, delay=1e-3),
              BusFault(FaultKind.DROP, "TPDO1", cycle=2, duration=1e-3))
    stop = threading.Event()
    done: list = []
    bridge = threading.Thread(target=lambda: done.append(run_bridge(
        gateway_side, drive_side, faults, 1e-3, process_data(load_drive_profile(None)), 1,
        0x7F, stop)), daemon=True)
    bridge.start()

    def received(b: can.BusABC) -> list[tuple[int, bytes]]:
        out = []
        while (m := b.recv(0.5)) is not None:
            out.append((m.arbitration_id, bytes(m.data)))
        return out

    try:
        for k in (1, 2):
            gateway.send(can.Message(arbitration_id=0x080, data=[k], is_extended_id=False))
            assert received(drive) == [(0x080, bytes([k]))]
            for cob in (0x181, 0x281):
                drive.send(can.Message(arbitration_id=cob, data=[k], is_extended_id=False))
            got = received(gateway)
            if k == 1:
                assert got == [(0x181, b"\x01")]  # TPDO2 held for a cycle
            else:
                assert got == [(0x281, b"\x01"), (0x281, b"\x02")]  # TPDO1 dropped
    finally:
        stop.set()
        bridge.join(5)
        for b in (gateway_side, gateway, drive_side, drive):
            b.shutdown()
    assert [f["acted"] for f in done[0].schedule.account()] == [1, 1]


def test_a_drive_deaf_to_113_syncs_while_accelerating_into_field_weakening(tmp_path):
    """The drive misses 113 SYNCs from 1.7 s (a host stopped for 113 ms): it holds its
    setpoints through them and latches the last ones, with their frame angle 113 periods
    old, at the SYNC it hears next, which the loop cannot know. The controller coasts on
    its model (ω̂ from (16) without (20)) and its next command sets the frame on the flux:
    the run completes and the speed comes back (before: ω̂ ran 50 rad/s from ω* and the
    guard stopped the run at 1.815 s). What the unknown late latch leaves is an error of
    the flux estimate's integration constant: with the open-loop estimator (24) the flux
    angle then swings by about 22° at the stator frequency for the rest of the run."""
    import math

    from dbc.motor import MotorParams
    from gateway.reference import paper_profile
    from gateway.session import run
    from gateway.spec import RunSpec
    from plant.scenario import resolve_scenario

    path = tmp_path / "deaf.toml"
    path.write_text('[scenario]\nname = "deaf"\ndescription = "113 SYNCs unheard"\n\n'
                    '[[bus.fault]]\nkind = "sync-missing"\ncycle = 1700\nduration = 0.113\n')
    spec = RunSpec.from_words(plant=resolve_scenario(str(path)), duration=3.5,
                              max_missed=1000, max_miss_rate=1.0)
    result = run(spec, paper_profile(), MotorParams.paper())
    s, sig = result.summary, result.sig
    assert sig is not None
    assert s["run"]["stop"] == "END_OF_PROFILE", s["run"]["stop_reason"]
    assert s["run"]["missed_cycles"] == 113
    assert s["speed_error"]["max"] < 30.0  # measured 23.2: the held torque's, while ω* climbs
    assert abs(s["speed_error"]["final"]) < 1.0  # measured 0.16
    late = sig["t"] > 3.0
    angle = np.degrees(np.arctan2(sig["psi_rq_hat"][late], sig["psi_rd_hat"][late]))
    assert np.max(np.abs(angle)) < 30.0  # measured 22.3 (the integration constant's error)
    assert math.isfinite(s["speed_error"]["rms"])
