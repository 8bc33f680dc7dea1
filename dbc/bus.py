"""Opening a CAN bus: python-can's interfaces behind one call, with errors a user can act on.

Both command lines (`hil-gateway`, `hil-plant`) take the same options and give the same
messages.

Interface, channel and bitrate come from the command line (-i/-c/-b) and otherwise from
python-can's own configuration: the environment variables CAN_INTERFACE, CAN_CHANNEL,
CAN_BITRATE and the config files (~/can.conf, ~/.canrc, /etc/can.conf, can.ini).
"""

from __future__ import annotations

import argparse
from dataclasses import dataclass
from typing import Any

import can

from dbc.errors import UserError


@dataclass(frozen=True)
class BusConfig:
    """Where the drive is: a python-can interface and channel (bitrate where it applies)."""

    interface: str
    channel: str
    bitrate: int | None = None
    extra: tuple[tuple[str, Any], ...] = ()

    def label(self) -> str:
        """'socketcan:vcan0'."""
        return f"{self.interface}:{self.channel}"


def add_bus_options(p: argparse.ArgumentParser) -> None:
    """-i/--interface, -c/--channel, -b/--bitrate with python-can's conventions."""
    g = p.add_argument_group(
        "CAN bus (python-can; defaults from CAN_INTERFACE/CAN_CHANNEL/CAN_BITRATE or "
        "python-can's config file)")
    g.add_argument("-i", "--interface", help="python-can interface: socketcan, pcan, kvaser, "
                   "vector, slcan, virtual, ...")
    g.add_argument("-c", "--channel", help="channel: vcan0, can0, PCAN_USBBUS1, 0, ...")
    g.add_argument("-b", "--bitrate", type=int, help="bitrate in bit/s (where the interface "
                   "sets it; SocketCAN takes it from `ip link`)")


def bus_config(args: argparse.Namespace) -> BusConfig:
    """Resolve the bus from the options and python-can's configuration."""
    given: dict[str, Any] = {}
    if args.interface:
        given["interface"] = args.interface
    if args.channel:
        given["channel"] = args.channel
    if args.bitrate is not None:
        if args.bitrate <= 0:
            raise UserError(f"bit rate {args.bitrate} is not positive: give it in bit/s, "
                            "e.g. -b 500000")
        given["bitrate"] = args.bitrate
    no_interface = UserError(
        "no CAN interface given and none configured: use -i/--interface and -c/--channel "
        "(e.g. -i socketcan -c vcan0), or set CAN_INTERFACE and CAN_CHANNEL, or write them in "
        "python-can's config file (~/can.conf). To try without hardware, run "
        "`hil-gateway sim`.")
    try:
        cfg = can.util.load_config(config=given)
    except (can.CanInterfaceNotImplementedError, ValueError) as exc:
        if "interface" not in given and "None" in str(exc):
            raise no_interface from exc
        raise UserError(f"unknown CAN interface {given.get('interface')!r} ({exc}): give one "
                        "python-can knows with -i (socketcan, pcan, kvaser, vector, slcan, "
                        "virtual, ...).") from exc
    interface = cfg.get("interface")
    channel = cfg.get("channel")
    if not interface:
        raise no_interface
    if channel is None or channel == "":
        raise UserError(f"no CAN channel given for interface {interface!r} (no channel): use "
                        "-c/--channel (e.g. vcan0, can0, PCAN_USBBUS1) or set CAN_CHANNEL.")
    bitrate = cfg.get("bitrate")
    return BusConfig(str(interface), str(channel), int(bitrate) if bitrate else None)


def open_bus(cfg: BusConfig, receive_own_messages: bool = True) -> can.BusABC:
    """Open the bus; a missing interface, driver or channel becomes a :class:`UserError`.

    ``receive_own_messages`` puts the frames this process sends into its own receive path
    (with the interface's timestamps), so the bus log holds both directions in bus order.
    """
    kwargs: dict[str, Any] = dict(cfg.extra)
    if cfg.bitrate:
        kwargs["bitrate"] = cfg.bitrate
    if receive_own_messages:
        kwargs["receive_own_messages"] = True
    try:
        try:
            return can.Bus(interface=cfg.interface, channel=cfg.channel, **kwargs)
        except (can.CanInterfaceNotImplementedError, can.CanInitializationError, TypeError):
            if not kwargs.pop("receive_own_messages", False):
                raise
            # an interface without receive_own_messages: open it without (the gateway then
            # opens its cycles when it sends SYNC, and logs only what it receives)
            return can.Bus(interface=cfg.interface, channel=cfg.channel, **kwargs)
    except can.CanInterfaceNotImplementedError as exc:
        raise UserError(
            f"CAN interface {cfg.interface!r} is not available: {exc}. Check the name "
            f"(python-can knows: {', '.join(sorted(can.VALID_INTERFACES))}) and that its "
            "driver/library is installed.") from exc
    except (can.CanInitializationError, can.CanOperationError, OSError, ValueError) as exc:
        hint = ""
        if cfg.interface == "socketcan":
            hint = (f" Is {cfg.channel} up? For a virtual CAN interface: sudo modprobe vcan; "
                    f"sudo ip link add dev {cfg.channel} type vcan; sudo ip link set up "
                    f"{cfg.channel} "
                    "(or run inside scripts/vcan-run).")
        raise UserError(f"cannot open CAN channel {cfg.label()}: {exc}.{hint}") from exc
