"""Lockstep throughput of the emulated drive alone on python-can's virtual bus.

Run: .venv/bin/python bench/bench_device.py [--cycles 3000] [--repeats 5] [--mode current-loop]
     [--profile] [--quick] [--json [FILE]]

A minimal master (raw python-can, no python-canopen in the loop) configures the device by
SDO, enables it, starts it, then repeats: send SYNC, wait for the last TPDO (TPDO3), send
RPDO1..3. Cycle period 1 ms (0x1006), current loop at f_pwm = 10 kHz (10 internal steps per
cycle). Prints the median cycles/s over the repeats and the ratio to real time
(target ≥ 5000 cycles/s, i.e. ≥ 5× real time). ``--profile`` adds one run with cProfile
around the device's per-SYNC path (it runs in the device's receiver thread). ``--quick``:
500 cycles x 2.

A run that fails (no TPDO3 within 1 s, an SDO abort, cycles missing or a fault in the
device's account) is a failed measurement: ``FAILED: <reason>`` in place of its figure,
exit status 1 (bench/_common.py); so is a missed target. ``--json`` keys: ``mode``,
``cycles``, ``repeats``, ``virtual_cycles_per_s`` and ``inprocess_cycles_per_s`` (medians),
``virtual_cycles_per_s_runs``, ``inprocess_cycles_per_s_runs``, ``target_cycles_per_s``,
``failed`` (with ``warm-up`` and ``profile``, null, when those runs fail).
"""

from __future__ import annotations

import argparse
import cProfile
import pstats
import statistics
import struct
import time

import can
from _common import Figures, RunError, add_json_option, failed_text, the_run

from dbc import load_codec
from gateway.transport import InProcessChannel
from plant.device import DriveDevice
from plant.params import DriveParams

TARGET = 5000.0


class Master:
    """Raw-frame master: SDO expedited writes, NMT, SYNC, RPDOs."""

    def __init__(self, bus: can.BusABC, node: int = 1) -> None:
        self.bus, self.node = bus, node
        self.codec = load_codec(node)

    def _wait(self, can_id: int, timeout: float = 1.0) -> can.Message:
        end = time.monotonic() + timeout
        while True:
            msg = self.bus.recv(max(end - time.monotonic(), 0.0))
            if msg is None:
                raise TimeoutError(f"no frame 0x{can_id:03X}")
            if msg.arbitration_id == can_id:
                return msg

    def sdo_write(self, index: int, sub: int, value: int, size: int) -> None:
        cmd = 0x23 | ((4 - size) << 2)
        data = struct.pack("<BHB", cmd, index, sub) + value.to_bytes(size, "little",
                                                                      signed=value < 0)
        self.bus.send(can.Message(arbitration_id=0x600 + self.node,
                                  data=data.ljust(8, b"\0"), is_extended_id=False))
        reply = self._wait(0x580 + self.node)
        if reply.data[0] != 0x60:
            raise RuntimeError(f"SDO 0x{index:04X}:{sub} aborted: {bytes(reply.data).hex()}")

    def nmt(self, cmd: int) -> None:
        self.bus.send(can.Message(arbitration_id=0, data=[cmd, self.node], is_extended_id=False))

    def run(self, cycles: int) -> float:
        """Lockstep cycles; returns the elapsed wall time, s."""
        c = self.codec
        send, recv = self.bus.send, self.bus.recv
        last_tpdo = c.frame_id("TPDO3")
        ids = {n: c.frame_id(n) for n in ("RPDO1", "RPDO2", "RPDO3")}
        sync = can.Message(arbitration_id=0x80, data=b"\x01", is_extended_id=False)
        t0 = time.perf_counter()
        for k in range(1, cycles + 1):
            sync.data = bytearray([k % 240 + 1])
            send(sync)
            while True:
                msg = recv(1.0)
                if msg is None:
                    raise TimeoutError(f"cycle {k}: no TPDO3")
                if msg.arbitration_id == last_tpdo:
                    break
            t = k * 1e-3
            frames = (
                ("RPDO1", {"controlword": 0x0F, "eps_0": 10.0 * t, "w_0": 10.0}),
                ("RPDO2", {"i_sd_ref": 4.0, "i_sq_ref": 4.0, "u_sd_ref": 0.0, "u_sq_ref": 0.0}),
                ("RPDO3", {"T_L": 0.0}),
            )
            for name, values in frames:
                send(can.Message(arbitration_id=ids[name], data=c.encode(name, values),
                                 is_extended_id=False))
        return time.perf_counter() - t0


def one_run(cycles: int, mode: str, profile: bool = False, transport: str = "virtual"
            ) -> float:
    """Cycles per second of one fresh device; RunError when the run fails."""
    with the_run():
        return _one_run(cycles, mode, profile, transport)


def _one_run(cycles: int, mode: str, profile: bool, transport: str) -> float:
    if transport == "virtual":
        channel = f"bench-device-{time.monotonic_ns()}"
        mbus = can.Bus(interface="virtual", channel=channel)
        dbus = can.Bus(interface="virtual", channel=channel)
    else:
        medium = InProcessChannel("bench-device")
        mbus, dbus = medium.bus(), medium.bus()
    dev = DriveDevice(dbus, 1, drive_params=DriveParams(mode=mode))
    prof = cProfile.Profile() if profile else None
    if prof is not None:  # profile the device's per-SYNC path where it runs
        cycle = dev._cycle

        def profiled(counter: int) -> None:
            prof.runcall(cycle, counter)

        dev._cycle = profiled  # type: ignore[method-assign]
    dev.start()
    try:
        m = Master(mbus)
        m._wait(0x701)  # boot-up
        m.sdo_write(0x1017, 0, 0, 2)  # no heartbeat during the run
        for cw in (0x06, 0x07, 0x0F):
            m.sdo_write(0x6040, 0, cw, 2)
        m.nmt(0x01)
        elapsed = m.run(cycles)
        acc = dev.account()
        if acc["cycles"] != cycles or acc["fault_count"] != 0:
            raise RunError(f"the device's account after {cycles} cycles: {acc}")
    finally:
        dev.stop()
        mbus.shutdown()
        dbus.shutdown()
    if prof is not None:
        pstats.Stats(prof).sort_stats("cumulative").print_stats(18)
    return cycles / elapsed


def rates(cycles: int, mode: str, transport: str, repeats: int) -> list[float]:
    out = []
    for r in range(repeats):
        with the_run(f"run {r + 1} of {repeats}"):
            out.append(one_run(cycles, mode, transport=transport))
    return out


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    p.add_argument("--cycles", type=int, help="cycles per run (3000; --quick 500)")
    p.add_argument("--repeats", type=int, help="runs per transport (5; --quick 2)")
    p.add_argument("--quick", action="store_true", help="500 cycles x 2 (unless given)")
    p.add_argument("--mode", default="current-loop", choices=("ideal", "current-loop",
                                                              "voltage"))
    p.add_argument("--profile", action="store_true")
    add_json_option(p)
    args = p.parse_args(argv)
    cycles = args.cycles if args.cycles is not None else 500 if args.quick else 3000
    repeats = args.repeats if args.repeats is not None else 2 if args.quick else 5
    fig = Figures(mode=args.mode, cycles=cycles, repeats=repeats, target_cycles_per_s=TARGET)
    try:
        one_run(200, args.mode)  # warm-up
    except RunError as exc:
        fig.fail("warm-up", str(exc))
        print(f"bench_device: warm-up run of 200 cycles: {failed_text(str(exc))}")
    ok = True
    for transport in ("virtual", "inprocess"):  # interleaved repeats: same machine load
        name = f"{transport}_cycles_per_s"
        runs = fig.measure(f"{name}_runs", rates, cycles, args.mode, transport, repeats)
        head = (f"bench_device [{transport}]: mode {args.mode}, 1 ms cycle, f_pwm 10 kHz, "
                f"{cycles} cycles x {repeats}:")
        if runs is None:
            fig.fail(name, fig.failed[f"{name}_runs"])
            print(f"{head} {failed_text(fig.failed[name])}")
            continue
        med = fig.put(name, statistics.median(runs))
        ok = ok and (med >= TARGET or transport != "virtual")
        print(f"{head} median {med:.0f} cycles/s (min {min(runs):.0f}, max {max(runs):.0f}) = "
              f"{med / 1000:.1f}x real time; target {TARGET:.0f}: "
              f"{'met' if med >= TARGET else 'MISSED'}")
    if args.profile:
        try:
            one_run(cycles, args.mode, profile=True)
        except RunError as exc:
            fig.fail("profile", str(exc))
            print(f"bench_device: profiled run: {failed_text(str(exc))}")
    fig.report_failures()
    fig.emit(args.json)
    return fig.exit_status(ok)


if __name__ == "__main__":
    raise SystemExit(main())
