"""Checks of every cycle that stop a run before it does harm (pure: no I/O).

* :class:`Plausibility` — the drive's measurements against what the drive can report:
  currents within its peak current, the DC link within its range, everything finite. A
  measurement outside is a sensor or bus fault, not a control problem.
* :class:`Envelope` — the divergence guard: speed, currents, flux, voltages and the
  speed estimate against the reference profile's demand plus a margin. A loop outside has
  lost control (e.g. a real-time run that missed too many cycles), whatever the drive says.

Both return None when the cycle is fine, else a one-line reason.
:class:`DivergenceWatch` turns the envelope into a stop: crossed in ``cycles`` cycles in a
row (the bus loop and ``hil-gateway simulate`` both use it).
"""

from __future__ import annotations

import math
from collections.abc import Mapping
from dataclasses import dataclass

import numpy as np

from gateway.cycle import CycleRow
from gateway.reference import Profile
from gateway.reference.demand import MotorLike, demand


@dataclass(frozen=True)
class Plausibility:
    """i_peak: the largest stator-current magnitude the drive may report, A.
    u_dc_min, u_dc_max: the DC-link range, V (None: only > 0 is required)."""

    i_peak: float
    u_dc_min: float | None = None
    u_dc_max: float | None = None

    def check(self, measured: Mapping[str, float]) -> str | None:
        """None, or what is implausible in the drive's decoded role values."""
        for name, v in measured.items():
            if not math.isfinite(v):
                return f"{name} = {v} is not a number"
        i = math.hypot(measured["i_sa"], measured["i_sb"])
        if i > self.i_peak:
            return (f"|i_s| = {i:.3f} A (i_sa {measured['i_sa']:.3f}, i_sb "
                    f"{measured['i_sb']:.3f}) beyond the drive's peak current {self.i_peak:g} A")
        u_dc = measured.get("u_dc")
        if u_dc is not None:
            lo = self.u_dc_min if self.u_dc_min is not None else 0.0
            hi = self.u_dc_max if self.u_dc_max is not None else math.inf
            if not lo < u_dc <= hi or u_dc <= 0.0:
                return (f"DC link u_dc = {u_dc:.1f} V outside the drive's range "
                        f"{lo:g}..{hi:g} V")
        return None


@dataclass(frozen=True)
class Envelope:
    """The bounds of a run that is under control, from the profile's demand.

    w_max: |ω̂| and |ω|, rad/s. i_max: |i_s|, A. psi_max: |ψ̂_r|, Wb. u_max: |u_s|, V.
    e_max: |ω̂ − ω*| (always) and |ω̂ − ω| (with the emulator's truth), rad/s.
    """

    w_max: float
    i_max: float
    psi_max: float
    u_max: float
    e_max: float

    @classmethod
    def from_demand(cls, w_peak: float, i_peak: float, psi_peak: float, u_peak: float,
                    i_limit: float = 0.0) -> Envelope:
        """Margins: speed 1.5× + 50 rad/s; speed error 20 rad/s + 10 % of the peak speed;
        flux 1.5× + 0.2 Wb; current 1.5× + 5 A, and at least 1.25× the controller's current
        limit ``i_limit`` + 1 A (its setpoints never exceed the limit); voltage 2× + 100 V
        (a coasting cycle's current step makes short voltage peaks). Wide enough for sampled
        runs with delay, missed cycles and parameter errors, narrow enough to stop a loop
        that lost the motor within a few cycles."""
        return cls(w_max=1.5 * w_peak + 50.0, i_max=max(1.5 * i_peak + 5.0,
                                                        1.25 * i_limit + 1.0),
                   psi_max=1.5 * psi_peak + 0.2, u_max=2.0 * u_peak + 100.0,
                   e_max=20.0 + 0.1 * w_peak)

    def check(self, r: CycleRow) -> str | None:
        """None, or which bound a cycle's row crossed."""
        w_hat, w_ref, w_m = r.w_hat, r.w_ref, r.w_m
        checks: tuple[tuple[str, float, float, str], ...] = (
            ("speed estimate |ω̂|", abs(w_hat), self.w_max, "rad/s"),
            ("speed error |ω̂ − ω*|", abs(w_hat - w_ref), self.e_max, "rad/s"),
            ("stator current |i_s|", math.hypot(r.i_sa, r.i_sb), self.i_max, "A"),
            ("stator voltage |u_s|", math.hypot(r.u_sa, r.u_sb), self.u_max, "V"),
            ("flux estimate |ψ̂_r|", r.psi_r_mod_hat, self.psi_max, "Wb"),
        )
        if math.isfinite(w_m):
            checks += (("speed |ω|", abs(w_m), self.w_max, "rad/s"),
                       ("estimation error |ω̂ − ω|", abs(w_hat - w_m), self.e_max, "rad/s"))
        for what, value, bound, unit in checks:
            if not value <= bound:  # NaN too
                return f"{what} = {value:.4g} {unit} beyond {bound:.4g} {unit}"
        return None


def profile_envelope(profile: Profile, motor: MotorLike, i_limit: float) -> Envelope:
    """The envelope of what ``profile`` asks of ``motor`` (:func:`demand`; the flux peak from
    the profile itself) with the controller's current limit ``i_limit``, A."""
    d = demand(profile, motor)
    psi_peak = float(np.max(profile.sample(np.linspace(0.0, profile.duration, 2001))["psi_ref"]))
    return Envelope.from_demand(d.w_peak, d.i_s_peak, psi_peak, d.u_s_peak, i_limit)


#: A speed this far from ω* in the first recorded cycle (rad/s) means the motor was turning
#: before the run: the divergence reason then says so.
START_SPEED = 5.0


class DivergenceWatch:
    """The divergence stop: :meth:`check` each cycle's row; True (and :attr:`reason` says
    which bound, when and for how long) once the row has been outside ``envelope`` in
    ``cycles`` cycles in a row."""

    def __init__(self, envelope: Envelope, cycles: int = 3) -> None:
        if cycles < 1:
            raise ValueError(f"divergence watch: cycles = {cycles!r} must be >= 1")
        self.envelope = envelope
        self.cycles = cycles
        self.outside = 0  # consecutive cycles outside the envelope
        self.reason: str | None = None
        self._start: tuple[float, float] | None = None  # (ω, ω*) of the first row with truth

    def check(self, row: CycleRow, k: int) -> bool:
        """Whether cycle ``k`` (its row ``row``) ends the run."""
        if self._start is None and math.isfinite(row.w_m):
            self._start = (row.w_m, row.w_ref)
        why = self.envelope.check(row)
        self.outside = self.outside + 1 if why else 0
        if why and self.outside >= self.cycles:
            self.reason = f"cycle {k} (t = {row.t:.4f} s): {why}, {self.outside} cycles in a row"
            if self._start is not None and abs(self._start[0] - self._start[1]) > START_SPEED:
                self.reason += (f"; the motor was already turning at {self._start[0]:.4g} rad/s "
                                "when the run started (the controller starts its estimates "
                                "from rest): let it come to a stop first")
            return True
        return False
