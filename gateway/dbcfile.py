"""`hil-gateway profile dbc`: the DBC of a run's whole bus for a node, for third-party tools.

Writes the built-in DBC that describes every frame of a run against the emulated drive
(:mod:`dbc.busdbc`: PDOs, NMT, SYNC, EMCY, heartbeats, SDO, value tables) with the COB-IDs
of the drive's node and the gateway's: what `cantools decode`, SavvyCAN, CANdb++ or a
logger's DBC view need to read a run's ``bus.blf`` (or a candump log) without unknown
frames. The vector modes' DBC comes in the run's setpoint frame, (d, q) or (a, b); the
standard modes (CST, CSV) have their own.
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path
from typing import Any

from dbc.busdbc import DEFAULT_GATEWAY_NODE, bus_dbc
from dbc.modes import DriveMode, SetpointFrame
from gateway.errors import UserError


def cmd_profile_dbc(args: argparse.Namespace) -> int:
    """`hil-gateway profile dbc [--node N] [--gateway-node N] [--setpoint-frame ab]
    [--drive-mode MODE] [-o FILE]`."""
    standard = args.drive_mode is not None and args.drive_mode.standard
    if standard and args.setpoint_frame is SetpointFrame.AB:
        raise UserError(f"--setpoint-frame ab with --drive-mode {args.drive_mode}: a standard "
                        "drive takes a target torque or speed, no setpoints in a frame; leave "
                        "--setpoint-frame out, or choose a vector --drive-mode")
    try:
        text = bus_dbc(args.node, args.setpoint_frame, standard, args.gateway_node)
    except ValueError as exc:
        raise UserError(f"--node {args.node}, --gateway-node {args.gateway_node}: {exc}"
                        ) from None
    if args.output is None:
        sys.stdout.write(text)
        return 0
    out = Path(args.output)
    try:
        out.write_text(text, encoding="utf-8")
    except OSError as exc:
        raise UserError(f"cannot write {str(out)!r}: {exc.strerror or exc}; choose a writable "
                        "place with -o") from None
    print(f"wrote {out}: the bus of drive node {args.node} and gateway node "
          f"{args.gateway_node}, " + ("standard modes" if standard else
                                      f"setpoints in ({', '.join(args.setpoint_frame)})"))
    return 0


def add_action(psub: Any) -> None:
    """Register `dbc` on the actions of the `reference`/`profile` subcommand."""
    p = psub.add_parser(
        "dbc", help="write the DBC of a run's whole bus for a node (third-party tools)",
        description="Write the DBC that describes every frame of a run against the emulated "
                    "drive (PDOs, NMT, SYNC, EMCY, heartbeats, SDO, value tables for the "
                    "controlword, statusword and modes of operation), with the COB-IDs of "
                    "the drive's node and the gateway's, for a DBC tool (python -m cantools "
                    "decode FILE < candump.log) to read the run's bus log.")
    p.add_argument("--node", type=int, default=1, metavar="N",
                   help="the drive's node id (default 1)")
    p.add_argument("--gateway-node", type=int, default=DEFAULT_GATEWAY_NODE, metavar="N",
                   help=f"the gateway's own node id, its heartbeat (default "
                        f"{DEFAULT_GATEWAY_NODE})")
    p.add_argument("--setpoint-frame", type=SetpointFrame, choices=list(SetpointFrame),
                   default=SetpointFrame.DQ,
                   help="the frame of the run's setpoints (RPDO2): dq (default) or ab (a "
                        "drive profile with setpoints = \"RPDO2_AB\")")
    p.add_argument("--drive-mode", type=DriveMode, choices=list(DriveMode),
                   help="the run's drive mode: torque or velocity give the standard modes' "
                        "DBC; default: a vector mode's")
    p.add_argument("-o", "--output", metavar="FILE",
                   help="write the DBC here (an existing file is replaced; default: standard "
                        "output)")
    p.set_defaults(func=cmd_profile_dbc)
