"""The emulated drive: inverter + motor model (1), pure (no I/O, no clock, no global state).

:class:`Drive` follows docs/ARCHITECTURE.md ("plant.drive.Drive"). Each :meth:`Drive.advance`
call simulates one period T as ``n = T·f_pwm`` internal steps of ``h = 1/f_pwm`` and returns
the :class:`Measurement` sampled at its end.

Setpoint frames (§E8, §E9): (d, q) setpoints are turned by the drive itself,
ε(t) = eps_0 + w_0·(t − t_app), where t_app is the start of the first period the setpoints
act on (the frame keeps turning if no new setpoints arrive); (a, b) setpoints are held.

Modes (:class:`plant.params.DriveParams`):

* ``ideal``: i_s equals the setpoint, turning continuously with ε(t); rows 1–3 of (1) are
  integrated with RK4, which samples i_s(t) exactly at each stage (chosen over the exact
  discretisation with ω frozen: the same fourth-order integrator as the other modes, no
  error from ω changing within a step, and ~1 µs per step). The reported voltage is
  the exact period average u = Δψ_s/T + R_s·mean(i_s), with ψ_s = σi_s + (M/L_r)ψ_r (§E1)
  and the analytic mean of the turning current vector. A setpoint change makes i_s jump at
  the start of the period: the jump is counted in Δψ_s (ψ_s at the start is taken before
  the jump), so Σ u·T reproduces the true stator flux at the samples — what the estimator
  (24) integrates.
* ``current-loop``: a discrete PI current controller in the setpoint frame, once per
  internal step from the *measured* current at the step start (the true current through the
  sensor model below, a fresh noise draw per step: a real drive regulates what its sensors
  read, so a sensor offset becomes a true current error), with the voltage feedforward
  u_s_ref added:
  u = u_s_ref + K_p·e + x, x ← x + K_i·h·e. Gains (:func:`pi_gains`): K_p = σ(1 − e^{−ω_bw·h})/h
  puts the discrete closed-loop pole at e^{−ω_bw·h} (the current follows a step as
  1 − e^{−ω_bw·t} at the steps; K_p → σ·ω_bw as h → 0), K_i = K_p·R_eff/σ with
  R_eff = R_s + R_r(M/L_r)² cancels the stator's electrical pole (1). The voltage vector is
  limited to |u| ≤ u_lim = u_dc/√3 (circular, direction kept). Anti-windup by
  back-calculation with the tracking time T_t = T_i = K_p/K_i = σ/R_eff: while the limit
  clips, x ← x + (h/T_i)·(u_applied − u_s_ref − x), i.e. the integrator low-passes the
  voltage actually applied (and the update equals K_i·h·e when not clipping). So |x| never
  exceeds the limit, and after a long saturation x holds about the voltage the new
  operating point needs (resistive drop + back-EMF): no overshoot and no slow creep.
  The voltage is held over the step (ZOH, the PWM average) and rotated to (a, b) with the
  angle of the step's midpoint (the usual PWM-delay angle compensation).
* ``voltage``: u_s_ref applied (rotated with the step's midpoint angle, held over the step),
  limited as above.

In ``current-loop`` and ``voltage`` the full model (1) is integrated with RK4, voltage held.

Current sensors (:class:`plant.params.DriveParams`): a three-phase drive measures phases a
and b (i_c = −i_a − i_b) and maps them to the (a, b) frame of (1) by the amplitude-invariant
Clarke transform, i_a = i_sa, i_b = −i_sa/2 + (√3/2)·i_sb. Each phase sensor reads
(1 + i_gain_error)(1 + i_gain_phase[k]) times the true phase current; then the offset
``i_offset_ab`` (in the (a, b) frame) and Gaussian noise (``i_noise_rms`` per axis) are
added. The measured current is what the drive reports *and* what its current control
regulates: in ``ideal`` mode (a perfect current loop) the *measured* current equals the
setpoint, i.e. the true current is the sensor model inverted (noise excluded).

Inverter voltage errors (``current-loop`` and ``voltage``; the reported voltage stays the
commanded one, as a real drive reports its reference): dead time, −dead_time·f_pwm·u_dc·
sign(i_k) on each phase k, from the true phase currents at the step start; DC-link ripple,
the applied vector scaled by 1 + u_dc_ripple·sin(2π·u_dc_ripple_hz·t) at the step midpoint
(the modulator assumes the nominal u_dc: no DC-link compensation). The reported DC link
(TPDO2's u_dc) is the period's mean of that rippled DC link, as a drive that measures its
DC link every PWM period reports it; in ``ideal`` mode (no inverter) the nominal u_dc.

Plant-side options of the constructor (see :mod:`plant.scenario`): ``load`` =
f(t, T_L) gives the dynamometer torque at time t from the value T_L passed to
:meth:`Drive.advance` (held over the period), evaluated at each internal step's midpoint;
``motor_drift`` = {field: relative change per second} makes the motor's parameters
p(t) = p·(1 + d·t), updated once per period at its midpoint (the current-loop gains keep
their initial tuning, as a real drive's would).

Disabled power stage (``enable(False)``, or an over-current trip |i_s| > i_trip): no voltage
is applied. The freewheeling diodes apply −u_lim·i_s/|i_s| while current flows; the step in
which the current would reverse is cut at the (linearly interpolated) zero crossing, after
which the stator is open (i_s = 0): the rotor flux decays as e^{−αt} while turning with the
rotor, which coasts under T_L — solved exactly. The reported voltage is the terminal voltage
(open stator: dψ_s/dt = (M/L_r)dψ_r/dt, the back-EMF). Assumes the back-EMF stays below
u_lim (no uncontrolled rectification into the DC link). In ``ideal`` mode disabled means
i_s = 0 at once. The PI integrator is reset while disabled.

Units: SI (A, V, Wb, rad, rad/s, N·m, s).
"""

from __future__ import annotations

import cmath
import math
import random
from collections.abc import Callable, Mapping
from dataclasses import dataclass, replace

from dbc.modes import DriveMode, SetpointFrame
from dbc.motor import MotorParams
from plant.motor import Coeffs, coeffs, rk4_step_full
from plant.params import DriveParams

_FRAMES = {f.value: f for f in SetpointFrame}
_isfinite = cmath.isfinite


@dataclass(frozen=True, slots=True)
class Setpoints:
    """Setpoints of one interval (docs/ARCHITECTURE.md).

    frame: :class:`SetpointFrame` — DQ (turned by the drive) or AB (held).
    i_s_ref: stator-current setpoint in that frame, A (d + jq or a + jb).
    u_s_ref: stator-voltage setpoint in that frame, V (feedforward in ``current-loop``,
        the applied voltage in ``voltage``, unused in ``ideal``).
    eps_0: frame angle at the start of the interval, rad; w_0: frame speed, rad/s
        (both ignored for "ab").
    """

    frame: SetpointFrame = SetpointFrame.DQ
    i_s_ref: complex = 0j
    u_s_ref: complex = 0j
    eps_0: float = 0.0
    w_0: float = 0.0

    def __post_init__(self) -> None:
        try:
            frame = _FRAMES[self.frame]  # SetpointFrame(self.frame), without Enum's call
        except (KeyError, TypeError):
            raise ValueError(f"Setpoints.frame = {self.frame!r}: use 'dq' or 'ab'") from None
        if frame is not self.frame:
            object.__setattr__(self, "frame", frame)
        try:  # the usual case (numbers), checked without the loop below
            if (_isfinite(self.i_s_ref) and _isfinite(self.u_s_ref) and _isfinite(self.eps_0)
                    and _isfinite(self.w_0)):
                return
        except TypeError:
            pass
        for name in ("i_s_ref", "u_s_ref", "eps_0", "w_0"):
            if not cmath.isfinite(complex(getattr(self, name))):
                raise ValueError(f"Setpoints.{name} = {getattr(self, name)!r} is not finite")


@dataclass(frozen=True, slots=True)
class Measurement:
    """One sample at the end of a period.

    i_s_ab: stator current with sensor errors, A.  u_s_ab: average applied (terminal)
    voltage over the period, V.  u_dc: the DC-link voltage's mean over the period, V
    (its ripple included; ``ideal`` mode: the nominal u_dc).  Truth for diagnostics:
    w_m (rad/s), psi_r_ab (Wb), T_e (N·m) at the sample instant.
    limit_active: the voltage limit clipped during the period (never in ``ideal`` mode,
    which has no voltage limit: its reported voltage may exceed u_lim).
    """

    i_s_ab: complex
    u_s_ab: complex
    u_dc: float
    w_m: float
    psi_r_ab: complex
    T_e: float
    limit_active: bool


_SET_MEASUREMENT = tuple(Measurement.__dict__[f].__set__ for f in (
    "i_s_ab", "u_s_ab", "u_dc", "w_m", "psi_r_ab", "T_e", "limit_active"))


def _measurement(i_s_ab: complex, u_s_ab: complex, u_dc: float, w_m: float,
                 psi_r_ab: complex, T_e: float, limit_active: bool,
                 _new: Callable = object.__new__, _cls: type = Measurement,
                 _s: tuple = _SET_MEASUREMENT) -> Measurement:
    """``Measurement(i_s_ab, u_s_ab, u_dc, w_m, psi_r_ab, T_e, limit_active)``, built
    faster (through its slots): every period's sample."""
    m = _new(_cls)
    _s[0](m, i_s_ab); _s[1](m, u_s_ab); _s[2](m, u_dc); _s[3](m, w_m)  # noqa: E702
    _s[4](m, psi_r_ab); _s[5](m, T_e); _s[6](m, limit_active)  # noqa: E702
    return m


@dataclass(frozen=True, slots=True)
class MotorState:
    """The state of model (1): ω (rad/s), ψ_r (Wb), i_s (A), fixed frame."""

    w_m: float = 0.0
    psi_r_ab: complex = 0j
    i_s_ab: complex = 0j


def pi_gains(motor: MotorParams, params: DriveParams) -> tuple[float, float]:
    """(K_p in V/A, K_i in V/(A·s)) of the current controller (see the module docstring)."""
    h = params.h
    K_p = motor.sigma * -math.expm1(-params.current_loop_bw * h) / h
    return K_p, K_p * motor.R_eff / motor.sigma


SQRT3 = math.sqrt(3.0)
LoadFunction = Callable[[float, float], float]


_NO_TURN = (1.0, 0.0, 1.0, 0.0)  # e^{j0}, e^{j0}: (a, b) setpoints are held


def _mean_turning(w_0_T: float) -> complex:
    """(e^{jx} − 1)/(jx) for x = ω0·T: the mean of e^{jω0·t} over [0, T]."""
    if abs(w_0_T) < 1e-4:
        return complex(1.0 - w_0_T * w_0_T / 6.0, 0.5 * w_0_T)
    return (cmath.exp(1j * w_0_T) - 1.0) / (1j * w_0_T)


class Drive:
    """Inverter + induction motor, advanced one period at a time (docs/ARCHITECTURE.md).

    ``Drive(motor, params, state=None)``; :meth:`set_setpoints`, :meth:`enable`,
    :meth:`advance`, :attr:`state`, :meth:`reset`, :attr:`t`. The power stage starts
    disabled with zero setpoints; the sensor-noise generator is seeded with
    ``params.seed`` (and re-seeded by :meth:`reset`).
    """

    def __init__(
        self,
        motor: MotorParams | None = None,
        params: DriveParams | None = None,
        state: MotorState | None = None,
        *,
        load: LoadFunction | None = None,
        motor_drift: Mapping[str, float] | None = None,
    ) -> None:
        self.motor = motor if motor is not None else MotorParams()
        self.params = params if params is not None else DriveParams()
        if self.params.mode.standard:
            raise ValueError(f"Drive: mode {self.params.mode} is the drive's own control "
                             "(plant.servo) over a current source: give the model 'ideal' or "
                             "'current-loop'")
        self._h = h = self.params.h
        self._set_coeffs(coeffs(self.motor))
        self._K_p, self._K_i = K_p, K_i = pi_gains(self.motor, self.params)
        self.load = load
        self.motor_drift = {k: float(v) for k, v in (motor_drift or {}).items() if v}
        p = self.params
        g = 1.0 + p.i_gain_error
        ka, kb = 1.0 + p.i_gain_phase[0], 1.0 + p.i_gain_phase[1]
        self._phase_gains = p.i_gain_phase != (0.0, 0.0)
        # measured (a, b) = S·true + offset, S = g·[[ka, 0], [(ka − kb)/√3, kb]]
        self._S = (g * ka, g * (ka - kb) / SQRT3, g * kb)
        self._g = g
        self._exact_sensors = (g == 1.0 and not self._phase_gains and p.i_offset_ab == 0
                               and p.i_noise_rms == 0.0)
        self._du_dead = p.dead_time * p.f_pwm * p.u_dc
        self._u_errors = self._du_dead > 0.0 or p.u_dc_ripple > 0.0
        # read once, not every period
        self._ideal = p.mode is DriveMode.IDEAL
        self._loop = p.mode is DriveMode.CURRENT_LOOP
        self._u_lim = u_lim = p.u_lim
        self._trip2 = p.i_trip**2
        # the current loop's constants: K_p, K_i·h, h/T_i = K_i·h/K_p, u_lim, u_lim²
        self._pi = (K_p, K_i * h, K_i * h / K_p, u_lim, u_lim * u_lim)
        self._u_dc = p.u_dc
        self._i_offset = p.i_offset_ab
        self._T_n: tuple[float, int] | None = None  # (T, its whole steps) of the last period
        self._w_0h: float | None = None  # ω0·h of the cached e^{jω0·h} and e^{jω0·h/2}
        self._turn = _NO_TURN
        self.reset(state)

    # ---- sensors and inverter errors ----------------------------------------------------------
    def _sense(self, i: complex, noise: bool = True) -> complex:
        """The measured current (a, b) for the true one (see the module docstring)."""
        p = self.params
        if self._phase_gains:
            sa, sba, sb = self._S
            z = complex(sa * i.real, sba * i.real + sb * i.imag) + p.i_offset_ab
        else:
            z = self._g * i + p.i_offset_ab
        if noise and p.i_noise_rms > 0.0:
            gauss = self._rng.gauss
            z += complex(gauss(0.0, p.i_noise_rms), gauss(0.0, p.i_noise_rms))
        return z

    def _unsense(self, z: complex) -> complex:
        """The true current whose noise-free measurement is z (inverse of :meth:`_sense`)."""
        z = z - self.params.i_offset_ab
        sa, sba, sb = self._S
        x = z.real / sa
        return complex(x, (z.imag - sba * x) / sb)

    def _u_error(self, u_ab: complex, i: complex, t_mid: float) -> complex:
        """The applied voltage for the commanded ``u_ab``: DC-link ripple and dead time."""
        p = self.params
        if p.u_dc_ripple > 0.0:
            u_ab *= 1.0 + p.u_dc_ripple * math.sin(2.0 * math.pi * p.u_dc_ripple_hz * t_mid)
        du = self._du_dead
        if du > 0.0:
            i_a = i.real
            i_b = -0.5 * i.real + 0.5 * SQRT3 * i.imag
            e_a = -du * ((i_a > 0.0) - (i_a < 0.0))
            e_b = -du * ((i_b > 0.0) - (i_b < 0.0))
            i_c = -i_a - i_b
            e_c = -du * ((i_c > 0.0) - (i_c < 0.0))
            u_ab += complex((2.0 * e_a - e_b - e_c) / 3.0, (e_b - e_c) / SQRT3)
        return u_ab

    def _dc_link(self, n: int) -> float:
        """The DC link's mean over the n internal steps from step ``self._n`` (what the
        drive reports, V): u_dc·(1 + u_dc_ripple·mean sin(2π·u_dc_ripple_hz·t_mid)), the
        ripple at each step's midpoint as :meth:`_u_error` applies it; the sum of sines in
        closed form, sin(ω·t_c)·sin(n·ωh/2)/(n·sin(ωh/2)), t_c the period's midpoint."""
        p = self.params
        if p.u_dc_ripple == 0.0:
            return self._u_dc
        w = 2.0 * math.pi * p.u_dc_ripple_hz
        half = 0.5 * w * self._h
        h, t0 = self._h, self._n * self._h
        if abs(math.sin(half)) < 1e-9:  # a whole number of ripple periods per step
            mean = sum(math.sin(w * (t0 + (k + 0.5) * h)) for k in range(n)) / n
        else:
            mean = math.sin(w * (t0 + 0.5 * n * h)) * math.sin(n * half) / (n * math.sin(half))
        return self._u_dc * (1.0 + p.u_dc_ripple * mean)

    def _drift(self, t_mid: float) -> None:
        """Motor parameters at t_mid (linear drifts); the coefficients of (1) follow."""
        m = self.motor
        values = {k: getattr(m, k) * (1.0 + d * t_mid) for k, d in self.motor_drift.items()}
        try:
            c = coeffs(replace(m, **values))
        except ValueError as exc:
            raise ValueError(f"motor drift at t = {t_mid:.3f} s: {exc}") from exc
        self._set_coeffs(c)

    def _set_coeffs(self, c: Coeffs) -> None:
        """The coefficients of (1) now, and as the internal steps read them: −α, αM, β, μ,
        R_s/σ, 1/σ, 1/J, h/2, h/6."""
        self._c = c
        h = self._h
        self._k = (-c.alpha, c.alpha_M, c.beta, c.mu, c.R_s_over_sigma, c.inv_sigma, c.inv_J,
                   0.5 * h, h / 6.0)

    # ---- commands ---------------------------------------------------------------------------
    def reset(self, state: MotorState | None = None) -> None:
        """Back to t = 0 with ``state`` (zero if None), disabled, zero setpoints, no trip."""
        s = state if state is not None else MotorState()
        self._w = float(s.w_m)
        self._psi = complex(s.psi_r_ab)
        self._i = complex(s.i_s_ab)
        self._n = 0
        self._sp = Setpoints()
        self._n_app: int | None = None
        self._enabled = False
        self._tripped = False
        self._x_ab = 0j
        self._rng = random.Random(self.params.seed)

    def set_setpoints(self, sp: Setpoints) -> None:
        """Make ``sp`` active from the next :meth:`advance` on (its start is t_app)."""
        self._sp = sp
        self._n_app = None

    def set_references(self, sp: Setpoints) -> None:
        """Make ``sp``'s current and voltage references active in the running (d, q) frame:
        new values without a new frame (an RPDO with the references alone). The frame keeps
        turning from where it is; ``sp``'s eps_0 and w_0 (which described an earlier
        interval's start) are not used. In another frame, or with none running yet, it is
        :meth:`set_setpoints`."""
        if (sp.frame is not SetpointFrame.DQ or self._sp.frame is not SetpointFrame.DQ
                or self._n_app is None):
            self.set_setpoints(sp)
            return
        self._sp = replace(self._sp, i_s_ref=sp.i_s_ref, u_s_ref=sp.u_s_ref)

    def brake(self, dw: float) -> None:
        """Slow the rotor by ``dw`` rad/s towards rest, not past it: the test bench's load
        machine holding an idle motor (:class:`plant.device.DriveDevice` between runs)."""
        self._w = math.copysign(max(abs(self._w) - max(dw, 0.0), 0.0), self._w)

    def enable(self, on: bool) -> None:
        """Power stage on/off. Switching on clears an over-current trip."""
        if on and not self._enabled:
            self._x_ab = 0j
            self._tripped = False
        self._enabled = bool(on)
        if not on:
            self._x_ab = 0j

    # ---- queries ----------------------------------------------------------------------------
    @property
    def state(self) -> MotorState:
        """The true motor state now."""
        return MotorState(self._w, self._psi, self._i)

    @property
    def t(self) -> float:
        """Simulated time, s (whole internal steps since :meth:`reset`)."""
        return self._n * self._h

    @property
    def enabled(self) -> bool:
        """The power stage is on (False after an over-current trip)."""
        return self._enabled

    @property
    def tripped(self) -> bool:
        """An over-current trip (|i_s| > i_trip) switched the power stage off."""
        return self._tripped

    @property
    def setpoints(self) -> Setpoints:
        """The active setpoints."""
        return self._sp

    # ---- simulation -------------------------------------------------------------------------
    def _whole_steps(self, T: float) -> int:
        n = round(T * self.params.f_pwm)
        if not (T > 0.0) or n < 1 or abs(n * self._h - T) > 1e-9 * T:
            raise ValueError(
                f"advance: T = {T!r} s is not a whole number of internal steps "
                f"h = 1/f_pwm = {self._h!r} s; use a positive multiple of h"
            )
        return n

    def _frame(self, n: int) -> tuple[complex, tuple[float, float, float, float]]:
        """(e^{jε} at the present step, (e^{jω0·h} and e^{jω0·h/2} as their real and
        imaginary parts)) for the active setpoints."""
        sp = self._sp
        if sp.frame is SetpointFrame.AB:
            return 1 + 0j, _NO_TURN
        if self._n_app is None:
            self._n_app = self._n
        w_0h = sp.w_0 * self._h
        rot = cmath.exp(1j * (sp.eps_0 + w_0h * (self._n - self._n_app)))
        if w_0h != self._w_0h:  # the same frame speed as the last period's: kept
            self._w_0h = w_0h
            step, half = cmath.exp(1j * w_0h), cmath.exp(0.5j * w_0h)
            self._turn = (step.real, step.imag, half.real, half.imag)
        return rot, self._turn

    def advance(self, T: float, T_L: float) -> Measurement:
        """Simulate the period (t, t + T] with the active setpoints and load torque T_L (N·m).

        T must be a whole number of internal steps (else ValueError). Returns the
        measurement at t + T: currents (with sensor errors), the period's average voltage
        and the truth.
        """
        T_n = self._T_n
        if T_n is not None and T_n[0] == T:
            n = T_n[1]
        else:
            n = self._whole_steps(T)
            self._T_n = (T, n)
        T_L = float(T_L)
        if self.motor_drift:
            self._drift((self._n + 0.5 * n) * self._h)
        if self._sp.frame is SetpointFrame.DQ and self._n_app is None:
            self._n_app = self._n
        if self._ideal:
            u_avg, limited = self._advance_ideal(n, T_L), False
        else:
            u_avg, limited = self._advance_inverter(n, T_L)
        u_dc = self._u_dc if self._ideal else self._dc_link(n)
        self._n += n
        return self._measure(u_avg, limited, u_dc)

    def advance_held(self, periods: int, T: float, T_L: float) -> Measurement:
        """:meth:`advance` ``periods`` times with the setpoints held (a drive that saw no SYNC
        in between: the SYNC counter told it that many periods passed); the measurement of
        the last period (its average voltage too), as on time."""
        for _ in range(periods - 1):
            self.advance(T, T_L)
        return self.advance(T, T_L)

    def _torque(self, k: float, T_L: float) -> float:
        """The load torque over internal step k of this period (dynamometer, N·m)."""
        if self.load is None:
            return T_L
        return self.load((self._n + k + 0.5) * self._h, T_L)

    def _trip(self) -> None:
        self._enabled = False
        self._tripped = True
        self._x_ab = 0j

    def _advance_ideal(self, n: int, T_L: float) -> complex:
        """Current-fed model; returns the exact average voltage Δψ_s/T + R_s·mean(i_s).

        The n RK4 steps of rows 1–3 of (1) run on float locals, as in
        :meth:`_run_inverter` (the same operations as :func:`plant.motor.
        rk4_step_current_fed`).
        """
        c = self._c
        h = self._h
        psi_s_start = c.sigma * self._i + c.M_over_L_r * self._psi
        sp = self._sp
        if self._enabled and abs(sp.i_s_ref) > self.params.i_trip:
            self._trip()
        if self._enabled:
            rot, (sa, sb, ha, hb) = self._frame(n)
            i_ref = sp.i_s_ref
            turning = _mean_turning(sp.w_0 * n * h) if sp.frame is SetpointFrame.DQ else 1.0
            mean_i = i_ref * rot * turning
            i0 = i_ref * rot  # the measured current at the step start: the setpoint
            ca, cb = i0.real, i0.imag
            # the measured current follows the setpoint; the true one is its sensor
            # model inverted (or the same with exact sensors)
            un = None if self._exact_sensors and self.load is None else self._unsense
            if un is not None:
                mean_i = un(mean_i)
            varying = self.load is not None
            na, aM, _, mu, _, _, inv_J, hh, h6 = self._k
            load = T_L * inv_J
            w, psi = self._w, self._psi
            pa, pb = psi.real, psi.imag
            for k in range(n):
                # the setpoint at the step's midpoint and end: i0·e^{jω0·h/2}, i0·e^{jω0·h}
                ma = ca * ha - cb * hb
                mb = ca * hb + cb * ha
                ea = ca * sa - cb * sb
                eb = ca * sb + cb * sa
                if un is None:
                    ia0, ib0, iam, ibm, ia1, ib1 = ca, cb, ma, mb, ea, eb
                else:
                    z = un(complex(ca, cb))
                    ia0, ib0 = z.real, z.imag
                    z = un(complex(ma, mb))
                    iam, ibm = z.real, z.imag
                    z = un(complex(ea, eb))
                    ia1, ib1 = z.real, z.imag
                if varying:
                    load = self._torque(k, T_L) * inv_J
                # one classical RK4 step of rows 1–3 of (1), i_s sampled at each stage:
                # dψ_r/dt = (−α + jω)ψ_r + αM·i_s, dω/dt = μ(ψ_ra·i_sb − ψ_rb·i_sa) − T_L/J
                dpa1 = na * pa - w * pb + aM * ia0
                dpb1 = na * pb + w * pa + aM * ib0
                dw1 = mu * (pa * ib0 - pb * ia0) - load
                w2 = w + hh * dw1
                pa2 = pa + hh * dpa1
                pb2 = pb + hh * dpb1
                dpa2 = na * pa2 - w2 * pb2 + aM * iam
                dpb2 = na * pb2 + w2 * pa2 + aM * ibm
                dw2 = mu * (pa2 * ibm - pb2 * iam) - load
                w3 = w + hh * dw2
                pa3 = pa + hh * dpa2
                pb3 = pb + hh * dpb2
                dpa3 = na * pa3 - w3 * pb3 + aM * iam
                dpb3 = na * pb3 + w3 * pa3 + aM * ibm
                dw3 = mu * (pa3 * ibm - pb3 * iam) - load
                w4 = w + h * dw3
                pa4 = pa + h * dpa3
                pb4 = pb + h * dpb3
                dpa4 = na * pa4 - w4 * pb4 + aM * ia1
                dpb4 = na * pb4 + w4 * pa4 + aM * ib1
                dw4 = mu * (pa4 * ib1 - pb4 * ia1) - load
                w = w + h6 * (dw1 + 2.0 * (dw2 + dw3) + dw4)
                pa = pa + h6 * (dpa1 + 2.0 * (dpa2 + dpa3) + dpa4)
                pb = pb + h6 * (dpb1 + 2.0 * (dpb2 + dpb3) + dpb4)
                ca, cb = ea, eb
            self._w, self._psi = w, complex(pa, pb)
            self._i = complex(ca, cb) if un is None else un(complex(ca, cb))
        else:
            mean_i = 0j
            self._i = 0j
            self._open_circuit(n * h, self._torque(0.5 * n - 0.5, T_L))
        psi_s_end = c.sigma * self._i + c.M_over_L_r * self._psi
        return (psi_s_end - psi_s_start) / (n * h) + c.R_s * mean_i

    def _advance_inverter(self, n: int, T_L: float) -> tuple[complex, bool]:
        """current-loop / voltage modes; returns (average voltage, limit clipped)."""
        done, u_sum, limited = 0, 0j, False
        if self._enabled:
            done, u_sum, limited = self._run_inverter(n, T_L)
        if done < n:
            # the load while disabled: the dynamometer's torque at the interval's midpoint
            u_sum += self._run_disabled(n - done, self._torque(0.5 * (n + done) - 0.5, T_L))
        return u_sum / n, limited

    def _run_inverter(self, n: int, T_L: float) -> tuple[int, complex, bool]:
        """The inverter's voltage, RK4 with ZOH: with the current loop (``self._loop``) PI +
        feedforward + circular limit + back-calculation anti-windup, else u_s_ref applied,
        circularly limited.

        Returns (steps done before a trip or n, sum of the applied step voltages, clipped).
        The n steps run in this one function on float locals (the real and imaginary parts
        of the complex quantities; the same operations in the same order as the complex
        forms, :func:`plant.motor.rk4_step_full`): no calls, no objects per step.
        """
        h = self._h
        rot, (sa, sb, ha, hb) = self._frame(n)
        sp = self._sp
        loop = self._loop
        trip2 = self._trip2
        na, aM, beta, mu, rs, inv_sigma, inv_J, hh, h6 = self._k
        load = T_L * inv_J
        w, psi, i = self._w, self._psi, self._i
        pa, pb, ia, ib = psi.real, psi.imag, i.real, i.imag
        sum_a = sum_b = 0.0
        done = n
        u_errors = self._u_errors
        varying = self.load is not None
        t0 = self._n * h
        if loop:
            i_ref, u_ff = sp.i_s_ref, sp.u_s_ref
            ref_a, ref_b, ff_a, ff_b = i_ref.real, i_ref.imag, u_ff.real, u_ff.imag
            K_p, K_i_h, h_over_T_i, u_lim, u_lim2 = self._pi
            sqrt = math.sqrt
            ra, rb = rot.real, rot.imag
            x = self._x_ab  # the integrator, to the setpoint frame: x·e^{−jε}
            xa = x.real * ra + x.imag * rb
            xb = x.imag * ra - x.real * rb
            limited = False
            # the sensors' model is skipped when it is exact, as long as nothing else varies
            plain = self._exact_sensors and not u_errors and not varying
            ura = urb = 0.0
        else:
            u = sp.u_s_ref
            u_lim = self._u_lim
            limited = abs(u) > u_lim
            if limited:
                u *= u_lim / abs(u)
            u_rot = u * rot * complex(ha, hb)
            ura, urb = u_rot.real, u_rot.imag
        for k in range(n):
            if loop:
                # the error in the setpoint frame: e = i_ref − i_meas·e^{−jε}
                if plain:
                    ma, mb = ia, ib
                else:
                    m = self._sense(complex(ia, ib))
                    ma, mb = m.real, m.imag
                ea = ref_a - (ma * ra + mb * rb)
                eb = ref_b - (mb * ra - ma * rb)
                ua = ff_a + K_p * ea + xa
                ub = ff_b + K_p * eb + xb
                m2 = ua * ua + ub * ub
                if m2 > u_lim2:
                    limited = True
                    scale = u_lim / sqrt(m2)
                    ua *= scale
                    ub *= scale
                    xa += h_over_T_i * (ua - ff_a - xa)  # back-calculation, T_t = T_i
                    xb += h_over_T_i * (ub - ff_b - xb)
                else:
                    xa += K_i_h * ea
                    xb += K_i_h * eb
                # to (a, b) with the angle of the step's midpoint: u·(e^{jε}·e^{jω0·h/2})
                ta = ra * ha - rb * hb
                tb = ra * hb + rb * ha
                uaa = ua * ta - ub * tb
                uab = ua * tb + ub * ta
            else:
                uaa, uab = ura, urb
            sum_a += uaa
            sum_b += uab
            if u_errors:
                u_app = self._u_error(complex(uaa, uab), complex(ia, ib), t0 + (k + 0.5) * h)
                uaa, uab = u_app.real, u_app.imag
            if varying:
                load = self._torque(k, T_L) * inv_J
            # one classical RK4 step of (1), the voltage held (ZOH)
            ud_a = uaa * inv_sigma
            ud_b = uab * inv_sigma
            # stage 1: dψ_r/dt = (−α + jω)ψ_r + αM·i_s (rows 2–3), di_s/dt = (u_s − R_s·i_s)/σ
            # − β·dψ_r/dt (rows 4–5), dω/dt = μ(ψ_ra·i_sb − ψ_rb·i_sa) − T_L/J (row 1)
            dpa1 = na * pa - w * pb + aM * ia
            dpb1 = na * pb + w * pa + aM * ib
            dia1 = ud_a - rs * ia - beta * dpa1
            dib1 = ud_b - rs * ib - beta * dpb1
            dw1 = mu * (pa * ib - pb * ia) - load
            # stage 2
            w2 = w + hh * dw1
            pa2 = pa + hh * dpa1
            pb2 = pb + hh * dpb1
            ia2 = ia + hh * dia1
            ib2 = ib + hh * dib1
            dpa2 = na * pa2 - w2 * pb2 + aM * ia2
            dpb2 = na * pb2 + w2 * pa2 + aM * ib2
            dia2 = ud_a - rs * ia2 - beta * dpa2
            dib2 = ud_b - rs * ib2 - beta * dpb2
            dw2 = mu * (pa2 * ib2 - pb2 * ia2) - load
            # stage 3
            w3 = w + hh * dw2
            pa3 = pa + hh * dpa2
            pb3 = pb + hh * dpb2
            ia3 = ia + hh * dia2
            ib3 = ib + hh * dib2
            dpa3 = na * pa3 - w3 * pb3 + aM * ia3
            dpb3 = na * pb3 + w3 * pa3 + aM * ib3
            dia3 = ud_a - rs * ia3 - beta * dpa3
            dib3 = ud_b - rs * ib3 - beta * dpb3
            dw3 = mu * (pa3 * ib3 - pb3 * ia3) - load
            # stage 4
            w4 = w + h * dw3
            pa4 = pa + h * dpa3
            pb4 = pb + h * dpb3
            ia4 = ia + h * dia3
            ib4 = ib + h * dib3
            dpa4 = na * pa4 - w4 * pb4 + aM * ia4
            dpb4 = na * pb4 + w4 * pa4 + aM * ib4
            dia4 = ud_a - rs * ia4 - beta * dpa4
            dib4 = ud_b - rs * ib4 - beta * dpb4
            dw4 = mu * (pa4 * ib4 - pb4 * ia4) - load
            w = w + h6 * (dw1 + 2.0 * (dw2 + dw3) + dw4)
            pa = pa + h6 * (dpa1 + 2.0 * (dpa2 + dpa3) + dpa4)
            pb = pb + h6 * (dpb1 + 2.0 * (dpb2 + dpb3) + dpb4)
            ia = ia + h6 * (dia1 + 2.0 * (dia2 + dia3) + dia4)
            ib = ib + h6 * (dib1 + 2.0 * (dib2 + dib3) + dib4)
            if loop:
                ra, rb = ra * sa - rb * sb, ra * sb + rb * sa  # e^{jε} of the next step
            else:
                ura, urb = ura * sa - urb * sb, ura * sb + urb * sa  # u_rot·e^{jω0·h}
            if ia * ia + ib * ib > trip2:
                done = k + 1
                break
        self._w, self._psi, self._i = w, complex(pa, pb), complex(ia, ib)
        if loop:
            self._x_ab = complex(xa * ra - xb * rb, xa * rb + xb * ra)  # x·e^{jε}
        if done < n:
            self._trip()
        return done, complex(sum_a, sum_b), limited

    def _run_disabled(self, n: int, T_L: float) -> complex:
        """Freewheeling diodes until i_s = 0, then open stator; returns Σ u_step (V)."""
        c = self._c
        h = self._h
        u_lim = self.params.u_lim
        self._x_ab = 0j
        w, psi, i = self._w, self._psi, self._i
        u_sum = 0j
        left = n
        while left > 0 and i != 0j:
            mag = abs(i)
            u = -u_lim / mag * i
            w1, psi1, i1 = rk4_step_full(c, w, psi, i, u, T_L, h)
            left -= 1
            along = (i1.real * i.real + i1.imag * i.imag) / mag  # i1 projected on i
            if along > 0.0:
                w, psi, i = w1, psi1, i1
                u_sum += u
                continue
            # the current reaches zero within this step: cut it there, then open stator
            f = mag / (mag - along)
            w, psi, _ = rk4_step_full(c, w, psi, i, u, T_L, f * h)
            i = 0j
            u_sum += f * u
            self._w, self._psi, self._i = w, psi, i
            u_sum += self._open_circuit((1.0 - f) * h, T_L) / h
            w, psi = self._w, self._psi
        self._w, self._psi, self._i = w, psi, i
        if left > 0:
            u_sum += self._open_circuit(left * h, T_L) / h
        return u_sum

    def _open_circuit(self, tau: float, T_L: float) -> complex:
        """i_s = 0 for tau (s), solved exactly; returns ∫u dt = (M/L_r)·Δψ_r (V·s).

        dω/dt = −T_L/J and dψ_r/dt = (−α + jω)ψ_r (rows 1–3 of (1) with i_s = 0).
        """
        c = self._c
        w, psi = self._w, self._psi
        dw = T_L * c.inv_J
        psi_end = psi * cmath.exp(complex(-c.alpha * tau, w * tau - 0.5 * dw * tau * tau))
        self._w = w - dw * tau
        self._psi = psi_end
        return c.M_over_L_r * (psi_end - psi)

    def _measure(self, u_avg: complex, limited: bool, u_dc: float) -> Measurement:
        i = self._i
        psi = self._psi
        # exact sensors: what _sense computes, without the call
        i_meas = self._g * i + self._i_offset if self._exact_sensors else self._sense(i)
        T_e = self._c.M_over_L_r * (psi.real * i.imag - psi.imag * i.real)
        return _measurement(i_meas, u_avg, u_dc, self._w, psi, T_e, limited)
