"""The emulated drive's own control in the standard CiA 402 modes (pure).

A standard inverter offers no vector current or voltage process data: it takes a target
torque (cyclic synchronous torque, CST, mode 10) or a target velocity (cyclic synchronous
velocity, CSV, mode 9) every SYNC and runs its own field-oriented control. This module is
that control (and cyclic synchronous position, CSP, mode 8: a position loop over the
speed loop; the profile modes, PV 3 and PT 4, give it the output of their ramp,
:mod:`plant.profile`), on top of the drive's current source (:class:`plant.drive.Drive` in ``ideal``
or ``current-loop`` mode), evaluated once per SYNC period:

* **Indirect field orientation** with the drive's own motor parameters (those in 0x2200):
  the rotor flux of the model in its own (d, q) frame, with the d-axis current i_d*
  magnetising it to ``psi_rated``, follows over one period T exactly
  ψ_d ← ψ_d·e^{−αT} + M·i_d*·(1 − e^{−αT}) (rows 2–3 of (1) in a frame aligned with ψ_r);
  the torque current is i_q* = T*·L_r/(M·ψ_d) (T_e = (M/L_r)·ψ_d·i_q, row 1 of (1)); the
  frame turns at ω_0 = ω + α·M·i_q*/ψ_d (the slip that keeps the rotor flux on the d axis)
  from the angle it reached at the end of the previous period. The (d, q) setpoints go to
  the drive, which turns their frame itself (§E9); ω is the rotor's speed at the middle of
  the period, extrapolated from the encoder's last two samples (a real drive runs this at
  its PWM rate; once per period, the speed's change within it would otherwise turn the
  flux off the d axis by Δω/(2α) while accelerating). With exact parameters the rotor flux
  stays on the d axis; an error decays with the rotor time constant 1/α.
* **Torque limit:** |T*| ≤ ``T_max``, and the current vector |i*| ≤ ``i_max`` (the d axis
  first: the flux is kept, the torque current gets what is left).
* **Position loop (CSP):** ω* = (w_bw/4)·(θ* − θ) + (θ*_k − θ*_{k−1})/T, θ the encoder's
  position (the trapezoid of its speed samples), then the speed loop.
* **Speed loop (CSV):** a PI on the encoder's speed, T* = K_p·e + x, x ← x + K_i·T·e with
  e = ω* − ω, tuned for a double closed-loop pole at ``w_bw`` on the motor's inertia
  (K_p = 2·J·w_bw, K_i = J·w_bw²); while the torque limit clips, the integrator holds
  (conditional integration).

The velocity actual value is the encoder's (the model's ω at the sample) and the torque
actual value the model's torque at the sample (:class:`plant.drive.Measurement`);
:attr:`Servo.T_est` is the torque the drive's own model expects, (M/L_r)·ψ_d·i_q*.
"""

from __future__ import annotations

import cmath
import math
from dataclasses import dataclass

from dbc.cia402 import OperationMode
from dbc.modes import SetpointFrame
from dbc.motor import MotorParams
from plant.drive import Setpoints

#: The emulated motor's rated torque, N·m (0x6076): the unit of 0x6071, 0x6072 and 0x6077
#: is 1/1000 of it.
T_RATED = 10.0
#: One unit of 0x6071/0x6077, N·m (1/1000 of the rated torque).
TORQUE_UNIT = T_RATED / 1000
#: The emulated motor's rated current, A (amplitude): about the current vector at the rated
#: torque and flux (3.4 A magnetising, 9.5 A torque-producing); the unit of 0x6078 of a twin
#: whose file has no 0x6075 is 1/1000 of it.
I_RATED = 10.0


@dataclass(frozen=True)
class ServoParams:
    """The drive's own control. psi_rated: rotor flux it magnetises to, Wb. i_max: current
    vector limit, A. T_max: torque limit, N·m (0x6072 · 0x6076 / 1000). w_bw: speed-loop
    bandwidth, rad/s (CSV)."""

    psi_rated: float = 1.16
    i_max: float = 20.0
    T_max: float = 20.0
    w_bw: float = 60.0

    def __post_init__(self) -> None:
        for name in ("psi_rated", "i_max", "T_max", "w_bw"):
            value = getattr(self, name)
            if not (math.isfinite(value) and value > 0.0):
                raise ValueError(f"ServoParams.{name} = {value!r} must be a finite number > 0")


def servo_for(motor: MotorParams, i_trip: float, T: float, max_torque: int | None = None,
              w_m: float = 0.0, torque_unit: float = TORQUE_UNIT) -> Servo:
    """The emulated drive's own control: current limit 0.8 × its over-current trip
    ``i_trip`` (20 A where there is none), torque limit ``max_torque`` in 1/1000 of the rated
    torque (0x6072, ``torque_unit`` N·m each; None: the default, 20 N·m), period ``T``, the
    motor's speed now ``w_m`` (rad/s: its encoder's first sample)."""
    i_max = 0.8 * i_trip if math.isfinite(i_trip) else 20.0
    T_max = ServoParams().T_max if max_torque is None else max_torque * torque_unit
    servo = Servo(motor, ServoParams(i_max=i_max, T_max=T_max), T)
    servo.w_enc = w_m
    return servo


class Servo:
    """Field orientation and speed loop of the standard modes (see the module docstring).

    :meth:`torque` and :meth:`velocity` return the (d, q) setpoints for the next period of
    ``T`` seconds; :meth:`reset` when the power stage goes off. :attr:`T_est` is the torque
    the drive reports (0x6077), N·m."""

    def __init__(self, motor: MotorParams, params: ServoParams, T: float) -> None:
        self.motor, self.params, self.T = motor, params, T
        self._decay = math.exp(-motor.alpha * T)
        self._K_p = 2.0 * motor.J * params.w_bw
        self._K_i = motor.J * params.w_bw ** 2
        self._K_pos = params.w_bw / 4.0
        self.theta = 0.0  # the encoder's position, rad (counted from power-up)
        self.w_enc = 0.0  # the encoder's speed at the last sample, rad/s
        self.reset()

    def reset(self) -> None:
        """Power off: no flux in the model, the frame at 0, the speed integrator empty."""
        self._psi_d = 0.0
        self._eps = 0.0
        self._x = 0.0
        self._w_last: float | None = None
        self._theta_ref_last: float | None = None
        self.T_est = 0.0

    def sample(self, w_m: float) -> None:
        """The encoder after each period: its speed :attr:`w_enc` is ``w_m`` and its
        position :attr:`theta` (rad) advances by the trapezoid of the speeds at the
        period's ends."""
        self.theta += 0.5 * (self.w_enc + w_m) * self.T
        self.w_enc = w_m

    def follow(self, mode: OperationMode, target: float) -> Setpoints:
        """One SYNC in a standard ``mode``: its ``target`` (SI: N·m, rad or rad/s, see
        :data:`plant.units.TARGETS`; in a profile mode the ramp's output) → the (d, q)
        setpoints for the period, on the encoder's last sample."""
        if mode.torque:
            return self.torque(target, self.w_enc)
        if mode is OperationMode.CYCLIC_SYNC_POSITION:
            return self.position(target, self.w_enc)
        return self.velocity(target, self.w_enc)

    def position(self, theta_ref: float, w_m: float) -> Setpoints:
        """CSP: a proportional position loop, gain ``w_bw``/4, with the target's own speed
        (its change over the period) fed forward, to a speed, then :meth:`velocity`."""
        last = self._theta_ref_last
        w_ff = 0.0 if last is None else (theta_ref - last) / self.T
        self._theta_ref_last = theta_ref
        return self.velocity(self._K_pos * (theta_ref - self.theta) + w_ff, w_m)

    def velocity(self, w_ref: float, w_m: float) -> Setpoints:
        """CSV: the speed PI (on ``w_m``, the encoder's ω, rad/s) to a torque, then
        :meth:`torque`."""
        e = w_ref - w_m
        T_cmd = self._K_p * e + self._x
        T_max = self.params.T_max
        if -T_max < T_cmd < T_max:
            self._x += self._K_i * self.T * e
        return self.torque(max(-T_max, min(T_max, T_cmd)), w_m)

    def torque(self, T_ref: float, w_m: float) -> Setpoints:
        """CST: the (d, q) setpoints that make ``T_ref`` N·m (limited) at speed ``w_m``."""
        m, p = self.motor, self.params
        T_ref = max(-p.T_max, min(p.T_max, T_ref))
        i_d = min(p.psi_rated / m.M, p.i_max)
        psi_d = self._psi_d
        i_q = 0.0
        if psi_d > 1e-3 * p.psi_rated:
            i_q_max = math.sqrt(max(p.i_max * p.i_max - i_d * i_d, 0.0))
            i_q = max(-i_q_max, min(i_q_max, T_ref * m.L_r / (m.M * psi_d)))
        # the rotor turns on during the period: its speed at the middle, extrapolated from
        # the encoder's last two samples, keeps the frame on the flux while accelerating
        w_mid = w_m if self._w_last is None else 1.5 * w_m - 0.5 * self._w_last
        self._w_last = w_m
        w_0 = w_mid + (m.alpha * m.M * i_q / psi_d if i_q else 0.0)
        sp = Setpoints(frame=SetpointFrame.DQ, i_s_ref=complex(i_d, i_q),
                       eps_0=math.remainder(self._eps, 2.0 * math.pi), w_0=w_0)
        self.T_est = m.M / m.L_r * psi_d * i_q
        self._eps += w_0 * self.T
        self._psi_d = psi_d * self._decay + m.M * i_d * (1.0 - self._decay)
        return sp

    @property
    def frame(self) -> complex:
        """e^{jε} of the drive's frame at the start of the next period."""
        return cmath.exp(1j * self._eps)
