"""``hil-plant``: run the emulated CiA 402 drive on a CAN bus.

``hil-plant run [-i IF] [-c CH] [-b BITRATE] [--node N] [--motor FILE] [--drive-mode M]
[--plant SCENARIO]``
opens the bus (python-can conventions; what is not given comes from python-can's config
file or the CAN_INTERFACE / CAN_CHANNEL / CAN_BITRATE environment variables), starts the
device, prints one line when it is ready, runs until SIGINT/SIGTERM, then goes silent
(power stage off, heartbeat stopped, bus shut down) and prints a short account.
Bad input: a one-paragraph message and exit status 2 (a traceback only with --debug).
"""

from __future__ import annotations

import argparse
import logging
import signal
import sys
import threading
from typing import Any

EXIT_OK, EXIT_USAGE, EXIT_FAILURE = 0, 2, 1


class UsageError(Exception):
    """Bad input: the message says what failed and how to fix it."""


def build_parser() -> argparse.ArgumentParser:
    """The argument parser of ``hil-plant``."""
    p = argparse.ArgumentParser(
        prog="hil-plant",
        description="The emulated induction-motor drive as a CANopen CiA 402 device.")
    sub = p.add_subparsers(dest="command", required=True, metavar="COMMAND")
    run = sub.add_parser("run", help="run the emulated drive until SIGINT/SIGTERM",
                         description="Run the emulated drive on a CAN bus until SIGINT/SIGTERM.")
    run.add_argument("-i", "--interface",
                     help="python-can interface (socketcan, virtual, pcan, ...); default: "
                          "python-can config file or CAN_INTERFACE")
    run.add_argument("-c", "--channel",
                     help="channel (vcan0, can0, PCAN_USBBUS1, ...); default: config or "
                          "CAN_CHANNEL")
    run.add_argument("-b", "--bitrate", type=int,
                     help="bit rate in bit/s (ignored by socketcan/virtual); default: config "
                          "or CAN_BITRATE")
    run.add_argument("--node", type=int, default=1, help="CANopen node id 1..127 (default 1)")
    run.add_argument("--motor", metavar="FILE",
                     help="motor parameters (TOML: J, R_s, R_r, L_s, L_r, M in SI units); "
                          "default: the paper's 0.6 kW motor")
    run.add_argument("--plant", metavar="SCENARIO",
                     help="plant scenario (TOML file or shipped name, e.g. rs+10; issue 14): "
                          "its motor factors multiply the device's motor (--motor or the "
                          "paper's), its sensor and inverter errors and drifts apply, and its "
                          "dynamometer adds the extra torque to RPDO3's T_L (torque = "
                          "\"profile\" needs the gateway's profile: simulate/sim only)")
    run.add_argument("--drive-mode", choices=("ideal", "current-loop", "voltage"),
                     default="current-loop",
                     help="default drive model (0x6060/0x2202; the master may change it by "
                          "SDO); default current-loop")
    run.add_argument("--log-level", default="WARNING",
                     choices=("DEBUG", "INFO", "WARNING", "ERROR"),
                     help="logging level on stderr (default WARNING)")
    run.add_argument("--debug", action="store_true", help="show tracebacks on errors")
    return p


def bus_config(args: argparse.Namespace) -> dict[str, Any]:
    """The python-can configuration: the options given, the rest from config file/env."""
    import can

    given: dict[str, Any] = {}
    if args.interface:
        given["interface"] = args.interface
    if args.channel:
        given["channel"] = args.channel
    if args.bitrate is not None:
        if args.bitrate <= 0:
            raise UsageError(f"bit rate {args.bitrate} is not positive: give it in bit/s, "
                             "e.g. -b 500000")
        given["bitrate"] = args.bitrate
    try:
        cfg = can.util.load_config(config=given)
    except can.CanInterfaceNotImplementedError as exc:
        if "interface" not in given and "None" in str(exc):
            raise UsageError(
                "no CAN interface given and none configured: pass -i/--interface and "
                "-c/--channel (e.g. -i socketcan -c vcan0, or -i virtual -c test), or set "
                "CAN_INTERFACE and CAN_CHANNEL, or write a python-can config file "
                "(~/.canrc)") from None
        raise UsageError(
            f"unknown CAN interface {given.get('interface')!r} ({exc}): use one python-can "
            f"knows, e.g. socketcan, virtual, pcan, kvaser, slcan") from None
    if cfg.get("channel") is None:
        raise UsageError(
            f"no channel for interface {cfg['interface']!r}: pass -c/--channel (e.g. -c vcan0) "
            f"or set CAN_CHANNEL")
    return cfg


def _open_bus(cfg: dict[str, Any]) -> Any:
    import can

    try:
        return can.Bus(**cfg)
    except (can.CanError, OSError, ValueError, ImportError) as exc:
        raise UsageError(
            f"cannot open CAN bus {cfg['interface']}:{cfg['channel']} ({exc}): check that the "
            f"interface exists and is up (e.g. `ip link set vcan0 up`), that its driver is "
            f"installed, and the channel name") from None


def cmd_run(args: argparse.Namespace) -> int:
    """``hil-plant run``."""
    if not 1 <= args.node <= 127:
        raise UsageError(f"node id {args.node} is outside 1..127: pass --node 1..127")
    from plant.params import DriveParams, MotorParams, ParamsError

    try:
        motor = MotorParams.from_toml(args.motor) if args.motor else MotorParams()
    except ParamsError as exc:
        raise UsageError(f"bad --motor file: {exc}") from None
    from plant.scenario import PlantScenario, ScenarioError, resolve_scenario

    try:
        plant = resolve_scenario(args.plant) if args.plant else PlantScenario()
        motor = plant.plant_motor(motor)
        params = plant.drive_params(DriveParams(mode=args.drive_mode))
        options = plant.drive_options(None)
    except ScenarioError as exc:
        raise UsageError(f"bad --plant scenario: {exc}") from None
    cfg = bus_config(args)
    bus = _open_bus(cfg)
    from plant.device import DriveDevice

    stop = threading.Event()
    device = DriveDevice(bus, args.node, motor, params, drive_options=options)
    old = {}
    if threading.current_thread() is threading.main_thread():
        old = {s: signal.signal(s, lambda *_: stop.set()) for s in (signal.SIGINT, signal.SIGTERM)}
    try:
        device.start()
        print(f"hil-plant: node {args.node} ready on {cfg['interface']}:{cfg['channel']} "
              f"(PRE-OPERATIONAL)" + ("" if plant.nominal else f", plant {plant.name}"),
              flush=True)
        while not stop.wait(0.2):
            pass
    finally:
        device.stop()
        bus.shutdown()
        for s, h in old.items():
            signal.signal(s, h)
    acc = device.account()
    faults = ", ".join(f"0x{code:04X}" for code, _ in acc["faults"]) or "none"
    print(f"hil-plant: stopped; {acc['cycles']} cycles, {acc['sync_gaps']} SYNC gaps, "
          f"{acc['fault_count']} faults ({faults})", flush=True)
    return EXIT_OK


def main(argv: list[str] | None = None) -> int:
    """Entry point of ``hil-plant``; returns the exit status."""
    parser = build_parser()
    args = parser.parse_args(argv)
    logging.basicConfig(level=getattr(args, "log_level", "WARNING"),
                        format="%(asctime)s %(levelname)s %(name)s: %(message)s")
    try:
        if args.command == "run":
            return cmd_run(args)
    except UsageError as exc:
        if args.debug:
            raise
        print(f"hil-plant: {exc}", file=sys.stderr)
        return EXIT_USAGE
    except KeyboardInterrupt:
        return EXIT_OK
    parser.error(f"unknown command {args.command!r}")
    return EXIT_USAGE
