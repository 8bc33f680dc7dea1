"""Helpers of the gateway tests: the emulated drive on a fresh virtual channel, a gateway
run against it (CLI or in a thread), waiting for cycles, checking the drive ended safe."""

from __future__ import annotations

import atexit
import functools
import itertools
import re
import shutil
import tempfile
import threading
import time
import warnings
from pathlib import Path

import can
import numpy as np

import gateway
from dbc.cia402 import State
from dbc.motor import MotorParams
from dbc.timing import SIM_HEARTBEAT_TIMEOUT_MS
from gateway.cli import main
from gateway.drive_profile import load_drive_profile
from gateway.reference import paper_profile
from gateway.runner import BusTarget
from gateway.session import Output
from gateway.session import run as session_run
from gateway.spec import RunSpec
from gateway.stop import StopSignals
from plant.device import DriveDevice
from plant.params import DriveParams

MOTOR = MotorParams.paper()
_channels = itertools.count()


class Emulator:
    """The emulated drive on its own Bus object of a fresh virtual channel."""

    def __init__(self, mode: str = "ideal", node: int = 1) -> None:
        self.channel = f"test-gw-{next(_channels)}-{time.monotonic_ns()}"
        self.bus = can.Bus(interface="virtual", channel=self.channel)
        self.device = DriveDevice(self.bus, node_id=node, motor=MOTOR,
                                  drive_params=DriveParams(mode=mode))
        self.device.start()

    def close(self) -> None:
        self.device.stop()
        self.bus.shutdown()


def emulator_factory():
    """Generator behind the ``emulator`` fixture (tests/conftest.py)."""
    emus: list[Emulator] = []

    def make(mode: str = "ideal", node: int = 1) -> Emulator:
        emus.append(Emulator(mode, node))
        return emus[-1]

    yield make
    for e in emus:
        e.close()


@functools.cache
def _patient_drive_profile(name: str = "emulator") -> Path:
    """The emulator's drive profile with the drive watching the gateway's heartbeat for
    :data:`dbc.timing.SIM_HEARTBEAT_TIMEOUT_MS` (1 s) instead of 300 ms, as `hil-gateway sim`
    does (written once per test process; the file is what ``--drive`` takes, and
    :func:`run_in_thread` loads the same one). Why: gateway, emulator and test share one
    interpreter in these tests, and on a loaded 2-core CI host the heartbeat thread once went
    unscheduled long enough to trip the drive (EMCY 0x8130) before cycle 1. No test using
    these helpers is about that timeout (tests/test_device.py and the two-process tests
    are)."""
    text = (Path(gateway.__file__).parent / "drives" / f"{name}.toml").read_text()
    text, n = re.subn(r"(?m)^heartbeat_timeout_ms = 300\b",
                      f"heartbeat_timeout_ms = {SIM_HEARTBEAT_TIMEOUT_MS}", text)
    assert n == 1, f"gateway/drives/{name}.toml: heartbeat_timeout_ms = 300 not found"
    folder = Path(tempfile.mkdtemp(prefix="hil-drive-"))
    atexit.register(shutil.rmtree, folder, ignore_errors=True)  # when the test process ends
    path = folder / f"{name}-1s.toml"
    path.write_text(text)
    return path


def gateway_run(emu: Emulator, out: Path, *args: str) -> int:
    """``hil-gateway run`` against ``emu`` in this process, with the drive profile of
    :func:`_patient_drive_profile` unless the test names its own ``--drive``."""
    drive = [] if "--drive" in args else ["--drive", str(_patient_drive_profile())]
    return main(["run", "-i", "virtual", "-c", emu.channel, "--out", str(out), *drive, *args])


def assert_disabled(emu: Emulator) -> None:
    """The shutdown left the drive's power stage off and the drive not enabled."""
    dev = emu.device
    deadline = time.monotonic() + 1.0
    while dev.cia402_state == State.OPERATION_ENABLED and time.monotonic() < deadline:
        time.sleep(0.01)
    assert dev.cia402_state != State.OPERATION_ENABLED
    assert not dev.drive.enabled
    assert dev.nmt_state != "OPERATIONAL", dev.account()


def bus_run(bus: can.BusABC, drive, out: Path, spec: RunSpec, signals: StopSignals,
            profile=None) -> dict:
    """One gateway run on ``bus`` (left open) through :func:`gateway.session.run`, writing
    into ``out`` (reused); returns the summary."""
    target = BusTarget(drive, lambda *_: (bus, "virtual:test", lambda: None))
    return session_run(spec, profile or paper_profile(), MOTOR, target=target,
                       output=Output(str(out), force=True), signals=signals).summary


def closed_run(bus: can.BusABC, out: Path, spec: RunSpec) -> dict:
    """:func:`bus_run` on ``bus`` with the drive profile of :func:`_patient_drive_profile`
    and no stop request; ``bus`` shut down after it; returns the summary."""
    try:
        return bus_run(bus, load_drive_profile(str(_patient_drive_profile())), out, spec,
                       StopSignals())
    finally:
        bus.shutdown()


def host_losses(k: np.ndarray, withheld: np.ndarray, window: int,
                skip: tuple[int, ...] | list[int] = (), since: int = 0) -> int:
    """The most cycles a real-time run lost on its own (missed, or withheld: its setpoints
    ready late) within any ``window`` cycles from slot ``since`` on; ``k`` the slots of the
    run's rows (``signals.csv``), ``withheld`` its column; the slots of a test's own holds
    (each in ``skip`` and the two after it) not counted. A host loaded beyond 20 % of the
    loop's miss-rate window (100 ms) is beyond what a default run accepts: its guards stop
    such a run."""
    lost = np.zeros(int(k[-1]) + 2)
    lost[np.setdiff1d(np.arange(1, int(k[-1]) + 1), k)] = 1
    lost[k[np.asarray(withheld) > 0]] = 1
    for h in skip:
        lost[h:h + 3] = 0
    return int(np.convolve(lost[max(since, 0):], np.ones(window), "full").max())


def run_in_thread(emu: Emulator, out: Path, cfg: RunSpec, signals: StopSignals):
    """A gateway run in a thread of this process, against ``emu``, with the drive profile of
    :func:`_patient_drive_profile`."""
    result: dict = {}
    bus = can.Bus(interface="virtual", channel=emu.channel, receive_own_messages=True)
    drive = load_drive_profile(str(_patient_drive_profile()))
    assert drive.heartbeat_timeout_ms == SIM_HEARTBEAT_TIMEOUT_MS == 1000

    def target() -> None:
        try:
            result["summary"] = bus_run(bus, drive, out, cfg, signals)
        except BaseException as exc:
            result["error"] = exc
        finally:
            bus.shutdown()

    th = threading.Thread(target=target)
    th.start()
    return th, result


def wait_cycles(out_device: DriveDevice, n: int, timeout: float = 10.0,
                run: threading.Thread | None = None) -> bool:
    """Wait until the drive has seen ``n`` cycles: True; False if the gateway's ``run``
    thread ended before."""
    deadline = time.monotonic() + timeout
    while out_device.account()["cycles"] < n:
        if run is not None and not run.is_alive():
            return out_device.account()["cycles"] >= n
        assert time.monotonic() < deadline, "the loop did not start"
        time.sleep(0.005)
    return True


def assert_lost_to_the_host(summary: dict) -> None:
    """A real-time run that ended before its test could act: by the divergence guard,
    safely, its reason naming the cycles that gave the drive no new setpoints (the host
    lost the loop's rate, :meth:`gateway.loop.CycleLoop._lost_note`)."""
    run = summary["run"]
    assert run["stop"] == "DIVERGED" and summary["shutdown"]["safe"], run["stop_reason"]
    assert "gave the drive no new setpoints" in run["stop_reason"], run["stop_reason"]


def realtime_run_past(make_emulator, out: Path, cfg: RunSpec, cycles: int,
                      attempts: int = 3
                      ) -> tuple[Emulator, threading.Thread, dict, StopSignals]:
    """A real-time gateway run in a thread (:func:`run_in_thread`) on a fresh emulated
    drive, once the drive has seen ``cycles`` cycles: (emulator, thread, result, signals),
    for a test that then acts on the running loop.

    A host that stalls can end such a run first, on its own: once the drive has held old
    setpoints long enough its divergence guard stops the run (seen once in CI: the first
    168 cycles lost, the flux never built, "field orientation lost" in cycle 169). Such an
    end must be safe and named with the lost cycles (checked, and reported as a warning);
    the run is then started again on a fresh drive, ``attempts`` times in all."""
    for attempt in range(1, attempts + 1):
        emu = make_emulator()
        signals = StopSignals()
        th, result = run_in_thread(emu, out, cfg, signals)
        if wait_cycles(emu.device, cycles, run=th):
            return emu, th, result, signals
        th.join(10)
        assert "error" not in result, result.get("error")
        s = result["summary"]
        run = s["run"]
        assert_lost_to_the_host(s)
        assert_disabled(emu)
        warnings.warn(f"attempt {attempt} of {attempts}: the host lost the real-time run "
                      f"before cycle {cycles}, which stopped safely: {run['stop_reason']}",
                      stacklevel=2)
    raise AssertionError(f"the host lost the real-time run before cycle {cycles} "
                         f"{attempts} times in a row")


