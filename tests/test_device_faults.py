"""The emulated drive is never left unsafe and never fails silently: over-speed,
non-finite model state and handler exceptions fault with a named EMCY; setpoints do not
survive a run; reserved COB-IDs, block transfers and unbounded segmented downloads are
refused; a seeded fuzz of 100,000 frames at the device while it cycles."""

from __future__ import annotations

import dataclasses
import math
import queue
import random
import struct
import time
from collections import Counter
from collections.abc import Iterator

import pytest
from canopen.sdo import SdoAbortedError
from test_device import Rig, abort_code, sw_state

from dbc.cia301 import Emcy
from plant.cia402 import State
from plant.device import DriveDevice
from plant.params import DriveParams


@pytest.fixture
def rig() -> Iterator[Rig]:
    r = Rig()
    yield r
    r.close()


def run_until_emcy(rig: Rig, code: int, cycles: int, **setpoints) -> dict:
    """SYNC (with the given setpoints each cycle) until EMCY ``code``; the last TPDOs."""
    for _ in range(cycles):
        rig.setpoints(**setpoints)
        out = rig.sync()
        if code in rig.emcy_codes():
            return out
    rig.wait_emcy(code, 0.5)
    return out


def model_finite(dev: DriveDevice) -> bool:
    s = dev.drive.state
    return all(math.isfinite(x) for x in (s.w_m, s.psi_r_ab.real, s.psi_r_ab.imag,
                                          s.i_s_ab.real, s.i_s_ab.imag))


def fault_reset_and_enable(rig: Rig) -> None:
    rig.control(0x00)
    rig.control(0x80)
    rig.control(0x00)
    rig.enable()


# ------------------------------------------------------------------ over-speed, NaN


def test_overspeed_faults_with_emcy_0x8400():
    rig = Rig(DriveParams(mode="ideal"))
    try:
        assert rig.read(0x2201, 9) == pytest.approx(600.0)
        rig.write(0x2201, 9, 50.0)
        rig.enable()
        rig.nmt("OPERATIONAL")
        t = run_until_emcy(rig, 0x8400, 200, T_L=-50.0)  # the load drives the motor
        emcy = next(e for e in rig.node.emcy.log if e.code == 0x8400)
        assert emcy.register == 0x21  # generic + device profile specific
        assert Emcy.describe(0x8400).startswith("over-speed")
        assert t["TPDO3"]["w_m"] > 50.0
        assert sw_state(rig.sync()["TPDO1"]["statusword"]) == "fault"
        assert not rig.dev.drive.enabled
        assert rig.read(0x603F) == 0x8400
    finally:
        rig.close()


def test_overspeed_is_supervised_with_the_power_stage_off():
    """A dynamometer (the emulated load) spins the motor of a drive whose power stage is
    off: over-speed is still reported (EMCY 0x8400, Fault), once, not every cycle."""
    rig = Rig(DriveParams(mode="ideal"))
    try:
        rig.write(0x2201, 9, 50.0)
        rig.nmt("OPERATIONAL")  # never enabled: the power stage stays off
        t = run_until_emcy(rig, 0x8400, 400, T_L=-50.0)
        assert t["TPDO3"]["w_m"] > 50.0 and not rig.dev.drive.enabled
        for _ in range(50):
            rig.setpoints(T_L=-50.0)
            rig.sync()
        assert rig.emcy_codes().count(0x8400) == 1
        assert rig.read(0x603F) == 0x8400
    finally:
        rig.close()


def test_overspeed_limit_is_a_parameter():
    assert DriveParams().w_max == 600.0
    assert DriveParams(w_max=math.inf).w_max == math.inf
    with pytest.raises(ValueError, match="w_max"):
        DriveParams(w_max=0.0)
    assert DriveParams.from_mapping({"w_max": 300}).w_max == 300.0


def test_non_finite_model_state_faults_and_resets_the_model():
    """The issue's case (a large load, no over-speed limit, the integration blew up): the
    numerical failure is injected as a NaN speed of the running model."""
    rig = Rig(DriveParams(mode="ideal", w_max=math.inf))
    try:
        rig.enable()
        rig.nmt("OPERATIONAL")
        rig.setpoints(i_dq=5.0, T_L=-20.0)
        rig.sync()
        with rig.dev._lock:
            rig.dev.drive._w = math.nan
        t = rig.sync()
        rig.wait_emcy(0x6100)
        assert sw_state(t["TPDO1"]["statusword"]) == "fault"
        assert t["TPDO3"]["w_m"] == 0.0 and t["TPDO1"]["i_sa"] == 0.0  # the model at rest
        assert model_finite(rig.dev) and not rig.dev.drive.enabled
        assert rig.read(0x603F) == 0x6100
        assert rig.dev.account()["internal_errors"] == 0  # a fault, not a crash
        for _ in range(3):  # TPDOs keep coming, finite
            assert sw_state(rig.sync(n_tpdos=3)["TPDO1"]["statusword"]) == "fault"
        fault_reset_and_enable(rig)
        rig.setpoints(i_dq=2.0)
        rig.sync()
        assert rig.sync()["TPDO1"]["i_sa"] == pytest.approx(2.0)
    finally:
        rig.close()


# ------------------------------------------------------------------ handler exceptions


def test_handler_exception_in_the_cycle_is_emcy_and_fault(rig, monkeypatch):
    rig.enable()
    rig.nmt("OPERATIONAL")
    rig.setpoints(i_dq=1.0)
    rig.sync()

    def boom(*a, **k):
        raise RuntimeError("injected")

    monkeypatch.setattr(rig.dev.pdo, "transmit", boom)
    rig.net.send_message(0x80, b"\x05")
    rig.wait_emcy(0x1000)
    assert rig.dev.account()["internal_errors"] == 1
    assert rig.read(0x1000) == 0x00010192  # still answers SDO
    assert sw_state(rig.statusword()) == "fault" and not rig.dev.drive.enabled
    assert rig.read(0x603F) == 0x1000 and rig.read(0x1001) & 0x01
    monkeypatch.undo()
    fault_reset_and_enable(rig)
    rig.setpoints(i_dq=1.0)
    rig.sync()
    assert rig.sync()["TPDO1"]["statusword"] & 0x6F == 0x27


def test_timer_exception_is_emcy_and_fault(rig, monkeypatch):
    rig.enable()
    calls = []

    def boom(now):
        calls.append(now)
        if len(calls) == 1:
            raise RuntimeError("injected")
        return 0.5

    monkeypatch.setattr(rig.dev.nmt, "timers", boom)
    rig.dev._wake.set()
    rig.wait_emcy(0x1000)
    assert rig.dev.account()["internal_errors"] == 1
    assert sw_state(rig.statusword()) == "fault" and not rig.dev.drive.enabled


def test_sdo_hook_exception_is_aborted_then_emcy_and_fault(rig, monkeypatch):
    rig.enable()

    def boom():
        raise ZeroDivisionError("injected")

    hooks = dataclasses.replace(rig.dev.sdo._hooks, statusword=boom)
    monkeypatch.setattr(rig.dev.sdo, "_hooks", hooks)
    assert abort_code(lambda: rig.read(0x6041)) == 0x08000000
    rig.wait_emcy(0x1000)
    assert rig.dev.account()["internal_errors"] == 1
    assert rig.dev.cia402_state is State.FAULT and not rig.dev.drive.enabled
    assert rig.read(0x1000) == 0x00010192


# ------------------------------------------------------------------ setpoints


@pytest.mark.parametrize("stop", ["disable", "fault"])
def test_setpoints_of_a_run_are_not_applied_on_re_enable(rig, stop):
    """Run with 6.5 A; stop (disable operation, or a fault and its reset); re-enable by
    RPDO1 alone: the first cycles' current is ~0 until new setpoints arrive."""
    rig.enable()
    rig.nmt("OPERATIONAL")
    for _ in range(20):
        rig.setpoints(i_dq=6.5)
        t = rig.sync()["TPDO1"]
    assert abs(complex(t["i_sa"], t["i_sb"])) == pytest.approx(6.5, abs=0.05)
    if stop == "disable":
        rig.send("RPDO1", {"controlword": 0x07, "eps_0": 0.0, "w_0": 0.0})
    else:
        rig.net.send_message(0x301, bytes(7))  # wrong length: EMCY 0x8210
    for _ in range(40):  # the currents decay
        t = rig.sync()["TPDO1"]
    assert abs(complex(t["i_sa"], t["i_sb"])) < 0.01
    if stop == "fault":
        for cw in (0x80, 0x06, 0x07):
            rig.send("RPDO1", {"controlword": cw, "eps_0": 0.0, "w_0": 0.0})
            rig.sync()
    assert rig.read(0x2011) == 0  # the dictionary's i_sd_ref too (a later RPDO1 uses it)
    for _ in range(3):  # enable operation, RPDO1 only (new frame, no new RPDO2)
        rig.send("RPDO1", {"controlword": 0x0F, "eps_0": 1.0, "w_0": 0.0})
        t = rig.sync()["TPDO1"]
        assert abs(complex(t["i_sa"], t["i_sb"])) < 0.01
    assert t["statusword"] & 0x6F == 0x27
    rig.setpoints(i_dq=2.0)  # new setpoints: applied
    rig.sync()
    t = rig.sync()["TPDO1"]
    assert abs(complex(t["i_sa"], t["i_sb"])) == pytest.approx(2.0, abs=0.05)


# ------------------------------------------------------------------ COB-IDs


@pytest.mark.parametrize("cob", [0x000, 0x001, 0x07F, 0x101, 0x180, 0x581, 0x5FF, 0x601,
                                 0x67F, 0x6E0, 0x6FF, 0x701, 0x77F, 0x780, 0x7FF])
def test_restricted_cob_ids_are_refused(rig, cob):
    assert abort_code(lambda: rig.write(0x1005, None, cob)) == 0x06090030
    assert abort_code(lambda: rig.write(0x1014, None, cob)) == 0x06090030
    assert abort_code(lambda: rig.write(0x1014, None, 0x80000000 | cob)) == 0x06090030
    rig.write(0x1400, 1, 0x80000201)  # invalidate before changing (CiA 301)
    assert abort_code(lambda: rig.write(0x1400, 1, cob)) == 0x06090030
    assert abort_code(lambda: rig.write(0x1400, 1, 0x80000000 | cob)) == 0x06090030
    rig.write(0x1800, 1, 0xC0000181)
    assert abort_code(lambda: rig.write(0x1800, 1, 0x40000000 | cob)) == 0x06090030
    assert rig.read(0x1005) == 0x80 and rig.read(0x1014) == 0x81


def test_cob_id_collisions_refused_and_allowed_ids_accepted(rig):
    assert abort_code(lambda: rig.write(0x1005, None, 0x201)) == 0x06090030  # RPDO1
    assert abort_code(lambda: rig.write(0x1014, None, 0x181)) == 0x06090030  # TPDO1
    rig.write(0x1400, 1, 0x80000201)
    assert abort_code(lambda: rig.write(0x1400, 1, 0x080)) == 0x06090030  # SYNC
    assert abort_code(lambda: rig.write(0x1400, 1, 0x301)) == 0x06090030  # RPDO2
    rig.write(0x1400, 1, 0x80000080)  # not valid: no collision
    rig.write(0x1400, 1, 0x80000210)
    rig.write(0x1400, 1, 0x210)
    rig.write(0x1005, None, 0x082)
    rig.write(0x1014, None, 0x0FF)
    rig.write(0x1014, None, 0x80000081)
    rig.write(0x1005, None, 0x080)


# ------------------------------------------------------------------ SDO protocol


class RawSdo:
    """Raw SDO request frames on a rig's bus, responses from 0x581."""

    def __init__(self, rig: Rig) -> None:
        self.rig = rig
        self.responses: queue.Queue[bytes] = queue.Queue()
        rig.net.subscribe(0x581, lambda cob, data, ts: self.responses.put(bytes(data)))

    def request(self, data: bytes) -> bytes:
        self.rig.net.send_message(0x601, data)
        return self.responses.get(timeout=1.0)

    @staticmethod
    def abort_of(resp: bytes) -> int | None:
        return struct.unpack_from("<L", resp, 4)[0] if resp[0] == 0x80 else None


def test_block_transfers_are_aborted(rig):
    sdo = RawSdo(rig)
    up = sdo.request(bytes([0xA4, 0x00, 0x10, 0x00, 0x7F, 0, 0, 0]))  # block upload
    assert up[:4] == bytes([0x80, 0x00, 0x10, 0x00]) and sdo.abort_of(up) == 0x05040001
    down = sdo.request(bytes([0xC6, 0x17, 0x10, 0x00, 2, 0, 0, 0]))  # block download
    assert down[:4] == bytes([0x80, 0x17, 0x10, 0x00]) and sdo.abort_of(down) == 0x05040001
    assert rig.read(0x1000) == 0x00010192


def test_segmented_download_is_bounded(rig):
    sdo = RawSdo(rig)
    # declared 4 bytes for an UNSIGNED16: refused at the initiate
    r = sdo.request(bytes([0x21, 0x17, 0x10, 0x00, 4, 0, 0, 0]))
    assert sdo.abort_of(r) == 0x06070012
    # declared 2, then a segment of 7 bytes: refused at the segment
    assert sdo.request(bytes([0x21, 0x17, 0x10, 0x00, 2, 0, 0, 0]))[0] == 0x60
    r = sdo.request(bytes([0x00, 1, 2, 3, 4, 5, 6, 7]))
    assert sdo.abort_of(r) == 0x06070012
    # the case: a download that never ends does not grow a buffer
    assert sdo.request(bytes([0x21, 0x08, 0x10, 0x00, 4, 0, 0, 0]))  # 0x1008: read-only
    toggle = 0
    aborted = 0
    for _ in range(300):
        r = sdo.request(bytes([toggle, 1, 2, 3, 4, 5, 6, 7]))
        aborted += r[0] == 0x80
        toggle ^= 0x10
    assert aborted >= 299
    buf = rig.dev.sdo._node.sdo._buffer
    assert buf is None or len(buf) <= 7
    # no size declared: bounded by the object's size (UNSIGNED16: 2 bytes)
    assert sdo.request(bytes([0x20, 0x17, 0x10, 0x00, 0, 0, 0, 0]))[0] == 0x60
    assert sdo.abort_of(sdo.request(bytes([0x00, 1, 2, 3, 0, 0, 0, 0]))) == 0x06070012
    # a segment with no download under way
    assert sdo.abort_of(sdo.request(bytes([0x00] * 8))) == 0x05040001
    # a proper segmented download still works
    rig.node.sdo.download(0x1017, 0, b"\x10\x00", force_segment=True)
    assert rig.read(0x1017) == 16
    assert rig.dev.account()["internal_errors"] == 0


# ------------------------------------------------------------------ fuzz

FUZZ_FRAMES = 100_000
RPDO_LENGTHS = {0x201: 6, 0x301: 8, 0x401: 2}


def _sdo_write(index: int, sub: int, value: int) -> tuple[int, bytes]:
    return 0x601, struct.pack("<BHBL", 0x2B, index, sub, value)  # 2 bytes expedited


def _recovery(rng: random.Random) -> list[tuple[int, bytes]]:
    """NMT start, fault reset, enable operation, fresh setpoints (as a master would)."""
    frames = [(0x000, bytes([0x01, 0x01]))]
    frames += [_sdo_write(0x6040, 0, cw) for cw in (0x00, 0x80, 0x06, 0x07, 0x0F)]
    i_d, i_q = rng.uniform(-3, 3), rng.uniform(-3, 3)
    frames.append((0x301, struct.pack("<hhhh", round(i_d * 1000), round(i_q * 1000), 0, 0)))
    frames.append((0x201, struct.pack("<HHh", 0x0F, 0, 0)))
    return frames


def _random_frame(rng: random.Random) -> tuple[int, bytes]:
    x = rng.random()
    if x < 0.30:  # SYNC, with or without a counter (sometimes malformed)
        n = rng.choice((0, 1, 1, 1, 2))
        return 0x080, bytes(rng.getrandbits(8) for _ in range(n))
    if x < 0.45:  # RPDOs, mostly of the right length and mostly keeping the drive enabled
        cob = rng.choice(tuple(RPDO_LENGTHS))
        n = RPDO_LENGTHS[cob] if rng.random() < 0.99 else rng.randint(0, 8)
        data = bytearray(rng.randbytes(n))
        if n == 6 and cob == 0x201 and rng.random() < 0.8:
            data[0:2] = b"\x0f\x00"  # enable operation
        elif n == 8 and cob == 0x301 and rng.random() < 0.8:
            struct.pack_into("<hh", data, 0, rng.randint(-15000, 15000),
                             rng.randint(-15000, 15000))  # within i_trip
        elif n == 2 and cob == 0x401 and rng.random() < 0.995:
            struct.pack_into("<h", data, 0, rng.randint(-500, 500))  # T_L within ±5 N·m
        return cob, bytes(data)
    if x < 0.55:  # SDO requests, random commands
        n = 8 if rng.random() < 0.9 else rng.randint(0, 8)
        return 0x601, rng.randbytes(n)
    if x < 0.57:  # NMT, heartbeat of the master
        return rng.choice((0x000, 0x77F)), rng.randbytes(rng.randint(0, 8))
    return rng.randint(0, 0x7FF), rng.randbytes(rng.randint(0, 8))


def test_fuzz_100k_frames_at_the_cycling_drive(monkeypatch):
    """Seeded: 100,000 random frames, handled by the device's frame handler (as the
    receiver does, under its lock) with the drive re-enabled every 250 frames, and 2,000
    more through the virtual bus. Never silent, never unsafe, still answering."""
    rng = random.Random(20261123)
    rig = Rig()
    dev = rig.dev
    emcys: Counter[int] = Counter()
    error = dev.emcy.error

    def counting_error(code):
        emcys[code] += 1
        error(code)

    monkeypatch.setattr(dev.emcy, "error", counting_error)
    try:
        rig.write(0x1016, 1, (0x7F << 16) | 1000)
        rig.enable()
        rig.nmt("OPERATIONAL")
        seen_ranges: set[int] = set()
        lengths: Counter[int] = Counter()
        enabled_frames = 0
        start = time.monotonic()
        for k in range(FUZZ_FRAMES):
            frames = _recovery(rng) if k % 250 == 0 else [_random_frame(rng)]
            for can_id, data in frames:
                seen_ranges.add(can_id >> 7)
                lengths[len(data)] += 1
                with dev._lock:
                    dev._handle(can_id, data)
                    state = dev.cia402_state
                    assert not dev.drive.enabled or state is State.OPERATION_ENABLED, (k, state)
                    enabled_frames += state is State.OPERATION_ENABLED
            if k % 5000 == 0:
                with dev._lock:
                    assert model_finite(dev), k
        elapsed = time.monotonic() - start
        # through the bus too (the receiver thread)
        for _ in range(2000):
            can_id, data = _random_frame(rng)
            rig.net.send_message(can_id, data)
        acc = dev.account()
        assert seen_ranges == set(range(16)) and set(lengths) == set(range(9))
        print({f"0x{c:04X}": n for c, n in emcys.items()})
        assert acc["cycles"] > 20_000 and enabled_frames > FUZZ_FRAMES // 10
        # back to a state that answers SDO (the fuzz may have left it STOPPED)
        rig.node.nmt.state = "PRE-OPERATIONAL"
        deadline = time.monotonic() + 3.0
        while True:
            try:
                assert rig.read(0x1000) == 0x00010192
                break
            except (SdoAbortedError, Exception):
                if time.monotonic() > deadline:
                    raise
                rig.node.nmt.state = "PRE-OPERATIONAL"
        with dev._lock:
            acc = dev.account()
            assert acc["internal_errors"] == emcys[Emcy.INTERNAL]  # none went silent
            assert acc["internal_errors"] == 0  # and the handlers raised nothing (no bug)
            assert dev.cia402_state in set(State)
            assert model_finite(dev)
            assert not dev.drive.enabled or dev.cia402_state is State.OPERATION_ENABLED
        print(f"fuzz: {elapsed:.1f} s, {acc['cycles']} cycles, {acc['fault_count']} faults, "
              f"{acc['internal_errors']} internal errors, {enabled_frames} frames enabled")
    finally:
        rig.close()


def test_every_missing_sub_index_is_an_abort_not_a_fault(emulator):
    """A third-party master reads one sub-index past the end of every object of the
    dictionary (0x1003 past its entries, 0x1016 past sub 1 …): each is answered with SDO
    abort 0x06090011 (sub-index does not exist), and the device stays out of Fault."""
    import canopen
    from canopen.sdo.exceptions import SdoAbortedError

    from dbc import EDS_PATH

    emu = emulator()
    od = canopen.import_od(str(EDS_PATH), 1)
    net = canopen.Network()
    net.connect(interface="virtual", channel=emu.channel)
    try:
        node = net.add_node(1, canopen.ObjectDictionary())
        node.sdo.RESPONSE_TIMEOUT = 1.0
        codes = {}
        for obj in od.values():
            subs = getattr(obj, "subindices", None)
            past = (max(subs) + 1) if subs else 1
            try:
                node.sdo.upload(obj.index, past)
                codes[(obj.index, past)] = None
            except SdoAbortedError as exc:
                codes[(obj.index, past)] = exc.code
        wrong = {f"0x{i:04X}.{s}": c for (i, s), c in codes.items() if c != 0x06090011}
        assert not wrong, wrong
        account = emu.device.account()
        assert account["internal_errors"] == 0 and account["fault_count"] == 0, account
        assert account["state"] != "FAULT"
    finally:
        net.disconnect()
