"""`hil-gateway sim`: the emulated drive started beside the gateway, in one process.

With :mod:`gateway.simulate` this is the only module of the gateway that imports
:mod:`plant` (it assembles the emulator); everything else on the gateway side knows the
drive only through the contract (:mod:`dbc`) and the bus.
"""

from __future__ import annotations

import os
from collections.abc import Callable

import can

from dbc.modes import DriveMode
from dbc.motor import MotorParams
from gateway.transport import InProcessChannel
from plant.device import DriveDevice
from plant.params import DriveParams


def open_emulator(transport: str, node: int, motor: MotorParams, mode: DriveMode
                  ) -> tuple[can.BusABC, str, Callable[[], None]]:
    """Start the emulated drive at ``node`` on a new in-process bus; returns the gateway's
    bus, its label ('inprocess:hil-sim-…') and the function that stops and closes it all."""
    if transport == "virtual":
        channel = f"hil-sim-{os.getpid()}"
        bus_gw = can.Bus(interface="virtual", channel=channel, receive_own_messages=True)
        bus_dev = can.Bus(interface="virtual", channel=channel)
    else:
        medium = InProcessChannel("hil-sim")
        channel = medium.name
        bus_gw, bus_dev = medium.bus(receive_own_messages=True), medium.bus()
    device = DriveDevice(bus_dev, node_id=node, motor=motor,
                         drive_params=DriveParams(mode=mode))

    def close() -> None:
        device.stop()
        bus_gw.shutdown()
        bus_dev.shutdown()

    try:
        device.start()
    except BaseException:
        close()
        raise
    return bus_gw, f"{transport}:{channel}", close


def emulator_limits() -> tuple[float, float]:
    """The default emulated drive's over-current trip (A) and voltage limit (V)."""
    p = DriveParams()
    return p.i_trip, p.u_lim
