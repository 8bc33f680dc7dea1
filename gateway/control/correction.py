"""The commissioning's sensor and inverter corrections, applied around any vector controller
(docs/robustness.md §7).

`hil-gateway identify` measures, besides model (1)'s parameters, what a real drive adds to
it (gateway/control/identify.py, the motor file's ``[commissioning]`` table): each phase
sensor reads

    r_a = i_a + o_a,        r_b = g_b·i_b + o_b                                     (C1)

(phase b's gain relative to phase a's, the offsets o_a, o_b in A), and the inverter applies
less than it reports by its dead-time voltage D along the signs of the phase currents,

    u_applied = u_reported − D·g(i),                                                (C2)

g the amplitude-invariant Clarke transform of the three phase currents' signs
(:func:`gateway.control.identify.dead_time_direction`). The drive regulates the current it
*reads*: with a current setpoint i* the true current is the inverse of (C1) at i*, a
current error the paper's laws do not know (an offset makes a torque ripple at the stator
frequency and, integrated by the voltage model (24), a flux drift: the "offset" rows of
README's robustness table).

:class:`CorrectedController` puts the inverse of each error around the controller. In: the
sample's current through the inverse of (C1), its voltage through (C2) at that current.
Out: the current setpoint through (C1) (what the drive must read for the true current to be
the controller's), the voltage setpoint plus D·g(i*). A constant (a, b) correction
in a (d, q) setpoint that turns at ω0 over the interval is exact at the interval's midpoint
(the angle the (a, b) setpoints take; an error of ω0·T/2 in angle at the ends, 0.05 rad at
100 rad/s and 1 ms, on a correction of a few mA).

Pure module: no I/O, no clock, no global state.
"""

from __future__ import annotations

import cmath
import math
from collections import deque
from collections.abc import Callable
from dataclasses import dataclass, replace
from typing import Any, NamedTuple

from gateway.control.interface import Command, DriveController, Sample
from gateway.control.laws import Refs

SQRT3 = math.sqrt(3.0)
_A = cmath.exp(2j * math.pi / 3)


@dataclass(frozen=True)
class SensorCorrection:
    """What commissioning measured besides model (1) (the motor file's ``[commissioning]``).

    offset_a, offset_b: the phase current sensors' offsets, A (added to the reading);
    gain_b: phase b's reading gain relative to phase a's; u_dead: the inverter's voltage
    error along a phase current's sign, V (dead time: dead_time·f_pwm·u_dc), (C1), (C2).
    """

    offset_a: float = 0.0
    offset_b: float = 0.0
    gain_b: float = 1.0
    u_dead: float = 0.0

    #: the keys of the motor file's [commissioning] table this takes
    KEYS = ("offset_a", "offset_b", "gain_b", "u_dead")

    def __post_init__(self) -> None:
        for name in self.KEYS:
            v = getattr(self, name)
            if isinstance(v, bool) or not isinstance(v, int | float) or not math.isfinite(v):
                raise ValueError(f"{name} = {v!r} must be a finite number")
        if not 0.5 <= self.gain_b <= 2.0:
            raise ValueError(f"gain_b = {self.gain_b!r} must be within 0.5…2 (phase b's "
                             "reading gain relative to phase a's)")

    #: a value within this many of its standard deviations (``<key>_std`` in the table) of
    #: no error is the test's noise, not the drive's error: not corrected
    SIGNIFICANT = 3.0

    @classmethod
    def from_table(cls, table: dict[str, Any]) -> SensorCorrection | None:
        """From a ``[commissioning]`` table (other keys ignored: what the test recorded
        besides); None when it has none of :attr:`KEYS`. A value with its standard
        deviation (``offset_a_std``, ...) within :attr:`SIGNIFICANT` of them of no error
        (0, or 1 for the gain) is taken as no error: correcting the test's noise costs
        precision (0.04 rad/s RMS per 0.1 mA of offset on the paper's profile)."""
        if not any(k in table for k in cls.KEYS):
            return None
        values = {}
        for k in cls.KEYS:
            if k not in table:
                continue
            v, std = table[k], table.get(f"{k}_std")
            none = 1.0 if k == "gain_b" else 0.0
            if (isinstance(v, int | float) and isinstance(std, int | float)
                    and not isinstance(std, bool) and abs(v - none) <= cls.SIGNIFICANT * std):
                v = none
            values[k] = v
        return cls(**values)

    @property
    def offset_ab(self) -> complex:
        """The offsets' image in the (a, b) frame: (o_a, (o_a + 2·o_b)/√3), A."""
        return _clarke(self.offset_a, self.offset_b)

    def true_current(self, i_read_ab: complex) -> complex:
        """The inverse of (C1): the true current (a, b) for the reading ``i_read_ab``, A."""
        r_a, r_b = phases(i_read_ab)
        return _clarke(r_a - self.offset_a, (r_b - self.offset_b) / self.gain_b)

    def reading(self, i_ab: complex) -> complex:
        """(C1): what the sensors read for the true current ``i_ab`` (a, b), A."""
        i_a, i_b = phases(i_ab)
        return _clarke(i_a + self.offset_a, self.gain_b * i_b + self.offset_b)

    def voltage_error(self, i_ab: complex) -> complex:
        """D·g(i) of (C2): what the inverter applies less than it reports at ``i_ab``, V."""
        if self.u_dead == 0.0:
            return 0j
        i_a, i_b = phases(i_ab)
        s_a, s_b = _sign(i_a), _sign(i_b)
        s_c = _sign(-i_a - i_b)
        return self.u_dead * (2.0 / 3.0) * (s_a + s_b * _A + s_c * _A.conjugate())

    def voltage_error_over(self, i0_ab: complex, i1_ab: complex) -> complex:
        """(C2) averaged over an interval whose current moves linearly from ``i0_ab`` to
        ``i1_ab`` (a, b): a phase whose current changes sign within it has its error
        for the share of the interval on either side, V."""
        if self.u_dead == 0.0:
            return 0j
        a0, b0 = phases(i0_ab)
        a1, b1 = phases(i1_ab)
        s_a, s_b = _mean_sign(a0, a1), _mean_sign(b0, b1)
        s_c = _mean_sign(-a0 - b0, -a1 - b1)
        return self.u_dead * (2.0 / 3.0) * (s_a + s_b * _A + s_c * _A.conjugate())


def _mean_sign(x0: float, x1: float) -> float:
    """The mean of sign(x) over an interval where x moves linearly from ``x0`` to ``x1``."""
    s0, s1 = _sign(x0), _sign(x1)
    if s0 == s1 or s0 == 0.0 or s1 == 0.0:
        # one end at zero: x has the other end's sign over the whole interval
        return s0 or s1
    tau = x0 / (x0 - x1)  # the crossing, as a share of the interval
    return s0 * (2.0 * tau - 1.0)


def phases(x_ab: Any) -> tuple[Any, Any]:
    """Phases a and b of an (a, b) vector, or of an array of them (the inverse
    amplitude-invariant Clarke transform)."""
    return x_ab.real, -0.5 * x_ab.real + 0.5 * SQRT3 * x_ab.imag


def _clarke(x_a: float, x_b: float) -> complex:
    """The (a, b) vector of phases a and b (c = −a − b): (x_a, (x_a + 2·x_b)/√3)."""
    return complex(x_a, (x_a + 2.0 * x_b) / SQRT3)


def _sign(x: float) -> float:
    return float((x > 0.0) - (x < 0.0))


class _Commanded(NamedTuple):
    """A commanded interval, for the sample that ends it: ``phi`` the turn of its (d, q)
    setpoints at its end past the midpoint (ω0·T/2), ``w_0`` its ω0, ``du`` the inverter's
    error (C2) its command was corrected for, V (a, b) (None: not known, held setpoints)."""

    phi: float = 0.0
    w_0: float = 0.0
    du: complex | None = None


class CorrectedController:
    """``inner`` with the corrections of :class:`SensorCorrection` around it (module
    docstring): it sees true currents and applied voltages, and its setpoints reach the
    motor as it meant them. Everything else (signals, withhold, coast, the inner
    controller's attributes) is the inner controller's.

    A (d, q) setpoint (``turning``) carries the offset's correction at the interval's midpoint
    angle: at the interval's end (the next sample) the drive regulates a correction turned
    by φ = ω0·T/2 past it, so the true current there differs from the controller's meaning
    by o·(e^{jφ} − 1) (zero on the interval's mean). The sample is corrected with the
    offset so turned, o·e^{jφ}: the controller sees the current its model of the interval
    has there, and no bias of R_s·o·jφ enters its voltage model (measured: 0.018 rad/s RMS
    on the paper's profile with a 10 mA offset, 0.003 with the turn).
    """

    def __init__(self, inner: DriveController, correction: SensorCorrection,
                 period: float, delay: int = 1, turning: bool = True) -> None:
        self.inner = inner
        self.correction = correction
        self.signals = inner.signals
        self._T = period
        self._turning = turning  # (d, q) setpoints: the drive turns them over the interval
        # each commanded interval not yet sampled, oldest first: the sample at t_k ends the
        # interval commanded d + 1 steps before
        self._turns: deque[_Commanded] = deque([_Commanded()] * (delay + 1))
        self._sampled = _Commanded()  # the interval that ended at the last sample
        #: the true current at the last sample (None before the first, and after a lost
        #: sample: the interval after it was not sampled at both ends)
        self._i_last: complex | None = None

    def __getattr__(self, name: str) -> Any:  # the inner controller's other attributes
        if name == "inner":  # not yet set (copy, pickle): no recursion
            raise AttributeError(name)
        return getattr(self.inner, name)

    def step(self, refs: Refs, sample: Sample) -> Command:
        c = self.correction
        self._sampled = ended = self._turns.popleft()
        phi = ended.phi
        i_read = sample.i_s_ab
        if phi:
            i_read -= c.offset_ab * (cmath.exp(1j * phi) - 1.0)
        i_true = c.true_current(i_read)
        # the inverter's error over the interval that ended, (C2′): along the currents
        # sampled at its two ends where both were (on a voltage drive the current is not
        # the one the law asked for, and near a phase's zero the error's sign is the
        # current's that flowed, docs/robustness.md §12); else the one its command was
        # corrected for (_command), where that command was sent
        i_last, self._i_last = self._i_last, i_true
        du = c.voltage_error_over(i_last, i_true) if i_last is not None else ended.du
        u_applied = sample.u_s_ab - (c.voltage_error(i_true) if du is None else du)
        cmd = self.inner.step(refs, replace(sample, i_s_ab=i_true, u_s_ab=u_applied))
        return self._command(cmd)

    def _command(self, cmd: Command) -> Command:
        """The inner controller's command with the corrections: what the drive must read,
        and apply, for the motor to get what the controller meant."""
        c = self.correction
        half = 0.5 * self._T * cmd.w_0
        # the setpoints' (a, b) image at the interval's midpoint, and its change
        turn = cmath.exp(1j * (cmd.eps_0 + half))
        i_ab = cmd.i_s_dq_ref * turn
        di = c.reading(i_ab) - i_ab
        # (C2) over the interval, whose current turns with the frame from ε0 to ε0 + ω0·T:
        # a phase current that changes sign within it has its error for the share of the
        # interval on either side (at its midpoint's sign alone the error was wrong by
        # 2·u_dead in that phase for half the interval on average, in 40 % of the
        # intervals at the paper's top speed)
        start = cmd.i_s_dq_ref * cmath.exp(1j * cmd.eps_0)
        du = c.voltage_error_over(start, start * cmath.exp(2j * half))
        di_ab = c.reading(cmd.i_s_ab_ref) - cmd.i_s_ab_ref
        du_ab = c.voltage_error(cmd.i_s_ab_ref)
        self._turn(cmd, du if self._turning else du_ab)
        return replace(cmd, i_s_dq_ref=cmd.i_s_dq_ref + di / turn,
                       u_s_dq_ref=cmd.u_s_dq_ref + du / turn,
                       i_s_ab_ref=cmd.i_s_ab_ref + di_ab, u_s_ab_ref=cmd.u_s_ab_ref + du_ab)

    def _turn(self, cmd: Command, du: complex | None = None) -> None:
        """Records the interval ``cmd`` commands (its turn at the end, its ω0, the error
        ``du`` its command was corrected for) for the sample that ends it."""
        self._turns.append(_Commanded(0.5 * self._T * cmd.w_0, cmd.w_0, du) if self._turning
                           else _Commanded(du=du))

    def _held(self) -> _Commanded:
        """The interval after the last one commanded, on held setpoints: the drive keeps
        turning their frame, one period further (its error not known)."""
        last = self._turns[-1] if self._turns else self._sampled
        return _Commanded(last.phi + self._T * last.w_0, last.w_0)

    def withhold(self) -> None:
        self._withhold_turn()
        self.inner.withhold()

    def coast(self) -> None:
        self._coast_turn()
        self.inner.coast()

    def _withhold_turn(self) -> None:
        self._turns.pop()  # not sent: the drive held the interval before's setpoints
        self._turns.append(self._held())

    def _coast_turn(self) -> None:
        self._i_last = None
        self._turns.append(self._held())
        self._sampled = self._turns.popleft()  # the interval that ended unsampled

    @property
    def delayed(self) -> Callable[[int], None] | None:
        """``delayed(n)`` where the inner controller has it (see
        :meth:`gateway.control.sampled.SampledController.delayed`): the last command
        withheld, ``n`` cycles coasted, and the interval after them that command's turn."""
        inner = getattr(self.inner, "delayed", None)
        if inner is None:
            return None

        def delayed(n: int) -> None:
            sent = self._turns[-1]
            self._withhold_turn()
            for _ in range(n):
                self._coast_turn()
            self._turns[-1] = sent
            inner(n)

        return delayed


class IdentifiedCorrection(CorrectedController):
    """The current sensors' offsets that ``inner``'s standstill identification found
    (:meth:`gateway.control.commissioning.Commissioning.step`: fitted with R_s and α during
    the magnetisation), corrected as :class:`CorrectedController` does from the sample
    that ends it; before it, and when the identification applies none, the samples and
    commands pass unchanged. ``inner`` has a ``commissioning`` (the paper's controller with
    ``identify``)."""

    def __init__(self, inner: DriveController, period: float, delay: int = 1,
                 turning: bool = True) -> None:
        super().__init__(inner, SensorCorrection(), period, delay, turning)
        self._waiting = True  # for the identification's result
        self._none = False  # it came and corrects nothing: the samples pass unchanged

    def step(self, refs: Refs, sample: Sample) -> Command:
        if not self._waiting:
            if self._none:
                return self.inner.step(refs, sample)
            return super().step(refs, sample)
        self._sampled = self._turns.popleft()
        cmd = self.inner.step(refs, sample)
        found = self.inner.commissioning.result
        if found is None:
            self._turn(cmd)
            return cmd
        self._waiting = False
        correction = self.inner.commissioning.correction
        if correction is None:
            self._none = True
            return cmd
        self.correction = correction
        self._none = correction == SensorCorrection()
        return self._command(cmd)
