"""`hil-gateway sim`: the emulated drive started beside the gateway, in one process.

With :mod:`gateway.simulate` this is the only module of the gateway that imports
:mod:`plant` (it assembles the emulator); everything else on the gateway side knows the
drive only through the contract (:mod:`dbc`) and the bus.
"""

from __future__ import annotations

import os
from collections.abc import Callable
from typing import Any

import can

from dbc.errors import UserError
from dbc.modes import DriveMode
from dbc.motor import MotorParams
from gateway.transport import InProcessChannel
from plant.device import DriveDevice
from plant.params import DriveParams
from plant.scenario import PlantScenario, ScenarioError, resolve_scenario


def load_scenario(arg: str | None) -> PlantScenario:
    """``--plant``: a scenario file or a shipped scenario's name; nominal when not given."""
    if arg is None:
        return PlantScenario()
    try:
        return resolve_scenario(arg)
    except ScenarioError as exc:
        raise UserError(str(exc)) from exc


def open_emulator(transport: str, node: int, motor: MotorParams, mode: DriveMode,
                  plant: PlantScenario | None = None, reference_load: Any = None,
                  ) -> tuple[can.BusABC, str, Callable[[], None]]:
    """Start the emulated drive at ``node`` on a new in-process bus; returns the gateway's
    bus, its label ('inprocess:hil-sim-…') and the function that stops and closes it all.

    ``plant``: how the emulated plant differs from the controller's model (the controller's
    ``motor`` × the scenario); ``reference_load``: the reference profile's load signal, for
    a scenario whose dynamometer follows the profile."""
    if transport == "virtual":
        channel = f"hil-sim-{os.getpid()}"
        bus_gw = can.Bus(interface="virtual", channel=channel, receive_own_messages=True)
        bus_dev = can.Bus(interface="virtual", channel=channel)
    else:
        medium = InProcessChannel("hil-sim")
        channel = medium.name
        bus_gw, bus_dev = medium.bus(receive_own_messages=True), medium.bus()
    plant = plant or PlantScenario()
    try:
        device = DriveDevice(
            bus_dev, node_id=node, motor=plant.plant_motor(motor),
            drive_params=plant.drive_params(DriveParams(mode=mode)),
            drive_options=plant.drive_options(
                None if reference_load is None else (lambda t: reference_load.at(t)[0])))
    except ValueError as exc:
        bus_gw.shutdown()
        bus_dev.shutdown()
        raise UserError(str(exc)) from exc

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
