"""Bus faults injected on purpose between the gateway and the emulated drive
(dbc/busfaults.py, gateway/faultbus.py), over the in-process bus of `sim`: each shipped
scenario's reaction, stop reason, exit status and run directory; seeded lockstep runs are
reproducible bit for bit; the faults column marks each injected fault."""

from __future__ import annotations

import json
import math

import numpy as np
import pytest

from dbc.busfaults import BusFault, BusFaultError, FaultKind, FaultSchedule, parse_bus_faults
from gateway.cli import main
from gateway.report import read_csv
from plant.scenario import ScenarioError, parse_scenario

RUN_FILES = ("summary.json", "signals.csv", "bus.blf")


def _sim(tmp_path, scenario: str, *args: str) -> tuple[int, dict, dict]:
    out = tmp_path / scenario
    rc = main(["sim", "--reference", "profiles/quick.toml", "--plant", scenario, "--out",
               str(out), *args])
    for name in RUN_FILES:  # a complete run directory, whatever the ending
        assert (out / name).is_file(), name
    assert not (out / "running.json").exists()
    summary = json.loads((out / "summary.json").read_text())
    return rc, summary, read_csv(out / "signals.csv")


def _marked(sig: dict, kind: FaultKind) -> np.ndarray:
    """The cycles (t) whose faults column has ``kind``'s bit."""
    bits = sig["faults"].astype(int)
    return sig["t"][(bits & kind.bit) != 0]


# --------------------------------------------------------------- ride through: exit 0


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
def test_faults_the_loop_rides_through(tmp_path, scenario, kind, check):
    rc, s, sig = _sim(tmp_path, scenario)
    run = s["run"]
    assert rc == 0 and run["stop"] == "END_OF_PROFILE", run["stop_reason"]
    assert check(run), run
    assert s["bus_faults"][0]["kind"] == kind.value and s["bus_faults"][0]["acted"] >= 1
    assert s["shutdown"]["safe"]
    assert s["speed_error"]["rms"] < 0.5  # it costs accuracy, never stability
    if kind not in (FaultKind.DROP, FaultKind.SYNC_MISSING, FaultKind.DELAY,
                    FaultKind.HEARTBEAT_STOP):
        # a cycle that completed carries its mark (a missed cycle has no row)
        assert len(_marked(sig, kind)) >= 1


# --------------------------------------------------------------- stop safe: exit 1


@pytest.mark.parametrize("scenario, stop, words", [
    ("bus-dlc", "BAD_FRAME", "of 6 bytes, expected 7"),
    ("bus-off", "BUS_OFF", "could not send"),
    ("bus-error-frames", "BUS_ERRORS", "error frames within"),
    ("bus-babble", "FOREIGN_WRITER", "0x301"),
    ("bus-second-master", "FOREIGN_SYNC", "SYNC the gateway did not send"),
])
def test_faults_that_stop_the_run_safely_by_name(tmp_path, scenario, stop, words):
    rc, s, _ = _sim(tmp_path, scenario)
    run = s["run"]
    assert rc == 1 and run["stop"] == stop, run["stop_reason"]
    assert words in run["stop_reason"]
    assert run["stop"] != "CONTROL_ERROR"
    assert s["shutdown"]["safe"], s["shutdown"]  # the power stage confirmed off


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


def test_simulate_refuses_bus_faults_with_the_command_that_runs_them(capsys):
    assert main(["simulate", "--plant", "bus-drop"]) == 2
    assert "hil-gateway sim --plant bus-drop" in capsys.readouterr().err


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
