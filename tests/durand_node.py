"""A third-party CiA 301 device: a responder node of `durand` (PyPI; "CANopen library for
responder nodes", not written here) on a python-can bus. durand's own object dictionary as
its ``Node`` builds it (device type 0x1000 = 0: no device profile; 128 SDO servers, 512
RPDOs and TPDOs, EMCY, heartbeat, LSS), with a vendor id and product code that are not the
emulator's, and a heartbeat of 1 s. Its boot-up is sent when the node is built.

In a test process: :class:`DurandNode` (the ``virtual`` interface, durand's scheduler in a
thread). As a process of its own (tests/test_durand_vcan.py)::

    python tests/durand_node.py -i socketcan -c vcan0 --node 5 --state STATE.json

runs until SIGTERM/SIGINT, then writes ``{"before": ..., "after": ...}`` (the writable
entries of its dictionary when it started and when it was told to stop) to STATE.json.
"""

from __future__ import annotations

import argparse
import json
import signal
import sys
import threading
from typing import Any

import can

#: Not the emulator's identity (dbc/cia402.eds: vendor 0, product 0x402) nor canopend's (0).
VENDOR = 0x00000D7A
PRODUCT = 0x00005050
HEARTBEAT_MS = 1000


def durand_missing() -> str | None:
    """None when durand imports; else why not (tests fail on it under CI=true)."""
    try:
        import durand  # noqa: F401
    except ImportError as exc:
        return f"durand is not installed ({exc}): pip install -e '.[test]'"
    return None


def writable_entries(od) -> dict[str, Any]:
    """``"IIII.SS"`` → value of every writable (rw/wo) entry of a durand dictionary."""
    from durand import Variable

    out: dict[str, Any] = {}
    for index, obj in od:
        entries = [(0, obj)] if isinstance(obj, Variable) else list(obj)
        for sub, var in entries:
            if var.writable:
                value = od.read(index, sub)
                out[f"{index:04X}.{sub:02X}"] = value.hex() if isinstance(value, bytes) \
                    else value
    return out


class TimerScheduler:
    """durand's scheduler interface (add, cancel, lock) on threading.Timer; after
    :meth:`close` no callback runs (one running is waited for)."""

    def __init__(self) -> None:
        self._lock = threading.RLock()  # held while a callback runs; it may add() again
        self._timers: set[threading.Timer] = set()
        self._closed = False

    @property
    def lock(self):
        return self._lock

    def add(self, delay: float, callback, args=(), kwargs=None) -> threading.Timer:
        def fire() -> None:
            with self._lock:
                self._timers.discard(timer)
                if not self._closed:
                    callback(*args, **(kwargs or {}))

        timer = threading.Timer(delay, fire)
        timer.daemon = True
        with self._lock:
            if not self._closed:
                self._timers.add(timer)
                timer.start()
        return timer

    def cancel(self, entry: threading.Timer) -> None:
        entry.cancel()
        with self._lock:
            self._timers.discard(entry)

    def close(self) -> None:
        with self._lock:
            self._closed = True
            for t in self._timers:
                t.cancel()
            self._timers.clear()


class DurandNode:
    """durand's ``Node`` at ``node_id`` on its own Bus object of ``channel``; started."""

    def __init__(self, interface: str, channel: str, node_id: int = 5) -> None:
        import durand

        self.bus = can.Bus(interface=interface, channel=channel)
        # durand's timers (heartbeat, EMCY inhibit, TPDO events) run on the scheduler it is
        # given; its default needs an asyncio loop, its SyncScheduler cannot be stopped
        # while a heartbeat is due: threading.Timer instead
        self._scheduler = TimerScheduler()
        self._previous = durand.get_scheduler()
        durand.set_scheduler(self._scheduler)
        self.network = durand.CANBusNetwork(self.bus)
        self.node = durand.Node(self.network, node_id)  # sends its boot-up
        od = self.node.object_dictionary
        od.write(0x1018, 1, VENDOR)  # a local write (the entries are read-only by SDO)
        od.write(0x1018, 2, PRODUCT)
        od.write(0x1017, 0, HEARTBEAT_MS)  # starts the heartbeat producer

    @property
    def object_dictionary(self):
        return self.node.object_dictionary

    def nmt_state(self) -> int:
        return int(self.node.nmt.state)

    def snapshot(self) -> dict[str, Any]:
        with self.network.lock:  # not while a frame is being handled
            return writable_entries(self.node.object_dictionary)

    def close(self) -> None:
        import durand

        self._scheduler.close()  # no timer fires after this
        self.network.stop()
        self.bus.shutdown()
        durand.set_scheduler(self._previous)


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("-i", "--interface", default="socketcan")
    ap.add_argument("-c", "--channel", default="vcan0")
    ap.add_argument("--node", type=int, default=5)
    ap.add_argument("--state", help="write the dictionary's writable entries here at exit")
    args = ap.parse_args(argv)
    stop = threading.Event()
    for sig in (signal.SIGTERM, signal.SIGINT):
        signal.signal(sig, lambda *_: stop.set())
    node = DurandNode(args.interface, args.channel, args.node)
    before = node.snapshot()
    print(f"durand node {args.node} on {args.interface}:{args.channel}: started", flush=True)
    while not stop.wait(0.2):
        pass
    after = node.snapshot()
    state = {"before": before, "after": after, "nmt_state": node.nmt_state()}
    node.close()
    if args.state:
        with open(args.state, "w") as f:
            json.dump(state, f)
    print("durand node: stopped", flush=True)
    return 0


if __name__ == "__main__":
    sys.exit(main())
