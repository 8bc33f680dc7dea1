"""The whole loop over CANopen: lockstep throughput, reaction time, real-time behaviour.

Run: .venv/bin/python bench/bench_loop.py [--quick] [--realtime-seconds 60]
     [-i socketcan -c vcan0]   (against `hil-plant run` in another process)

Without -i/-c, the emulated drive runs in this process on python-can's virtual bus (threads
of one interpreter: the gateway and the drive share the GIL). Figures:

* lockstep: cycles per second of the paper scenario at 1 ms (target ≥ 2000 cycles/s, i.e.
  the 2.5 s scenario in ≤ 1.25 s), median of repeats; ratio to real time;
* reaction: the gateway's time from the last TPDO's arrival to the RPDOs sent, median and
  p99 over all lockstep cycles (target p99 ≤ 200 µs);
* real time at 1 ms for N seconds: missed cycles (target 0), late RPDOs, SYNC jitter
  (|SYNC period − 1 ms|) median and p99, SYNC → TPDO p99.
"""

from __future__ import annotations

import argparse
import statistics
import sys
import tempfile
from pathlib import Path

import can
import numpy as np

from dbc.modes import DriveMode
from dbc.motor import MotorParams
from gateway.drive_profile import load_drive_profile
from gateway.reference import paper_profile
from gateway.report import read_csv
from gateway.runner import RunConfig, run_gateway
from gateway.sim import open_emulator


def _buses(args: argparse.Namespace, transport: str):
    """(gateway bus, cleanup): the external bus, or the emulator on a new in-process bus
    (:func:`gateway.sim.open_emulator`, as `hil-gateway sim` starts it)."""
    if args.interface:
        bus = can.Bus(interface=args.interface, channel=args.channel, receive_own_messages=True)
        return bus, bus.shutdown
    bus, _label, cleanup = open_emulator(transport, 1, MotorParams.paper(), DriveMode.IDEAL)
    return bus, cleanup


def one_run(args: argparse.Namespace, cfg: RunConfig, tag: str, transport: str
            ) -> tuple[dict, dict]:
    bus, cleanup = _buses(args, transport)
    out = Path(tempfile.mkdtemp(prefix=f"bench-{tag}-"))
    try:
        summary = run_gateway(bus, load_drive_profile(None), paper_profile(),
                              MotorParams.paper(), cfg, out,
                              own_echo=(args.interface or "virtual") in ("socketcan", "virtual"))
    finally:
        cleanup()
    return summary, read_csv(out / "signals.csv")


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--quick", action="store_true", help="fewer repeats, 5 s of real time")
    ap.add_argument("--repeats", type=int, default=5)
    ap.add_argument("--realtime-seconds", type=float, default=60.0)
    ap.add_argument("-i", "--interface")
    ap.add_argument("-c", "--channel")
    args = ap.parse_args(argv)
    repeats = 2 if args.quick else args.repeats
    rt_seconds = 5.0 if args.quick else args.realtime_seconds
    where = (f"{args.interface}:{args.channel} (drive in another process)" if args.interface
             else "python-can virtual bus, drive emulator in the same process")
    print(f"Python {sys.version.split()[0]}; {where}")

    transports = ["external"] if args.interface else ["virtual", "inprocess"]
    for transport in transports:
        rates, reactions = [], []
        for r in range(repeats):
            summary, sig = one_run(args, RunConfig(timing="lockstep"), f"ls{r}", transport)
            rates.append(summary["run"]["cycles"] / summary["run"]["wall_time_s"])
            reactions.append(sig["reaction"])
        reaction = np.concatenate(reactions) * 1e6
        rate = statistics.median(rates)
        print(f"[{transport}] lockstep, paper scenario at 1 ms, {repeats} runs: median "
              f"{rate:6.0f} cycles/s ({rate / 1000:.2f}x real time; target >= 2000) [runs: "
              f"{', '.join(f'{x:.0f}' for x in rates)}]")
        print(f"[{transport}] reaction TPDO -> RPDO: median {np.median(reaction):6.1f} us, p99 "
              f"{np.percentile(reaction, 99):6.1f} us (target p99 <= 200 us), max "
              f"{np.max(reaction):.0f} us, over {reaction.size} cycles")

    cfg = RunConfig(timing="realtime", duration=rt_seconds, max_missed=10**9)
    transport = transports[-1]
    summary, sig = one_run(args, cfg, "rt", transport)
    run, t = summary["run"], summary["timing"]
    print(f"[{transport}] real time at 1 ms for {rt_seconds:g} s: {run['cycles']} cycles, missed "
          f"{run['missed_cycles']} (target 0), late RPDO {run['late_rpdo']}")
    print(f"  SYNC jitter median {1e6 * t['sync_jitter']['median']:6.1f} us, p99 "
          f"{1e6 * t['sync_jitter']['p99']:7.1f} us, max {1e6 * t['sync_jitter']['max']:7.1f} us")
    print(f"  SYNC -> TPDO median {1e6 * t['sync_to_tpdo']['median']:6.1f} us, p99 "
          f"{1e6 * t['sync_to_tpdo']['p99']:7.1f} us; reaction p99 "
          f"{1e6 * t['reaction']['p99']:6.1f} us")
    del sig
    return 0


if __name__ == "__main__":
    sys.exit(main())
