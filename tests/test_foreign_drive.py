"""A drive that shares nothing with the emulator but the standard (tests/foreign_drive.py),
described by a drive profile file alone: another node id (127 included), another PDO layout
and scaling, no SYNC-counter echo, TPDOs in reversed order. It runs the quick reference
profile to the emulator's result (within the bus quantisation)."""

from __future__ import annotations

import itertools
import json
import re
import threading
import time
import warnings

import numpy as np
import pytest

from gateway.cli import main
from gateway.report import read_csv

_channels = itertools.count()


def _run(channel: str, profile, out, *args: str) -> tuple[int, dict]:
    rc = main(["run", "-i", "virtual", "-c", channel, "--drive", str(profile),
               "--reference", "profiles/quick.toml", "--out", str(out), *args])
    return rc, json.loads((out / "summary.json").read_text())


@pytest.mark.parametrize("node, gateway_node", [(42, 0x7F), (127, 100)])
def test_foreign_drive_runs_the_quick_profile_like_the_emulator(foreign, tmp_path, node,
                                                                 gateway_node):
    drive, channel, profile = foreign(node, gateway_node)
    rc, s = _run(channel, profile, tmp_path / "foreign")
    assert rc == 0, s["run"]
    assert s["run"]["cycles"] == 500 and s["run"]["missed_cycles"] == 0
    assert s["run"]["tpdo_events"] == {}  # reversed order, no echo: every TPDO was used
    # no 0x1019, 0x1007, 0x1016 on this drive: not written, and said so
    notes = " ".join(s["configuration_notes"])
    assert "0x1019" in notes and "0x1007" in notes and "0x1016" in notes
    assert "load torque" not in notes  # its T_L signal (a dynamometer) applies the load
    assert drive.state != 0x0237 and drive.nmt == "PRE-OPERATIONAL"  # shut down
    assert s["shutdown"]["safe"]
    # the emulator on the same reference profile, ideal current source like this drive
    ref_rc = main(["sim", "--drive-mode", "ideal", "--reference", "profiles/quick.toml",
                   "--out", str(tmp_path / "emulator")])
    ref = json.loads((tmp_path / "emulator" / "summary.json").read_text())
    assert ref_rc == 0
    # the truth crosses the bus at 1/16 rad/s here (1/32 on the emulator): equal to that
    assert abs(s["speed_error"]["rms"] - ref["speed_error"]["rms"]) < 0.04
    assert abs(s["speed_error"]["final"]) < 0.07 and abs(ref["speed_error"]["final"]) < 0.05
    assert abs(s["flux_error"]["final"] - ref["flux_error"]["final"]) < 2e-3
    assert s["peak_current"] == pytest.approx(ref["peak_current"], abs=0.05)


def test_gateway_node_equal_to_the_drive_is_refused(foreign, tmp_path, capsys):
    _, channel, profile = foreign(42)
    rc = main(["run", "-i", "virtual", "-c", channel, "--drive", str(profile),
               "--gateway-node", "42", "--out", str(tmp_path / "x")])
    assert rc == 2 and "gateway" in capsys.readouterr().err


def test_a_drive_without_the_laws_signals_is_refused_by_name(foreign, tmp_path, capsys):
    """A profile that maps only standard objects: refused at bring-up, naming the roles."""
    _, channel, profile = foreign(42)
    text = profile.read_text()
    text = text.replace('i_sa = "TX1.Ia"\n', "").replace('i_sb = "TX1.Ib"\n', "")
    profile.write_text(text)
    rc = main(["run", "-i", "virtual", "-c", channel, "--drive", str(profile),
               "--out", str(tmp_path / "x")])
    err = capsys.readouterr().err
    assert rc == 2 and "i_sa" in err and "i_sb" in err and "phase a" in err


def test_foreign_drive_runs_the_paper_scenario_sensorless(foreign, tmp_path):
    """The issue's "done when": the paper's scenario from a profile file alone (node 127)."""
    _, channel, profile = foreign(127, 100)
    rc = main(["run", "-i", "virtual", "-c", channel, "--drive", str(profile),
               "--reference", "profiles/paper.toml", "--out", str(tmp_path / "paper")])
    s = json.loads((tmp_path / "paper" / "summary.json").read_text())
    assert rc == 0 and s["run"]["cycles"] == 2500, s["run"]
    # truth at this drive's 1/16 rad/s: the sensorless loop tracks to that resolution
    assert s["speed_error"]["rms"] < 0.05 and abs(s["speed_error"]["final"]) < 0.07


def test_a_load_the_drive_cannot_apply_is_named(foreign, tmp_path, caplog):
    """A drive profile without the T_L signal (no dynamometer the gateway can drive): by
    default the laws are not told the profile's load (not told against a real
    drive), and the run says so; told anyway (--load known), the run warns with the ways
    out. This drive's shaft carries no load, so the untold run tracks better."""
    def without_load_signal(node: int):
        _, channel, profile = foreign(node)
        text = profile.read_text()
        new = re.sub(r'(?m)^(T_L = .*|load = "RX3")\n', "", text)
        assert new != text
        profile.write_text(new)
        return channel, profile

    channel, profile = without_load_signal(42)
    rc, s = _run(channel, profile, tmp_path / "x")
    notes = " ".join(s["configuration_notes"])
    assert rc == 0, s["run"]
    assert s["configuration"]["load"] == "untold"
    assert "load torque (up to 2 N·m) is not told to the controller" in notes, notes
    assert "--load known" in notes
    untold = read_csv(tmp_path / "x" / "signals.csv")
    channel, profile = without_load_signal(42)
    rc, s = _run(channel, profile, tmp_path / "k", "--load", "known")
    notes = " ".join(s["configuration_notes"])
    assert s["configuration"]["load"] == "known"
    assert "told the profile's load torque (up to 2 N·m)" in notes, notes
    assert "--load untold" in notes and "--load observed" in notes
    assert "cannot apply" in caplog.text  # the warning (stderr)
    assert s["run"]["cycles"] > 0
    told = read_csv(tmp_path / "k" / "signals.csv")
    # the drive reports its speed (truth): a phantom 2 N·m fed forward costs accuracy
    err = {name: float(np.max(np.abs(sig["w_m"] - sig["w_ref"])[sig["t"] > 0.35]))
           for name, sig in (("untold", untold), ("told", told))}
    assert err["untold"] < 0.5 * err["told"], err
    # over a duration in which the profile has no load yet (it starts at 350 ms): no note
    # (another drive: this one's motor still turns)
    channel, profile = without_load_signal(42)
    rc, s = _run(channel, profile, tmp_path / "y", "--duration", "0.3s")
    assert rc == 0 and "load torque" not in " ".join(s["configuration_notes"])


# ------------------------------------------------- the foreign-SYNC rule without a counter


@pytest.mark.timing
def test_sync_jitter_without_a_counter_is_not_a_foreign_sync(foreign, tmp_path, monkeypatch):
    """Real time against a drive without 0x1019 (no SYNC counter): every 7th SYNC held up
    by 0.8 of a period, so the next comes 0.2 of a period after it, as a loaded host does.
    That is jitter, not another producer: the count of SYNCs says so."""
    from gateway.loop import CycleLoop

    real = CycleLoop._sync_message
    period = 0.004
    held = []

    def jittered(self, k):
        if self._sync_thread is not None and k % 7 == 0:
            held.append(k)
            time.sleep(0.8 * period)
        return real(self, k)

    monkeypatch.setattr(CycleLoop, "_sync_message", jittered)
    for attempt in range(1, 4):
        held.clear()
        _drive, channel, profile = foreign(42)
        out = tmp_path / f"run-{attempt}"
        rc, s = _run(channel, profile, out, "--timing", "realtime", "--period", "4ms",
                     "--duration", "0.5s", "--max-miss-rate", "1")
        run = s["run"]
        # every SYNC sent so far, held ones included, was judged ours
        assert run["stop"] != "FOREIGN_SYNC", run
        # a host that stops the process for tens of ms (a VM's stall) can leave a real
        # speed error the divergence guard stops (named with the lost cycles), or, stalled
        # for a dozen periods in a row (once here: 12 at 4 ms), stop the run as the drive
        # lost — both end safe, and neither is this test's question; any other end is a
        # failure
        assert rc == 0 or (run["stop"] == "DIVERGED" and s["shutdown"]["safe"]) or (
            run["stop"] == "DRIVE_LOST" and "consecutive cycles without the drive's TPDOs"
            in run["stop_reason"] and s["shutdown"]["safe"]), run
        if len(held) > 10:
            break
        # stopped so before a dozen holds (under stress-ng once: at cycle 66, 11 of its
        # last 25 cycles lost): too few to answer, a fresh run
        warnings.warn(f"attempt {attempt}: the run ended after {len(held)} held SYNCs: "
                      f"{run['stop_reason']}", stacklevel=1)
    assert len(held) > 10


@pytest.mark.timing
def test_another_sync_producer_without_a_counter_is_named_by_count(foreign, tmp_path):
    """A second producer sending SYNC at the same rate: stopped as FOREIGN_SYNC, and the
    message says the count is the evidence."""
    import can

    _drive, channel, profile = foreign(42)
    stop = threading.Event()

    def other_producer():
        with can.Bus(interface="virtual", channel=channel) as bus:
            while not stop.wait(0.004):
                bus.send(can.Message(arbitration_id=0x080, data=b"", is_extended_id=False))

    th = threading.Thread(target=other_producer, daemon=True)
    th.start()
    try:
        rc, s = _run(channel, profile, tmp_path / "run", "--timing", "realtime", "--period",
                     "4ms", "--duration", "2s", "--max-miss-rate", "1")
    finally:
        stop.set()
        th.join(5)
    assert rc == 1
    assert s["run"]["stop"] == "FOREIGN_SYNC", s["run"]
    assert "by count" in s["run"]["stop_reason"]


def test_foreign_sync_rule_by_counter_data_and_count():
    """The rule alone: with a counter by the counter; without one, a SYNC with data is
    another's, and the k-th SYNC is ours while the producer can have sent k."""
    from types import SimpleNamespace

    from gateway.loop import FOREIGN_SYNC_SLACK, CycleLoop, LoopConfig, Timing

    def loop(**kw):
        cfg = LoopConfig(n_cycles=10, timing=kw.pop("timing", Timing.REALTIME),
                         sync_counter=kw.pop("counter", False))
        state = {"_T": 1e-3, "_syncs_sent": 0, "_sync_thread": None,
                 "_producer_start": time.time(), **kw}
        return SimpleNamespace(cfg=cfg, **state)

    rule = CycleLoop._foreign_sync
    with_counter = loop(counter=True)
    assert rule(with_counter, 3, b"\x03") == ""
    assert "by the SYNC counter" in rule(with_counter, 3, b"\x07")
    assert "by its data" in rule(loop(), 1, b"\x01")
    thread = loop(_sync_thread=object(), _syncs_sent=5)
    assert rule(thread, 5 + FOREIGN_SYNC_SLACK, b"") == ""
    assert "by count" in rule(thread, 6 + FOREIGN_SYNC_SLACK, b"")
    kernel = loop(_producer_start=time.time() - 0.0105)  # 11 SYNCs by now at most
    assert rule(kernel, 11, b"") == ""
    assert "by count" in rule(kernel, 40, b"")
    lockstep = loop(timing=Timing.LOCKSTEP, _syncs_sent=4)
    assert rule(lockstep, 4, b"") == "" and "by count" in rule(lockstep, 5, b"")


def test_kernel_syncs_that_did_not_reach_the_gateway_are_skipped_slots_by_the_counter():
    """With the kernel's broadcast manager (socketcan, real time) and a counter, a SYNC
    whose counter is ahead of the last one seen by n opens cycle k + n (the slots between
    skipped), as the drive counts them; before, a loaded host's lost SYNCs (33 then 0x24
    in the UML sandbox) stopped the run as another producer's. A repeat, or a counter
    further ahead than the manager can have sent by now, is still another producer's."""
    from types import SimpleNamespace

    from gateway.loop import FOREIGN_SYNC_SLACK, CycleLoop, LoopConfig, Timing

    def loop(k, since_start_s, task=True, counter=True):
        cfg = LoopConfig(n_cycles=1000, timing=Timing.REALTIME, sync_counter=counter)
        return SimpleNamespace(cfg=cfg, _k=k, _T=1e-3, _sync_task=object() if task else None,
                               _producer_start=time.time() - since_start_s,
                               _syncs_sent=0, _sync_thread=None)

    cycle, rule = CycleLoop._kernel_cycle, CycleLoop._foreign_sync
    busy = loop(33, 0.0405)  # 41 SYNCs sent by now at most
    assert cycle(busy, bytes([34])) == 34  # the next
    assert cycle(busy, bytes([0x24])) == 36  # 34 and 35 did not reach the gateway
    assert rule(busy, 36, bytes([0x24])) == ""
    assert cycle(busy, bytes([41 + FOREIGN_SYNC_SLACK])) == 41 + FOREIGN_SYNC_SLACK
    # beyond what the manager can have sent: the next cycle, and the rule names it
    assert cycle(busy, bytes([42 + FOREIGN_SYNC_SLACK])) == 34
    assert "ours would carry 22 (hex" in rule(busy, 34, bytes([42 + FOREIGN_SYNC_SLACK]))
    assert cycle(busy, bytes([33])) == 34 and rule(busy, 34, bytes([33]))  # a repeat
    # across the counter's overflow (240 → 1)
    wrap = loop(239, 0.3)
    assert cycle(wrap, bytes([2])) == 242 and rule(wrap, 242, bytes([2])) == ""
    # the first SYNC: counter 1 is cycle 1; 3 means the first two were not seen
    assert cycle(loop(0, 0.01), bytes([1])) == 1 and cycle(loop(0, 0.01), bytes([3])) == 3
    # no broadcast manager (the SYNC thread keeps its slots), or no counter: the next
    assert cycle(loop(33, 0.0405, task=False), bytes([0x24])) == 34
    assert cycle(loop(33, 0.0405, counter=False), b"") == 34
