"""The drive emulator as a CANopen CiA 402 device on any python-can bus.

:class:`DriveDevice` wraps a pure :class:`plant.drive.Drive` in a CiA 301 slave composed
like a python-canopen node of parts, each in its module:

* ``nmt`` (:mod:`plant.nmt`): NMT slave state, boot-up, reset node (dictionary back to its
  defaults, emulated motor at rest, boot-up) and reset communication (0x1000..0x1FFF back
  to defaults, boot-up), heartbeat producer 0x1017 and consumer 0x1016. PDOs only in
  OPERATIONAL, SDO not in STOPPED.
* ``sdo`` (:mod:`plant.sdo`): python-canopen's ``LocalNode``/``SdoServer`` with the
  dictionary and the access rules of :mod:`plant.od`.
* ``pdo`` (:mod:`plant.pdo`): the RPDOs and TPDOs built on entering OPERATIONAL.
* ``emcy`` (:mod:`plant.emcy`): error register 0x1001, 0x1003, 0x603F, the EMCY frame.
* the CiA 402 power state machine (:mod:`plant.cia402`): controlword 0x6040 by SDO (at
  once) or by RPDO (applied with the other RPDO data), statusword 0x6041. The power stage
  (``Drive.enable``) is on only in "Operation enabled".
* in a standard mode the drive's own control (:mod:`plant.servo`; a profile mode's ramp
  and statusword bits, :mod:`plant.profile`), with the targets and actual values in the
  units of the dictionary (:mod:`plant.units`).

The dictionary is ``dbc/drive.eds``, or a twin's (``dictionary``, :mod:`plant.twin`):
another drive's EDS/DCF, whose standard objects the model backs and whose other objects
are plain storage. This module composes the parts and runs the cycle.

* Sampled timing (docs/ARCHITECTURE.md): on each SYNC in OPERATIONAL the drive (1) with
  RPDO apply = on receipt (0x2203 = 1) makes the data received since the last SYNC active,
  (2) advances the simulation by the cycle period 0x1006 — by as many periods as the SYNC
  counter says passed, when it skips values (a master held up skips the SYNCs it could not
  send, and a SYNC the drive did not receive still took its period) —, (3) samples and sends
  TPDO1..3 (those valid, every n-th SYNC for transmission type n), (4) with RPDO apply = at
  the next SYNC (default, CiA 301 synchronous) makes the received data active. The
  simulation advances only on SYNC: lockstep, deterministic. A frame received (eps_0,
  w_0) restarts the (d, q) frame; references received alone act in the running frame.
* Safe reactions, each with an EMCY (0x80+n: code, error register 0x1001, 5 zero bytes), a
  0x1003 entry, 0x603F and the CiA 402 Fault state (power stage off; the model lets the
  currents decay): master heartbeat lost (0x1016; wall clock, or simulated time in
  lockstep: 0x2205 time base, :mod:`plant.nmt`) 0x8130; RPDO deadline
  (0x14xx sub 5 event timer, counted in SYNC periods of simulated time) 0x8250; RPDO of
  wrong length 0x8210; over-current (|i_s_ref| or |i_s| beyond i_trip) 0x2310; over-speed
  (|ω| beyond w_max, 0x2201 sub 9, power stage on or off) 0x8400; a non-finite model state or
  measurement 0x6100 (the model is put back at rest, so the device stays usable); any
  handler exception (a bug) 0x1000. The DC-link voltage limit sets statusword bit 11
  while it clips (no fault). Fault reset (rising edge of controlword bit 7) sends EMCY
  0x0000. Setpoints never outlive a run: leaving Operation enabled, and entering it with
  no RPDO data waiting, zeroes them (active and in the dictionary).

Two threads: the receiver (``bus.recv``; every frame handled under one lock by
:meth:`DriveDevice._handle`, malformed frames ignored) and the timer (heartbeat producer
and consumer, under the same lock). On a bus that delivers in the sender's thread (one
with ``in_sender_thread`` true and ``set_receiver``: `hil-gateway sim`'s in-process
channel, :mod:`gateway.transport`) there is no receive thread: the bus hands each frame to
the device, one at a time and in order, in the thread that sent it, and the device
handles it there under the same lock. A handler exception in any of them is never
silent: it is counted (``internal_errors``), logged with its traceback, and answered with
EMCY 0x1000 and Fault (power stage off); the device keeps running and answering SDO.
:meth:`DriveDevice.stop` joins the threads (and takes the device off such a bus's
delivery); the caller owns the bus.
"""

from __future__ import annotations

import logging
import math
import sys
import threading
import time
from collections import deque
from collections.abc import Callable
from dataclasses import replace
from typing import Any

import can
from canopen.objectdictionary import datatypes

from dbc import scaling
from dbc.cia301 import NMT_ID, SDO_RX_BASE, Emcy, NmtState, sync_periods
from dbc.cia402 import (
    CURRENT_ACTUAL,
    CW_HALT_BIT,
    DC_LINK_VOLTAGE,
    MAX_TORQUE,
    POSITION_ACTUAL,
    PROFILE_ACCELERATION,
    PROFILE_DECELERATION,
    SUPPORTED_MODES,
    TORQUE_ACTUAL,
    TORQUE_DEMAND,
    TORQUE_SLOPE,
    VELOCITY_ACTUAL,
    VELOCITY_DEMAND,
    VELOCITY_THRESHOLD,
    VELOCITY_THRESHOLD_TIME,
    VELOCITY_WINDOW,
    VELOCITY_WINDOW_TIME,
    OperationMode,
)
from dbc.edsfile import configured
from dbc.modes import DriveMode
from dbc.motor import MotorParams
from plant import od as odm
from plant.cia402 import PowerStateMachine, State
from plant.drive import Drive, Measurement, MotorState, Setpoints
from plant.emcy import EmcyProducer
from plant.nmt import NmtSlave
from plant.params import DriveParams
from plant.pdo import SETPOINT_SIGNALS, PdoRuntime, Rpdo
from plant.profile import DEFAULTS, ProfileRamp, ProfileSettings
from plant.rpdo import setpoints_from_rpdos
from plant.sdo import SdoHooks, SdoServer, Sender
from plant.servo import Servo, servo_for
from plant.timing import sync_cycle
from plant.units import EMULATOR, TARGETS, DriveUnits, Quantity, units_from

log = logging.getLogger(__name__)

FAULT_LOG = 100  #: faults kept in the account
#: Between runs (:meth:`DriveDevice._idle`): how often the idle motor advances, s; how hard
#: the test bench brakes it to rest, rad/s² (from 100 rad/s in 0.2 s); the longest step,
#: internal steps (a stalled thread does not make one huge step); the flux below which
#: the motor is at rest, Wb.
IDLE_STEP_S = 0.02
IDLE_BRAKE = 500.0
IDLE_MAX_STEPS = 1000
IDLE_FLUX = 1e-6


class DriveDevice:
    """The emulated drive as a CANopen CiA 402 device (see the module docstring).

    ``DriveDevice(bus, node_id=1, motor=None, drive_params=None)``: ``motor`` and
    ``drive_params`` (default: the paper's motor, the default current-loop inverter) are the
    device's defaults, to which reset node returns; ``drive_params.mode`` sets the defaults
    of 0x6060 (−2 for "voltage", else −1) and 0x2202 (0 for "ideal", else 1); ``mode``, if
    given, is the default of 0x6060 instead (a standard mode, e.g. profile velocity).
    ``drive_options``: keyword arguments of every :class:`plant.drive.Drive` the device
    builds (the dynamometer ``load`` and ``motor_drift`` of a plant scenario).
    ``on_sample(cycle, measurement)``, optional: called in the receive thread after each
    cycle's model step with the cycle number (periods lived since the account was cleared:
    SYNCs, and the periods a skipping SYNC counter told) and the full-resolution
    :class:`Measurement`
    (for diagnostics in the same process, e.g. `hil-gateway sim`'s truth record).

    The parts ``nmt``, ``sdo``, ``pdo`` and ``emcy`` are for diagnostics: every frame and
    timer goes through the device, which holds its lock while a part runs.
    """

    def __init__(self, bus: can.BusABC, node_id: int = 1, motor: MotorParams | None = None,
                 drive_params: DriveParams | None = None,
                 drive_options: dict[str, Any] | None = None,
                 on_sample: Callable[[int, Measurement], None] | None = None,
                 mode: OperationMode | None = None,
                 dictionary: odm.Dictionary | None = None) -> None:
        if isinstance(node_id, bool) or not isinstance(node_id, int) or not 1 <= node_id <= 127:
            raise ValueError(f"node id {node_id!r} is outside 1..127")
        self.bus = bus
        #: the bus hands frames to the device in the sender's thread (module docstring)
        self._in_sender_thread = (getattr(bus, "in_sender_thread", False) is True
                                  and callable(getattr(bus, "set_receiver", None)))
        self.node_id = node_id
        self.on_sample = on_sample
        self._motor0 = motor if motor is not None else MotorParams()
        self._params0 = drive_params if drive_params is not None else DriveParams()
        self._mode0 = (OperationMode(mode) if mode is not None
                       else OperationMode(self._params0.mode.mode_of_operation))
        self._units = EMULATOR
        self._drive_options = dict(drive_options or {})
        if dictionary is None:
            dictionary = odm.Dictionary.emulator(node_id)
        self._store = odm.ObjectStore(node_id, self._overrides(dictionary), dictionary,
                                      f_pwm=self._params0.f_pwm)
        #: how :meth:`_put` writes each object it has written (its dictionary's type)
        self._put_kinds: dict[odm.Key, Any] = {}
        self._values = self._store.values
        self._send = Sender(bus)
        self._lock = threading.RLock()
        self._stop_event = threading.Event()
        self._wake = threading.Event()
        self._threads: list[threading.Thread] = []
        self.nmt = NmtSlave(node_id, self._values, self._send.send_message, self._wake,
                            start=self._enter_operational, pdos_off=self._pdos_off,
                            reset_node=self._reset_node,
                            reset_communication=self._reset_communication_state,
                            heartbeat_lost=lambda: self._fault(Emcy.HEARTBEAT),
                            own=dictionary.own)
        history = max((sub for i, sub in self._store.vars if i == 0x1003), default=0)
        self.emcy = EmcyProducer(self._values, self._send.send_message, lambda: self.nmt.state,
                                 history)
        self.pdo = PdoRuntime(self._store, bus)
        self.sdo = SdoServer(self._store, self._send, SdoHooks(
            nmt_state=lambda: self.nmt.state,
            statusword=lambda: self._statusword(self._limit),
            counters=lambda: (self._cycles_total, self._sync_gaps, self._fault_count),
            parameters=self._parameters_written, controlword=self._controlword,
            heartbeats=self.nmt.configure_heartbeats, sync_cob_id=self.pdo.set_sync_id,
            clear_error_history=self.emcy.clear_history, clear_account=self._clear_account,
            signal=self._signal_written))
        self._sm = PowerStateMachine()
        self._k = self._store.signals  # the emulator's own signal objects (none in a twin)
        self._factor = {n: scaling(n)[0] for n in self._k}
        self._setpoint_keys = tuple(k for n, k in self._k.items() if n in SETPOINT_SIGNALS)
        self._logged: set[tuple[str, type]] = set()  # internal errors logged with traceback
        # account (cumulative since construction)
        #: how hard the test bench brakes the idle motor to rest between runs, rad/s² (0:
        #: not at all; :meth:`_idle`)
        self.idle_brake = IDLE_BRAKE
        self._idle_at: float | None = None
        self._cycles_total = 0
        self._periods_total = 0  # the periods the model lived on SYNC (counter gaps too)
        self._sync_gaps = 0
        self._faults: deque[tuple[int, float]] = deque(maxlen=FAULT_LOG)
        self._fault_count = 0
        self._internal_errors = 0
        self._reset_application()
        self._reset_communication_state()

    # ---- public API -------------------------------------------------------------------------
    def start(self) -> None:
        """Boot: boot-up message, PRE-OPERATIONAL, heartbeat producer, receiver running."""
        with self._lock:
            if self._threads:
                raise RuntimeError("DriveDevice already started")
            self._stop_event.clear()
            self._sm.boot()
            self.nmt.boot()
        loops = [(self._timer_loop, "timer")]
        if self._in_sender_thread:
            self.bus.set_receiver(self._receive)  # type: ignore[attr-defined]
        else:
            loops.insert(0, (self._rx_loop, "rx"))
        for target, name in loops:
            t = threading.Thread(target=target, name=f"hil-plant-{name}-{self.node_id}",
                                 daemon=True)
            self._threads.append(t)
            t.start()

    def stop(self) -> None:
        """Power stage off, heartbeat stopped, silent on the bus (the bus stays open)."""
        self._stop_event.set()
        self._wake.set()
        if self._in_sender_thread:
            self.bus.set_receiver(None)  # type: ignore[attr-defined]
        for t in self._threads:
            t.join(timeout=2.0)
        self._threads.clear()
        with self._lock:
            self._drive.enable(False)
            self.nmt.state = NmtState.STOPPED
            self.pdo.clear()

    def __enter__(self) -> DriveDevice:
        self.start()
        return self

    def __exit__(self, *exc: object) -> None:
        self.stop()

    def account(self) -> dict[str, Any]:
        """cycles, sync_gaps, faults [(EMCY code, time.time()), the last 100], fault_count,
        state (CiA 402), nmt, internal_errors (handler exceptions, each also an EMCY 0x1000
        and a Fault: always 0 unless a bug)."""
        with self._lock:
            return {
                "cycles": self._cycles_total,
                "sync_gaps": self._sync_gaps,
                "faults": list(self._faults),
                "fault_count": self._fault_count,
                "state": self._sm.state.name,
                "nmt": self.nmt.state,
                "internal_errors": self._internal_errors,
            }

    @property
    def nmt_state(self) -> str:
        """NMT state name as python-canopen spells it."""
        return self.nmt.state

    @property
    def cia402_state(self) -> State:
        """The CiA 402 state."""
        return self._sm.state

    @property
    def drive(self) -> Drive:
        """The wrapped model (read its ``state``/``setpoints`` for diagnostics only)."""
        return self._drive

    # ---- defaults and resets ----------------------------------------------------------------
    def _overrides(self, dictionary: odm.Dictionary) -> dict[odm.Key, Any]:
        """The defaults the device sets: the emulator's parameters (its own dictionary), or
        a twin's truths: 0x6502 the modes it offers, 0x6061 its default mode, 0x6079 the
        DC link voltage."""
        p = self._params0
        if not dictionary.own:
            od, out = dictionary.od, {}
            if SUPPORTED_MODES in od:
                out[(SUPPORTED_MODES, 0)] = sum(m.supported_bit for m in dictionary.modes)
            if 0x6060 in od and 0x6061 in od:
                out[(0x6061, 0)] = configured(od[0x6060]) or 0
            if DC_LINK_VOLTAGE in od:
                out[(DC_LINK_VOLTAGE, 0)] = min(round(p.u_dc * 1000), 0xFFFFFFFF)
            return out
        m = self._motor0
        o: dict[odm.Key, Any] = {(odm.MOTOR, k): float(getattr(m, n))
                                 for k, n in enumerate(odm.MOTOR_SUBS, 1)}
        o.update({
            (odm.DRIVE, 1): float(p.u_dc), (odm.DRIVE, 2): float(p.i_trip),
            (odm.DRIVE, 3): float(p.current_loop_bw),
            (odm.DRIVE, 4): float(complex(p.i_offset_ab).real),
            (odm.DRIVE, 5): float(complex(p.i_offset_ab).imag),
            (odm.DRIVE, 6): float(p.i_gain_error), (odm.DRIVE, 7): float(p.i_noise_rms),
            (odm.DRIVE, 8): round(p.f_pwm), (odm.DRIVE, 9): float(p.w_max),
            (odm.SEED, 0): p.seed & 0xFFFFFFFF,
            (0x6060, 0): int(self._mode0),
            (0x6061, 0): int(self._mode0),
            (odm.MODEL, 0): p.mode.emulator_model,
            (0x6079, 0): min(round(p.u_dc * 1000), 0xFFFFFFFF),
        })
        return o

    def _drive_params(self) -> tuple[MotorParams, DriveParams]:
        v = self._values
        if not self._store.own:  # a twin: the device's motor and inverter, at its period
            model = self._params0.mode
            return self._motor0, replace(
                self._params0, mode=model if model in (DriveMode.IDEAL, DriveMode.CURRENT_LOOP)
                else DriveMode.CURRENT_LOOP, f_pwm=self._store.internal_rate)
        motor = MotorParams.from_mapping(
            {n: v[(odm.MOTOR, k)] for k, n in enumerate(odm.MOTOR_SUBS, 1)}, "0x2200")
        mode = DriveMode.VOLTAGE if v[(0x6060, 0)] == DriveMode.VOLTAGE.mode_of_operation else (
            DriveMode.IDEAL if v[(odm.MODEL, 0)] == DriveMode.IDEAL.emulator_model
            else DriveMode.CURRENT_LOOP)
        f_pwm = v[(odm.DRIVE, 8)]
        params = replace(
            self._params0, mode=mode, u_dc=v[(odm.DRIVE, 1)], i_trip=v[(odm.DRIVE, 2)],
            current_loop_bw=v[(odm.DRIVE, 3)],
            i_offset_ab=complex(v[(odm.DRIVE, 4)], v[(odm.DRIVE, 5)]),
            i_gain_error=v[(odm.DRIVE, 6)], i_noise_rms=v[(odm.DRIVE, 7)],
            f_pwm=self._params0.f_pwm if f_pwm == round(self._params0.f_pwm) else float(f_pwm),
            w_max=v[(odm.DRIVE, 9)],
            seed=v[(odm.SEED, 0)])
        return motor, params

    def _operation_mode(self) -> OperationMode | None:
        """The mode 0x6060 selects, None for a value that is no mode the device offers."""
        value = self._values.get((0x6060, 0))
        return OperationMode(value) if value in self._store.modes else None

    def _units_now(self) -> DriveUnits:
        """The units of the standard objects: the emulator's, or a twin's from its present
        values (:mod:`plant.units`)."""
        return EMULATOR if self._store.own else units_from(self._store.lookup)[0]

    def _make_servo(self, motor: MotorParams, params: DriveParams) -> None:
        """The drive's own control in a standard mode (0x6060 3, 4, 8, 9 or 10), with the
        ramp of a profile mode; none in a vector mode."""
        v = self._values
        mode = self._operation_mode()
        self._servo: Servo | None = None
        self._profile: ProfileRamp | None = None
        if mode is None or not mode.standard:
            return
        T = self._store.period
        self._servo = servo_for(motor, params.i_trip, T, v.get((MAX_TORQUE, 0)),
                                self._drive.state.w_m, self._units.torque)
        if mode.profiled:
            self._profile = ProfileRamp(mode, T, self._servo.params.T_max)

    def _reset_application(self) -> None:
        """Power-on / reset node: defaults, motor at rest, no setpoints, no faults."""
        self._store.reset()
        self._units = self._units_now()
        motor, params = self._drive_params()
        self._drive = Drive(motor, params, **self._drive_options)
        self._make_servo(motor, params)
        self._params_dirty = False
        self._T_L = 0.0
        self._sp_fresh = self._cw_fresh = self._tl_fresh = False
        self._frame_fresh = False  # eps_0 or w_0 received since the last latch
        self._limit = False
        self._off_since: float | None = None  # monotonic time the power stage went off
        self.emcy.reset()
        self._sm = PowerStateMachine()

    def _reset_communication_state(self) -> None:
        self._store.reset(communication_only=True)
        self.emcy.restore()
        self.pdo.clear()
        self.nmt.configure_heartbeats()

    def _reset_node(self) -> None:
        self._reset_application()
        self._reset_communication_state()
        self._sm.boot()

    # ---- NMT --------------------------------------------------------------------------------
    def _enter_operational(self) -> None:
        """Rebuild the model if parameters changed, then the PDO runtime."""
        if self._params_dirty:
            self._rebuild_drive()
        self.pdo.build()

    def _pdos_off(self) -> None:
        self.pdo.clear()

    def _rebuild_drive(self) -> None:
        try:
            motor, params = self._drive_params()
            old = self._drive
            new = Drive(motor, params, state=old.state, **self._drive_options)
        except ValueError as exc:  # guarded by the SDO checks; keep the old model
            log.error("node %d: parameters rejected, model unchanged: %s", self.node_id, exc)
            return
        new.set_setpoints(old.setpoints)
        new.enable(self._sm.power)
        self._drive = new
        self._units = self._units_now()
        self._make_servo(motor, params)
        self._params_dirty = False

    # ---- SDO write effects ------------------------------------------------------------------
    def _parameters_written(self) -> None:
        self._params_dirty = True

    def _clear_account(self) -> None:
        self._cycles_total = self._sync_gaps = self._fault_count = 0
        self._periods_total = 0
        self._faults.clear()

    def _signal_written(self, index: int) -> None:
        """An RPDO signal object written by SDO: active at the next latch."""
        if index == self._k["T_L"][0]:
            self._tl_fresh = True
        else:
            self._sp_fresh = self._frame_fresh = True

    # ---- CiA 402 ----------------------------------------------------------------------------
    def _controlword(self, cw: int) -> None:
        before = self._sm.state
        after = self._sm.command(cw)
        if before is State.FAULT and after is not State.FAULT:
            self.emcy.clear()
        if after is not before:
            log.debug("node %d: %s -> %s", self.node_id, before.name, after.name)
            was_on = self._drive.enabled
            if self._sm.power and not was_on and self._off_since is not None:
                self._rest(time.monotonic() - self._off_since)
            self._drive.enable(self._sm.power)
            if was_on and not self._sm.power:
                self._off_since = time.monotonic()
                self._clear_setpoints()  # the run's setpoints end with it
            elif self._sm.power and not self._sp_fresh:
                self._clear_setpoints()  # a run starts from zero (data pending: latched next)

    def _rest(self, idle: float) -> None:
        """The model advances only on SYNC, but the real motor does not wait: after ``idle``
        seconds with the power stage off, the stator currents are gone and the rotor flux has
        decayed by e^{−α·idle}; the speed is kept (model (1) has no friction). The model
        restarts from there at t = 0, like the gateway's new run."""
        s, m = self._drive.state, self._drive.motor
        decay = math.exp(-m.R_r / m.L_r * max(idle, 0.0))
        self._drive.reset(MotorState(s.w_m, s.psi_r_ab * decay, 0j))

    def _clear_setpoints(self) -> None:
        """Zero setpoints, active and in the dictionary's setpoint objects (eps_0, w_0 and the
        current/voltage references of either frame): a run never starts with the setpoints
        of the one before; the frame comes with the next RPDO. T_L (the emulated load, not
        a setpoint of the drive) is kept."""
        for key in self._setpoint_keys:
            self._values[key] = 0
        self._drive.set_setpoints(Setpoints())

    def _fault(self, code: Emcy) -> None:
        """Safe reaction: EMCY, error register, 0x1003, 0x603F, Fault, power stage off."""
        log.warning("node %d: fault, EMCY 0x%04X", self.node_id, code)
        self._faults.append((code, time.time()))
        self._fault_count += 1
        self._sm.fault()
        if self._drive.enabled:
            self._off_since = time.monotonic()
        self._drive.enable(False)
        self._clear_setpoints()  # re-enabling needs fresh setpoints
        self._sp_fresh = self._frame_fresh = False
        self.emcy.error(code)

    def _internal_error(self, where: str) -> None:
        """A handler raised (a bug): counted, logged (with the traceback the first time for
        this place and exception type), EMCY 0x1000 and Fault (power stage off); a model
        left non-finite is put back at rest. Called from an ``except`` block."""
        self._internal_errors += 1
        exc = sys.exc_info()[1]
        kind = (where.split(" ", 1)[0], type(exc))
        if kind in self._logged:
            log.error("node %d: %s failed again: %r", self.node_id, where, exc)
        else:
            self._logged.add(kind)
            log.exception("node %d: %s failed", self.node_id, where)
        try:
            if not self._model_finite():
                self._drive.reset(MotorState())
            self._fault(Emcy.INTERNAL)
        except Exception:  # the bus refuses the EMCY, …: the power stage is off regardless
            self._sm.fault()
            self._drive.enable(False)
            log.exception("node %d: reaction to an internal error failed", self.node_id)

    def _model_finite(self) -> bool:
        s = self._drive.state
        return (math.isfinite(s.w_m) and math.isfinite(s.psi_r_ab.real)
                and math.isfinite(s.psi_r_ab.imag) and math.isfinite(s.i_s_ab.real)
                and math.isfinite(s.i_s_ab.imag))

    # ---- PDOs and the cycle -----------------------------------------------------------------
    def _on_rpdo(self, r: Rpdo, data: bytes) -> None:
        if not self.pdo.receive(r, data, self._cycles):
            self._fault(Emcy.PDO_LENGTH)
            return
        self._cw_fresh |= r.controlword
        self._sp_fresh |= r.setpoints
        self._frame_fresh |= r.frame
        self._tl_fresh |= r.load

    def _latch(self) -> None:
        """Make the data received since the last latch active (controlword, setpoints, T_L);
        in a standard cyclic mode the drive's own control turns the target into setpoints."""
        v, k, f = self._values, self._k, self._factor
        if self._cw_fresh:
            self._cw_fresh = False
            self._controlword(v[(0x6040, 0)])
        if self._tl_fresh:
            self._tl_fresh = False
            self._T_L = v[k["T_L"]] * f["T_L"]
        if self._sp_fresh:
            self._sp_fresh = False
            rpdo1 = {"eps_0": v[k["eps_0"]] * f["eps_0"], "w_0": v[k["w_0"]] * f["w_0"]}
            rpdo2 = {n: v[k[n]] * f[n] for n in self.pdo.frame_names}
            sp = setpoints_from_rpdos(rpdo1, rpdo2)
            if self._frame_fresh:
                self._drive.set_setpoints(sp)
            else:  # references alone (their RPDO came a SYNC after the frame's): frame runs on
                self._drive.set_references(sp)
            self._frame_fresh = False
            if (self._sm.power and self._drive.params.mode is not DriveMode.VOLTAGE
                    and abs(sp.i_s_ref) > self._drive.params.i_trip):
                self._fault(Emcy.OVERCURRENT)
        if self._servo is not None:
            self._servo_step()

    def _servo_step(self) -> None:
        """A standard mode: the target of 0x607A, 0x60FF or 0x6071 (in a profile mode
        through its ramp, :mod:`plant.profile`) → (d, q) setpoints for this period
        (:mod:`plant.servo`); with the power stage off the drive's control starts over."""
        servo, profile = self._servo, self._profile
        assert servo is not None
        if not self._sm.power:
            servo.reset()
            if profile is not None:
                profile.stop()
                self._put(TORQUE_DEMAND if profile.mode.torque else VELOCITY_DEMAND, 0.0)
            return
        mode = self._operation_mode()
        if mode is None:
            return
        target = self._target(mode)
        if profile is not None:
            target = profile.step(target, self._settings(), self._halt, servo.w_enc)
            index, quantity = ((TORQUE_DEMAND, Quantity.TORQUE) if mode.torque
                               else (VELOCITY_DEMAND, Quantity.VELOCITY))
            self._put(index, target / self._units.of(quantity))
        self._drive.set_setpoints(servo.follow(mode, target))

    def _target(self, mode: OperationMode) -> float:
        """The target of a standard mode in SI (N·m, rad, rad/s)."""
        index, quantity = TARGETS[mode]
        return self._values.get((index, 0), 0) * self._units.of(quantity)

    @property
    def _halt(self) -> bool:
        """Controlword bit 8 (halt) of the last controlword applied."""
        return bool(self._sm.controlword & CW_HALT_BIT)

    def _settings(self) -> ProfileSettings:
        """The profile parameters now, in SI (an object the dictionary lacks: the
        emulator's default)."""
        u, d = self._units, DEFAULTS

        def si(index: int, unit: float, default: float) -> float:
            raw = self._values.get((index, 0))
            return default if raw is None else raw * unit

        return ProfileSettings(
            acceleration=si(PROFILE_ACCELERATION, u.acceleration, d.acceleration),
            deceleration=si(PROFILE_DECELERATION, u.acceleration, d.deceleration),
            torque_slope=si(TORQUE_SLOPE, u.torque, d.torque_slope),
            window=si(VELOCITY_WINDOW, u.velocity, d.window),
            window_time=si(VELOCITY_WINDOW_TIME, 1e-3, d.window_time),
            threshold=si(VELOCITY_THRESHOLD, u.velocity, d.threshold),
            threshold_time=si(VELOCITY_THRESHOLD_TIME, 1e-3, d.threshold_time))

    def _statusword(self, limit: bool) -> int:
        """0x6041: the power state's bits and, in a profile mode, its own (bits 10, 12)."""
        bits = self._profile.bits if self._profile is not None else 0
        return self._sm.statusword(limit) | bits

    def _put(self, index: int, value: float, wrap: bool = False) -> None:
        """A standard object's value (sub 0), rounded, saturated at (``wrap``: modulo) the
        range of its integer type (a twin's REAL type: as it is); nothing if the dictionary
        lacks it."""
        key = (index, 0)
        kind = self._put_kinds.get(key)
        if kind is None:
            kind = self._put_kinds[key] = _put_kind(self._store.vars.get(key))
        if kind is _NOT_PUT:
            return
        if kind is _FLOAT:
            self._values[key] = float(value)
            return
        bits, signed, lo, hi = kind
        x = round(value)
        if wrap:
            x %= 1 << bits
            x -= (1 << bits) if signed and x >> (bits - 1) else 0
        else:
            x = max(lo, min(hi, x))
        self._values[key] = x

    def _on_sync(self, data: bytes) -> None:
        n = len(data)
        if n > 1:
            return  # not a SYNC (CiA 301: 0 or 1 data bytes)
        counter = data[0] if n else 0
        periods = 1
        if n:
            pdo = self.pdo
            last = pdo.last_counter
            if last is not None:
                ov = self._values[(0x1019, 0)]
                if ov >= 2:
                    gap = counter != (1 if last >= ov else last + 1)
                    if gap and 1 <= counter <= ov and 1 <= last <= ov:
                        periods = sync_periods(last, counter, ov)
                else:  # overflow unknown here: accept a wrap to 1 (CiA 301) or to 0
                    gap = counter not in ((last + 1) & 0xFF, 1)
                if gap:
                    self._sync_gaps += 1
            pdo.last_counter = counter
        self._cycle(counter, periods)

    @property
    def _cycles(self) -> int:
        return self._cycles_total

    def _cycle(self, counter: int, periods: int = 1) -> None:
        """One SYNC: (latch) → advance ``periods``·T → sample → TPDOs → (latch)."""
        m = self._cycles_total + 1
        for _ in self.pdo.expired(m):
            self._fault(Emcy.RPDO_TIMEOUT)
        sync_cycle(lambda: self._advance_and_transmit(m, counter, periods), self._latch,
                   self.pdo.apply)

    def _advance_and_transmit(self, m: int, counter: int, periods: int = 1) -> Measurement:
        """Advance the model by ``periods``·T (the time the SYNC counter says passed since
        the last SYNC; the setpoints held), sample, send the TPDOs of cycle ``m``. The
        sample is the last period's (its average voltage too), as on time."""
        drive = self._drive
        was_on = drive.enabled
        meas = drive.advance_held(periods, self.pdo.period, self._T_L)
        self._cycles_total = m
        self._periods_total += periods
        if not (self._model_finite() and _finite(meas)):
            # the model failed numerically: Fault, and back at rest so the device stays usable
            drive.reset(MotorState())
            self._fault(Emcy.MODEL_NON_FINITE)
            meas = _at_rest(drive.params.u_dc)
        elif was_on and drive.tripped:
            self._fault(Emcy.OVERCURRENT)
        elif abs(meas.w_m) > drive.params.w_max and (was_on or self._sm.state
                                                      is not State.FAULT):
            # supervised with the power stage off too (a dynamometer or a load can drive
            # the motor): once, as a real drive's speed monitor reports it
            self._fault(Emcy.OVERSPEED)
        if self.on_sample is not None:  # what the TPDOs carry: the at-rest sample after a
            self.on_sample(self._periods_total, meas)  # non-finite model, not its NaNs
        self._limit = meas.limit_active
        u = self._units  # the standard actual values, in the units of the dictionary
        self._put(VELOCITY_ACTUAL, meas.w_m / u.velocity)
        self._put(TORQUE_ACTUAL, meas.T_e / u.torque)
        self._put(CURRENT_ACTUAL, abs(meas.i_s_ab) / u.current)
        if self._servo is not None:  # the encoder counts in the standard modes
            self._servo.sample(meas.w_m)
            self._put(POSITION_ACTUAL, self._servo.theta / u.position, wrap=True)
            profile = self._profile
            if profile is not None:
                profile.supervise(meas.w_m, self._target(profile.mode), self._settings(),
                                  self._halt)
        self.pdo.sample(meas, self._statusword(meas.limit_active), counter)
        self.pdo.transmit(m)
        return meas

    # ---- threads ----------------------------------------------------------------------------
    def _dispatch(self, can_id: int, data: bytes) -> None:
        nmt = self.nmt
        state = nmt.state
        if can_id == NMT_ID:
            nmt.on_command(data)
        elif state is NmtState.OPERATIONAL and can_id == self.pdo.sync_id:
            if len(data) <= 1:
                nmt.on_sync(self.pdo.period)
            self._on_sync(data)
        elif state is NmtState.OPERATIONAL and can_id in self.pdo.rpdos:
            self._on_rpdo(self.pdo.rpdos[can_id], data)
        elif can_id == SDO_RX_BASE + self.node_id:
            if state is not NmtState.STOPPED and len(data) == 8:
                self.sdo.on_request(can_id, data)
        elif (nmt.hb_consumer is not None and can_id == nmt.hb_consumer[0]
              and len(data) >= 1):
            nmt.on_heartbeat()

    def _rx_loop(self) -> None:
        recv, stop = self.bus.recv, self._stop_event
        while not stop.is_set():
            try:
                msg = recv(0.02)
            except Exception as exc:  # bus closed under us or a driver error
                if stop.is_set():
                    break
                log.error("node %d: receive failed: %s", self.node_id, exc)
                stop.wait(0.1)
                continue
            if msg is None or msg.is_extended_id or msg.is_remote_frame or msg.is_error_frame:
                continue
            with self._lock:
                if stop.is_set():
                    break
                self._handle(msg.arbitration_id, bytes(msg.data))

    def _receive(self, msg: can.Message) -> None:
        """One frame from a bus that delivers in the sender's thread: what the receive
        thread does with each frame it receives."""
        if msg.is_extended_id or msg.is_remote_frame or msg.is_error_frame:
            return
        with self._lock:
            if self._stop_event.is_set():
                return
            self._handle(msg.arbitration_id, bytes(msg.data))

    def _handle(self, can_id: int, data: bytes) -> None:
        """One received frame (the caller holds the lock); a handler exception is an
        internal error (EMCY 0x1000, Fault), never silent."""
        try:
            self._dispatch(can_id, data)
        except Exception:
            self._internal_error(f"frame 0x{can_id:03X} {data.hex()}")

    def _timer_loop(self) -> None:
        stop = self._stop_event
        while not stop.is_set():
            wait = 0.5
            with self._lock:
                if stop.is_set():
                    break
                now = time.monotonic()
                try:
                    wait = self._timers(now)
                except Exception:
                    self._internal_error("timer")
            self._wake.wait(max(wait, 0.0005))
            self._wake.clear()

    def _timers(self, now: float) -> float:
        """Heartbeat producer and consumer, and the idle motor; returns the time to the
        next deadline, s."""
        return min(self.nmt.timers(now), self._idle(now))

    def _idle(self, now: float) -> float:
        """Between runs the motor lives in real time: while the device is not OPERATIONAL
        (no SYNC drives the model) and its power stage is off, the model advances by the
        wall time that passed (the flux decays, the rotor coasts) and the test bench's load
        machine brakes the rotor to rest at ``idle_brake`` rad/s², so a second run finds it
        at rest as a real bench would. A motor at rest is left as it is (its time does not
        move: runs stay deterministic). Returns the time to the next idle step, s."""
        drive = self._drive
        if self.nmt.state is NmtState.OPERATIONAL or drive.enabled or self.idle_brake <= 0:
            self._idle_at = None
            return IDLE_STEP_S
        state = drive.state
        if state.w_m == 0.0 and abs(state.psi_r_ab) < IDLE_FLUX and abs(state.i_s_ab) == 0.0:
            self._idle_at = None
            return IDLE_STEP_S
        if self._idle_at is None:
            self._idle_at = now
            return IDLE_STEP_S
        h = drive.params.h
        n = int((now - self._idle_at) / h)
        if n <= 0:
            return IDLE_STEP_S
        n = min(n, IDLE_MAX_STEPS)
        self._idle_at = now if n == IDLE_MAX_STEPS else self._idle_at + n * h
        meas = drive.advance(n * h, 0.0)
        drive.brake(self.idle_brake * n * h)
        if self._off_since is not None:  # what is left for _rest: the time since this step
            self._off_since = self._idle_at
        if abs(drive.state.psi_r_ab) < IDLE_FLUX and drive.state.w_m == 0.0:
            drive.reset(MotorState(0.0, 0j, 0j))  # at rest: exactly (a deterministic start)
        self._put(VELOCITY_ACTUAL, drive.state.w_m / self._units.velocity)
        self._put(TORQUE_ACTUAL, meas.T_e / self._units.torque)
        return IDLE_STEP_S


_NOT_PUT = "not written"  # no such object, or not a number
_FLOAT = "float"


def _put_kind(var: Any) -> Any:
    """How :meth:`DriveDevice._put` writes an object (an ODVariable, or None when the
    dictionary lacks it): as a float, as an integer (bits, signed, lowest, highest), or
    not at all."""
    if var is None:
        return _NOT_PUT
    if var.data_type in datatypes.FLOAT_TYPES:
        return _FLOAT
    if var.data_type not in datatypes.INTEGER_TYPES:
        return _NOT_PUT
    bits, signed = len(var), var.data_type in datatypes.SIGNED_TYPES
    lo, hi = (-(1 << (bits - 1)), (1 << (bits - 1)) - 1) if signed else (0, (1 << bits) - 1)
    return bits, signed, lo, hi


def _finite(meas: Measurement) -> bool:
    """Every number of a measurement is finite."""
    isfinite = math.isfinite
    i, u, psi = meas.i_s_ab, meas.u_s_ab, meas.psi_r_ab
    return (isfinite(i.real) and isfinite(i.imag) and isfinite(u.real) and isfinite(u.imag)
            and isfinite(meas.w_m) and isfinite(psi.real) and isfinite(psi.imag)
            and isfinite(meas.T_e))


def _at_rest(u_dc: float) -> Measurement:
    """The measurement of a model at rest (after a reset from a non-finite state)."""
    return Measurement(0j, 0j, u_dc, 0.0, 0j, 0.0, False)
