"""``hil-plant``: run the emulated CiA 402 drive on a CAN bus.

``hil-plant run [-i IF] [-c CH] [-b BITRATE] [--node N] [--motor FILE] [--drive-mode MODE]
[--plant SCENARIO] [--eds FILE]``
opens the bus (python-can conventions; what is not given comes from python-can's config
file or the CAN_INTERFACE / CAN_CHANNEL / CAN_BITRATE environment variables), starts the
device, prints one line when it is ready, runs until SIGINT/SIGTERM, then goes silent
(power stage off, heartbeat stopped, bus shut down) and prints a short account. With
``--eds`` the device is a twin of the drive the EDS/DCF describes (:mod:`plant.twin`); the
ready line is followed by what the twin offers, assumes and keeps as plain storage.
Bad input: a one-paragraph message and exit status 2 (a traceback only with --debug).
"""

from __future__ import annotations

import argparse
import logging
import signal
import sys
import threading
from typing import Any

from dbc.bus import add_bus_options, bus_config, open_bus
from dbc.cia402 import OperationMode
from dbc.errors import UserError
from dbc.modes import DriveMode

EXIT_OK, EXIT_USAGE, EXIT_FAILURE = 0, 2, 1
#: The emulated drive's standard modes beyond :class:`DriveMode` (which the gateway runs):
#: the profile modes, for a master that sends a target and lets the drive ramp to it.
PROFILE_MODES: dict[str, OperationMode] = {"profile-velocity": OperationMode.PROFILE_VELOCITY,
                                           "profile-torque": OperationMode.PROFILE_TORQUE}


def _debug_option(p: argparse.ArgumentParser, default: Any) -> None:
    p.add_argument("--debug", action="store_true", default=default,
                   help="show tracebacks on errors")


def build_parser() -> argparse.ArgumentParser:
    """The argument parser of ``hil-plant``; ``--debug`` goes before or after the command."""
    p = argparse.ArgumentParser(
        prog="hil-plant",
        description="The emulated induction-motor drive as a CANopen CiA 402 device.")
    _debug_option(p, False)
    sub = p.add_subparsers(dest="command", required=True, metavar="COMMAND")
    run = sub.add_parser("run", help="run the emulated drive until SIGINT/SIGTERM",
                         description="Run the emulated drive on a CAN bus until SIGINT/SIGTERM.")
    add_bus_options(run)
    run.add_argument("--node", type=int, default=None,
                     help="CANopen node id 1..127 (default 1; with --eds FILE.dcf, its "
                          "[DeviceComissioning] NodeID)")
    run.add_argument("--eds", metavar="FILE",
                     help="present the drive this EDS or DCF describes (a twin of your drive "
                          "before the hardware arrives): its identity, its PDOs, its CiA 402 "
                          "objects on the emulated motor, its modes as its 0x6502 lists them "
                          "(those the emulator has); other objects as plain storage")
    run.add_argument("--motor", metavar="FILE",
                     help="motor parameters (TOML: J, R_s, R_r, L_s, L_r, M in SI units, "
                          "e.g. gateway/motors/paper.toml); default: the paper's 0.6 kW motor")
    run.add_argument("--plant", metavar="SCENARIO",
                     help="plant scenario (TOML file or shipped name, e.g. rs+10): "
                          "its motor factors multiply the device's motor (--motor or the "
                          "paper's), its sensor and inverter errors and drifts apply, and its "
                          "dynamometer adds the extra torque to RPDO3's T_L (torque = "
                          "\"profile\" needs the gateway's profile: simulate/sim only)")
    run.add_argument("--drive-mode", choices=[*(m.value for m in DriveMode), *PROFILE_MODES],
                     default=DriveMode.CURRENT_LOOP.value, metavar="MODE",
                     help="default drive model and mode (0x2202, 0x6060; the master may change "
                          "them by SDO): ideal or current-loop (current vector mode -1), "
                          "voltage (-2), velocity (CSV 9), torque (CST 10), profile-velocity "
                          "(PV 3), profile-torque (PT 4); default current-loop")
    run.add_argument("--log-level", default="WARNING",
                     choices=("DEBUG", "INFO", "WARNING", "ERROR"),
                     help="logging level on stderr (default WARNING)")
    _debug_option(run, argparse.SUPPRESS)
    return p


def cmd_run(args: argparse.Namespace) -> int:
    """``hil-plant run``."""
    if args.node is not None and not 1 <= args.node <= 127:
        raise UserError(f"node id {args.node} is outside 1..127: pass --node 1..127")
    if args.eds and args.drive_mode not in (DriveMode.IDEAL, DriveMode.CURRENT_LOOP):
        raise UserError(f"--drive-mode {args.drive_mode} with --eds: a twin's modes are its "
                        "file's (0x6060, 0x6502); give --drive-mode ideal or current-loop (the "
                        "model under the drive's own control), or leave it out")
    from dbc.motor import MotorParams, ParamsError
    from plant.params import DriveParams

    try:
        motor = MotorParams.from_toml(args.motor) if args.motor else MotorParams()
    except ParamsError as exc:
        raise UserError(f"bad --motor file: {exc}") from None
    from plant.scenario import PlantScenario, ScenarioError, resolve_scenario

    try:
        plant = resolve_scenario(args.plant) if args.plant else PlantScenario()
        motor = plant.plant_motor(motor)
        profile_mode = PROFILE_MODES.get(args.drive_mode)
        params = plant.drive_params(DriveParams(
            mode=DriveMode.CURRENT_LOOP if profile_mode else DriveMode(args.drive_mode)))
        options = plant.drive_options(None)
    except ScenarioError as exc:
        raise UserError(f"bad --plant scenario: {exc}") from None
    twin = None
    if args.eds:
        from plant.twin import load_twin

        twin = load_twin(args.eds, args.node, params.f_pwm)
    node = twin.node_id if twin is not None else args.node or 1
    cfg = bus_config(args)
    bus = open_bus(cfg, receive_own_messages=False)
    from plant.device import DriveDevice

    stop = threading.Event()
    device = DriveDevice(bus, node, motor, params, drive_options=options, mode=profile_mode,
                         dictionary=None if twin is None else twin.dictionary)
    old = {}
    if threading.current_thread() is threading.main_thread():
        old = {s: signal.signal(s, lambda *_: stop.set()) for s in (signal.SIGINT, signal.SIGTERM)}
    try:
        device.start()
        print(f"hil-plant: node {node} ready on {cfg.label()} (PRE-OPERATIONAL)"
              + ("" if plant.nominal else f", plant {plant.name}"), flush=True)
        if twin is not None:
            print("\n".join(f"  {line}" for line in twin.describe()), flush=True)
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
    except UserError as exc:
        if args.debug:
            raise
        print(f"hil-plant: {exc}", file=sys.stderr)
        return exc.exit_code
    except KeyboardInterrupt:
        return EXIT_OK
    parser.error(f"unknown command {args.command!r}")
    return EXIT_USAGE
