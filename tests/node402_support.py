"""A master we did not write: python-canopen's BaseNode402 against an emulated drive (the
emulator, or a twin of another drive's EDS) on a python-can ``virtual`` bus, in lockstep:
the target by RPDO1, a SYNC, the TPDOs back (tests/test_standard_modes.py,
tests/test_profile_modes.py, tests/test_twin.py); or against a drive in another process."""

from __future__ import annotations

import time
import uuid
from collections.abc import Callable, Sequence
from pathlib import Path

import can
import canopen
from canopen.profiles.p402 import BaseNode402

from plant.device import DriveDevice


class Master402:
    """``make_device(bus)`` started at node ``node`` on a fresh virtual channel, or (None) a
    drive already on ``interface``/``channel``; a BaseNode402 built from ``eds`` on another
    Bus object of that channel."""

    def __init__(self, make_device: Callable[[can.BusABC], DriveDevice] | None, node: int,
                 eds: Path | str | canopen.ObjectDictionary, interface: str = "virtual",
                 channel: str | None = None) -> None:
        channel = channel or f"test-402-{uuid.uuid4().hex}"
        self.dev_bus = self.dev = None
        if make_device is not None:
            self.dev_bus = can.Bus(interface=interface, channel=channel)
            self.dev = make_device(self.dev_bus)
        self.net = canopen.Network()
        self.net.NOTIFIER_CYCLE = 0.05
        self.net.connect(interface=interface, channel=channel)
        self.node = BaseNode402(node, eds if isinstance(eds, canopen.ObjectDictionary)
                                else str(eds))
        self.net.add_node(self.node)
        self.node.sdo.RESPONSE_TIMEOUT = 0.5
        # a loaded host may hold either side for a while: the state walk waits, not fails
        self.node.TIMEOUT_SWITCH_STATE_FINAL = 20.0
        self.node.TIMEOUT_SWITCH_STATE_SINGLE = 5.0
        self.node.TIMEOUT_SWITCH_OP_MODE = 5.0
        self.node.TIMEOUT_CHECK_TPDO = 5.0
        self.target: int | None = None
        if self.dev is None:
            return
        booted: list[int] = []
        self.node.nmt.add_heartbeat_callback(booted.append)  # before the device boots
        self.dev.start()
        deadline = time.monotonic() + 5.0
        while 0 not in booted:
            assert time.monotonic() < deadline, "no boot-up from the emulated drive"
            time.sleep(0.005)

    def close(self) -> None:
        if self.dev is not None:
            self.dev.stop()
        self.net.disconnect()
        if self.dev_bus is not None:
            self.dev_bus.shutdown()

    def configure(self, mode: str, target: int | None,
                  rpdo1: Sequence[int] | None = None,
                  tpdos: Sequence[Sequence[int]] | None = None,
                  period_us: int | None = 1000) -> None:
        """Cycle period (0x1006, unless None), mode by SDO 0x6060 (checked against 0x6502),
        the PDOs: ``rpdo1``/``tpdos`` remapped through the master's PDO API (every other
        PDO off, all on every SYNC), or (None) the drive's own mapping read back; then
        OPERATIONAL and Operation enabled. ``target``: the object the cycles stream in
        RPDO1 (None: none)."""
        node = self.node
        node.nmt.state = "PRE-OPERATIONAL"
        if period_us is not None:
            node.sdo[0x1006].raw = period_us
        node.op_mode = mode
        assert node.sdo[0x6061].raw == node.sdo[0x6060].raw
        node.tpdo.read()
        node.rpdo.read()
        if rpdo1 is not None or tpdos is not None:
            for pdo in (*node.rpdo.values(), *node.tpdo.values()):
                pdo.clear()
                pdo.enabled = False
            used = [node.rpdo[1], *(node.tpdo[k] for k in range(1, len(tpdos or ()) + 1))]
            for index in rpdo1 or ():
                node.rpdo[1].add_variable(index)
            for k, objects in enumerate(tpdos or (), 1):
                for index in objects:
                    node.tpdo[k].add_variable(index)
            for pdo in used:
                pdo.trans_type = 1
                pdo.enabled = True
            node.rpdo.save()
            node.tpdo.save()
        node.setup_402_state_machine(read_pdos=False)
        node.nmt.state = "OPERATIONAL"
        self.target = target
        # the state machine is walked while SYNCs and the synchronous RPDO1 run
        if target is not None:
            node.rpdo[1][target].raw = 0
        node.rpdo[1].start(0.005)
        self.net.sync.start(0.005)
        try:
            node.state = "OPERATION ENABLED"
        finally:  # stopped once (SocketCAN's broadcast manager refuses a second stop)
            self.net.sync.stop()
            node.rpdo[1].stop()

    def cycle(self, value: int | None = None) -> int:
        """One lockstep cycle: ``value`` (if given) as the target in RPDO1, RPDO1, SYNC, and
        wait for the last enabled TPDO (the drive sends them in order) → the statusword."""
        node = self.node
        if value is not None:
            assert self.target is not None
            node.rpdo[1][self.target].raw = value
        node.rpdo[1].transmit()
        last = [p for p in node.tpdo.values() if p.enabled][-1]
        with last.receive_condition:  # armed before the SYNC: a fast answer is not missed
            last.is_received = False
            self.net.sync.transmit()
            assert last.receive_condition.wait_for(lambda: last.is_received, 10.0), \
                "no TPDO within 10 s of the SYNC"
        return self.value(0x6041)

    def value(self, index: int) -> int:
        """The raw value of ``index`` in the last TPDOs received."""
        return self.node.tpdo_values[index]
