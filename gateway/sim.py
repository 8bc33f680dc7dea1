"""`hil-gateway sim`: the emulated drive started beside the gateway, in one process.

With :mod:`gateway.simulate` this is the only module of the gateway that imports
:mod:`plant` (it assembles the emulator); everything else on the gateway side knows the
drive only through the contract (:mod:`dbc`) and the bus.
"""

from __future__ import annotations

import os
import threading
from collections.abc import Callable
from dataclasses import replace
from typing import TYPE_CHECKING, Any

import numpy as np

from dbc.errors import UserError
from dbc.modes import DriveMode
from dbc.motor import MotorParams
from dbc.timing import SIM_HEARTBEAT_TIMEOUT_MS, Timing
from plant.drive import Measurement
from plant.params import DriveParams
from plant.scenario import (
    PlantScenario,
    ScenarioError,
    parse_scenario,
    resolve_scenario,
    scenario_source,
)

if TYPE_CHECKING:
    import can

    from gateway.drive_profile import Mapping
    from gateway.runner import BusTarget


class TruthRecorder:
    """The emulator's state at full resolution, cycle by cycle (ω, |ψr|, T_e as the model
    has them, not through TPDO3's INT16): the device's ``on_sample`` hook."""

    def __init__(self) -> None:
        self._rows: dict[int, tuple[float, float, float]] = {}
        self._lock = threading.Lock()

    def __call__(self, cycle: int, meas: Measurement) -> None:
        with self._lock:
            self._rows[cycle] = (meas.w_m, abs(meas.psi_r_ab), meas.T_e)

    def __len__(self) -> int:
        return len(self._rows)

    def columns(self, cycles: np.ndarray) -> dict[str, np.ndarray] | None:
        """w_m, psi_r_mod, T_e for the given cycle numbers (k of t_k = k·T), or None when a
        cycle is missing (the record then keeps TPDO3's values)."""
        with self._lock:
            rows = [self._rows.get(int(k)) for k in cycles]
        if any(r is None for r in rows):
            return None
        data = np.asarray(rows, dtype=float).reshape(len(rows), 3)
        return {"w_m": data[:, 0], "psi_r_mod": data[:, 1], "T_e": data[:, 2]}


def load_scenario(arg: str | None) -> PlantScenario:
    """``--plant``: a scenario file or a shipped scenario's name; nominal when not given."""
    if arg is None:
        return PlantScenario()
    try:
        return resolve_scenario(arg)
    except ScenarioError as exc:
        raise UserError(str(exc)) from exc


def scenario_text(arg: str) -> tuple[str, str]:
    """``--plant ARG``'s TOML text and source name (a file, or a shipped scenario's name)."""
    try:
        return scenario_source(arg)
    except ScenarioError as exc:
        raise UserError(str(exc)) from exc


def scenario_from_text(text: str, source: str) -> PlantScenario:
    """A plant scenario from its TOML text (``source`` names it in messages)."""
    try:
        return parse_scenario(text, source)
    except ScenarioError as exc:
        raise UserError(str(exc)) from exc


def open_emulator(transport: str, node: int, motor: MotorParams, mode: DriveMode,
                  plant: PlantScenario | None = None, reference_load: Any = None,
                  on_sample: Callable[[int, Measurement], None] | None = None,
                  wrap: Callable[[can.BusABC, can.BusABC], can.BusABC] | None = None,
                  in_sender_thread: bool = True,
                  ) -> tuple[can.BusABC, str, Callable[[], None]]:
    """Start the emulated drive at ``node`` on a new in-process bus; returns the gateway's
    bus, its label ('inprocess:hil-sim-…') and the function that stops and closes it all.

    ``in_sender_thread`` (the in-process channel only): the drive handles each frame in the
    thread that sent it (:mod:`gateway.transport`; a lockstep cycle then runs in the
    gateway's receive thread without a hand-off); otherwise in a receive thread of its own,
    as in real time, where the gateway's SYNC thread must stay free for its schedule.

    ``plant``: how the emulated plant differs from the controller's model (the controller's
    ``motor`` × the scenario); ``reference_load``: the reference profile's load signal, for
    a scenario whose dynamometer follows the profile; ``on_sample``: the device's per-cycle
    hook (e.g. a :class:`TruthRecorder`); ``wrap``: given the gateway's bus and a bus of
    another node on the same medium, the bus the gateway uses (the scenario's bus faults,
    :func:`gateway.faultbus.inject`)."""
    import can  # here: `simulate` reads its scenario (load_scenario) without python-can

    from gateway.transport import InProcessChannel
    from plant.device import DriveDevice

    if transport == "virtual":
        channel = f"hil-sim-{os.getpid()}"
        bus_gw = can.Bus(interface="virtual", channel=channel, receive_own_messages=True)
        bus_dev = can.Bus(interface="virtual", channel=channel)
        if wrap is not None:
            bus_gw = wrap(bus_gw, can.Bus(interface="virtual", channel=channel))
    else:
        medium = InProcessChannel("hil-sim")
        channel = medium.name
        bus_gw = medium.bus(receive_own_messages=True)
        bus_dev = medium.bus(in_sender_thread=in_sender_thread)
        if wrap is not None:
            bus_gw = wrap(bus_gw, medium.bus())
    plant = plant or PlantScenario()
    try:
        device = DriveDevice(
            bus_dev, node_id=node, motor=plant.plant_motor(motor),
            drive_params=plant.drive_params(DriveParams(mode=mode)),
            drive_options=plant.drive_options(
                None if reference_load is None else (lambda t: reference_load.at(t)[0])),
            on_sample=on_sample)
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


def sim_target(mode: DriveMode, plant: PlantScenario | None = None, reference_load: Any = None,
               transport: str = "inprocess", gateway_node: int | None = None,
               plant_label: str = "the plant scenario", mapping: Mapping | None = None
               ) -> BusTarget:
    """`sim`'s target: the emulated drive in ``mode`` started in this process on a new bus
    (``transport``: "inprocess" or python-can's "virtual"; in lockstep, on the in-process
    channel, the drive handles its frames in the sender's thread) for each run, with its built-in
    drive profile (the standard one for a standard ``mode``), whose watch of the gateway's
    heartbeat is :data:`dbc.timing.SIM_HEARTBEAT_TIMEOUT_MS`; ``plant`` and
    ``reference_load`` as for :func:`open_emulator`, the scenario's bus faults injected
    between the gateway (``gateway_node``; None: the profile's) and the drive, a fault on
    a message the drive has not named with ``plant_label`` before the bus opens. The
    emulator's full-resolution truth is recorded for the summary. ``mapping``: its
    process data (:class:`gateway.drive_profile.Mapping`; None: the default)."""
    from gateway.drive_profile import emulator_profile, load_drive_profile
    from gateway.runner import BusTarget

    truth = TruthRecorder()
    drive = load_drive_profile(None, emulator_profile(mode, mapping))
    drive = replace(drive, heartbeat_timeout_ms=max(drive.heartbeat_timeout_ms,
                                                    SIM_HEARTBEAT_TIMEOUT_MS))

    def open_buses(spec: Any, motor: MotorParams, node: int
                   ) -> tuple[can.BusABC, str, Callable[[], None]]:
        wrap = _fault_wrapper(plant, spec.period, drive, node,
                              gateway_node or drive.gateway_node, plant_label)
        return open_emulator(transport, node, motor, spec.drive_mode, plant, reference_load,
                             on_sample=truth, wrap=wrap,
                             in_sender_thread=spec.timing is Timing.LOCKSTEP)

    return BusTarget(drive, open_buses, command="sim", truth=truth)


def _fault_wrapper(plant: PlantScenario | None, period: float, drive: Any, node: int,
                   gateway_node: int, label: str
                   ) -> Callable[[can.BusABC, can.BusABC], can.BusABC] | None:
    """The scenario's bus faults between the gateway and the drive (None: none)."""
    faults = getattr(plant, "bus_faults", ())
    if not faults:
        return None
    from gateway.faultbus import check_faults, inject
    from gateway.process_data import process_data

    pd = process_data(drive, node)
    check_faults(faults, pd, label)

    def wrap(bus: can.BusABC, other: can.BusABC) -> can.BusABC:
        return inject(bus, faults, period, pd, node, gateway_node, other)
    return wrap


def emulator_rate() -> float:
    """The emulated drive's nominal internal rate (PWM/current loop), Hz."""
    return DriveParams().f_pwm


def emulator_limits() -> tuple[float, float]:
    """The default emulated drive's over-current trip (A) and voltage limit (V)."""
    p = DriveParams()
    return p.i_trip, p.u_lim
