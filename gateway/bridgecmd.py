"""`hil-gateway bridge`: a fault-injecting bridge between two CAN channels, the gateway's
and the drive's (e.g. vcan0 and vcan1), so that a plant scenario's bus faults act between
two processes without modifying either: ``hil-plant run -c vcan1``, the bridge, and
``hil-gateway run -c vcan0``.
"""

from __future__ import annotations

import argparse
import json
import signal
import threading
import time
from pathlib import Path
from typing import Any

from dbc.bus import add_bus_options, bus_config, open_bus
from dbc.busfaults import FaultKind
from gateway.errors import UserError


def cmd_bridge(args: argparse.Namespace) -> int:
    from gateway.drive_profile import load_drive_profile
    from gateway.faultbus import check_faults, run_bridge
    from gateway.process_data import process_data
    from gateway.sim import load_scenario
    from gateway.units import parse_duration

    plant = load_scenario(args.plant)
    if not plant.bus_faults:
        raise UserError(f"--plant {args.plant} injects no bus faults ([[bus.fault]]): the "
                        "bridge would only forward frames")
    drive = load_drive_profile(args.drive)
    node = args.node or drive.node
    pd = process_data(drive, node)
    check_faults(plant.bus_faults, pd, f"--plant {args.plant}")
    period = parse_duration(args.period, "--period")
    cfg = bus_config(args)
    gateway_side = open_bus(cfg, receive_own_messages=False)
    try:
        drive_cfg = bus_config(argparse.Namespace(interface=cfg.interface, channel=args.to,
                                                  bitrate=args.bitrate))
        drive_side = open_bus(drive_cfg, receive_own_messages=False)
    except BaseException:
        gateway_side.shutdown()
        raise
    try:
        if any(f.kind is FaultKind.ERROR_FRAMES for f in plant.bus_faults):
            _check_error_frames(cfg)
    except BaseException:
        gateway_side.shutdown()
        drive_side.shutdown()
        raise
    stop = threading.Event()
    old = {s: signal.signal(s, lambda *_: stop.set()) for s in (signal.SIGINT, signal.SIGTERM)}
    if args.duration:
        timer = threading.Timer(parse_duration(args.duration, "--duration"), stop.set)
        timer.daemon = True
        timer.start()
    print(f"bridge: {cfg.label()} (gateway) <-> {drive_cfg.label()} (drive), node {node}, "
          f"{len(plant.bus_faults)} fault(s) of {plant.name}; Ctrl-C to stop", flush=True)
    try:
        faulty = run_bridge(gateway_side, drive_side, plant.bus_faults, period, pd, node,
                            args.gateway_node or drive.gateway_node, stop)
    finally:
        for s, h in old.items():
            signal.signal(s, h)
        gateway_side.shutdown()
        drive_side.shutdown()
    account: dict[str, Any] = {"cycles": faulty.k, "bus_faults": faulty.schedule.account()}
    print(json.dumps(account))
    if args.json:
        Path(args.json).write_text(json.dumps(account, indent=2) + "\n")
    return 0


def _check_error_frames(cfg: Any) -> None:
    """The interface delivers an error frame a process sends (SocketCAN's vcan does not:
    the kernel takes it and hands it to no one); a :class:`UserError` saying so."""
    import can

    tx, rx = open_bus(cfg, receive_own_messages=False), open_bus(cfg, receive_own_messages=False)
    try:
        tx.send(can.Message(is_error_frame=True, arbitration_id=0, is_extended_id=False))
        deadline = time.monotonic() + 0.5
        while time.monotonic() < deadline:
            msg = rx.recv(0.1)
            if msg is not None and msg.is_error_frame:
                return
    except can.CanError:
        pass
    finally:
        tx.shutdown()
        rx.shutdown()
    raise UserError(f"{cfg.label()} does not deliver error frames that a process sends (a "
                    "virtual CAN interface carries none; only a controller makes them), so "
                    "the scenario's error-frames fault cannot act between two processes "
                    "here: inject it in one process (hil-gateway sim --plant ...), or over "
                    "a real CAN interface")


def add_parser(sub: Any) -> None:
    p = sub.add_parser(
        "bridge", help="forward frames between two CAN channels, injecting bus faults",
        description="Forward every frame between the gateway's channel (-c) and the drive's "
                    "(--to), injecting the bus faults of a plant scenario ([[bus.fault]]) on "
                    "the way, so that they act between two processes without modifying "
                    "either. Cycles are counted by the gateway's SYNCs. Prints how often "
                    "each fault acted when stopped (Ctrl-C, SIGTERM or --duration).")
    p.add_argument("--plant", required=True, metavar="SCENARIO",
                   help="plant scenario (file or shipped name, e.g. bus-drop) with the faults")
    p.add_argument("--to", required=True, metavar="CHANNEL",
                   help="the drive's channel (same interface as -i), e.g. vcan1")
    p.add_argument("--drive", metavar="PROFILE",
                   help="drive profile whose DBC names the messages (default: the emulator's)")
    p.add_argument("--node", type=int, help="the drive's node id (default: the profile's)")
    p.add_argument("--gateway-node", type=int, help="the gateway's node id (its heartbeat)")
    p.add_argument("--period", default="1ms", help="the loop's period (fault start/duration "
                   "in s become cycles), default 1ms")
    p.add_argument("--duration", metavar="S", help="stop after this long (default: Ctrl-C)")
    p.add_argument("--json", metavar="FILE", help="write the account (faults acted) here")
    add_bus_options(p)
    p.set_defaults(func=cmd_bridge)


__all__ = ["add_parser", "cmd_bridge"]
