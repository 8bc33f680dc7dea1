"""Checks of every cycle that stop a run before it does harm (pure: no I/O).

* :class:`Plausibility` — the drive's measurements against what the drive can report:
  currents within its peak current, the DC link within its range, everything finite. A
  measurement outside is a sensor or bus fault, not a control problem.
* :class:`Envelope` — the divergence guard: speed, currents, flux, voltages and the
  speed estimate against the reference profile's demand plus a margin. A loop outside has
  lost control (e.g. a real-time run that missed too many cycles), whatever the drive says.
  It also watches field orientation, which needs no speed sensor: the controller's flux
  estimate must point along its frame's d axis. Beyond ``angle_max`` the frame has lost the
  flux — typically a load torque the laws are not told, larger than they tolerate; then the
  speed estimate can still read ω* while the motor stalls (docs/robustness.md §2).

Both return None when the cycle is fine, else a one-line reason.
:class:`DivergenceWatch` turns the envelope into a stop: crossed in ``cycles`` cycles in a
row (the bus loop and ``hil-gateway simulate`` both use it).
"""

from __future__ import annotations

import math
from collections.abc import Mapping
from dataclasses import dataclass, replace
from typing import Any

import numpy as np

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
        i = math.hypot(measured.get("i_sa", 0.0), measured.get("i_sb", 0.0))
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


#: Field orientation is lost when the controller's flux estimate in its own frame has turned
#: more than this from the d axis (degrees) or collapsed below this fraction of ψ* (3 cycles).
#: Measured blind (no truth) on 216 robustness runs (1 ms; both designs; open-loop,
#: drift-free, rs-adaptive and true flux; paper, zero-speed and slow-reversal profiles; nine
#: plants): no run that stayed within 20 rad/s of ω* was stopped by it; most runaways were,
#: often before their speed error reached 20 rad/s; so are motors lost to an untold load
#: (docs/robustness.md §2).
ORIENTATION_LIMIT = 90.0
FLUX_COLLAPSE = 0.2
#: A slower loss (an untold load in field weakening) keeps the estimate near the d axis while
#: the flux fades: a flux estimate below this fraction of ψ* for FLUX_DEFICIT_TIME seconds
#: stops the run too. Longest such deficit in a run that stayed within 20 rad/s of ω*:
#: 0.28 s (drift-free estimator, slow reversal, real-drive plant); 1 N·m untold at 200 rad/s
#: and 0.5 Wb: 0.67 s, with the motor 90 rad/s slow.
FLUX_DEFICIT = 0.5
FLUX_DEFICIT_TIME = 0.5


@dataclass(frozen=True)
class Envelope:
    """The bounds of a run that is under control, from the profile's demand.

    w_max: |ω̂| and |ω|, rad/s. i_max: |i_s|, A. psi_max: |ψ̂_r|, Wb. u_max: |u_s|, V.
    e_max: |ω̂ − ω*| (always) and |ω̂ − ω| (with the emulator's truth), rad/s.
    angle_max: |∠(ψ̂_rd + jψ̂_rq)|, the flux estimate's angle from the frame's d axis, degrees;
    psi_min: |ψ̂_r|/ψ*, its least magnitude; both checked once ψ* ≥ psi_on (Wb: early in
    the magnetisation the estimate is too small to have a meaningful angle). deficit,
    deficit_time: |ψ̂_r|/ψ* below ``deficit`` for ``deficit_time`` s (:meth:`flux_deficit`;
    :class:`DivergenceWatch` times it).
    """

    w_max: float
    i_max: float
    psi_max: float
    u_max: float
    e_max: float
    psi_on: float = math.inf
    angle_max: float = ORIENTATION_LIMIT
    psi_min: float = FLUX_COLLAPSE
    deficit: float = FLUX_DEFICIT
    deficit_time: float = FLUX_DEFICIT_TIME

    @classmethod
    def from_demand(cls, w_peak: float, i_peak: float, psi_peak: float, u_peak: float,
                    i_limit: float = 0.0) -> Envelope:
        """Margins: speed 1.5× + 50 rad/s; speed error 20 rad/s + 10 % of the peak speed;
        flux 1.5× + 0.2 Wb; current 1.5× + 5 A, and at least 1.25× the controller's current
        limit ``i_limit`` + 1 A (its setpoints never exceed the limit); voltage 2× + 100 V
        (a coasting cycle's current step makes short voltage peaks). Wide enough for sampled
        runs with delay, missed cycles and parameter errors, narrow enough to stop a loop
        that lost the motor within a few cycles. Orientation is checked from ψ* ≥ 25 % of
        the peak flux."""
        return cls(w_max=1.5 * w_peak + 50.0, i_max=max(1.5 * i_peak + 5.0,
                                                        1.25 * i_limit + 1.0),
                   psi_max=1.5 * psi_peak + 0.2, u_max=2.0 * u_peak + 100.0,
                   e_max=20.0 + 0.1 * w_peak, psi_on=0.25 * psi_peak)

    def for_controller(self, controller: Any) -> Envelope:
        """The envelope for ``controller``: a test that moves the rotor within its own speed
        limit (its ``speed_limit``, rad/s: the rotating commissioning) instead of following
        the profile's speed has |ω| bounded by 1.5× that limit + 50 rad/s and no speed-error
        bound (the test stops its torque itself past its limit); any other controller, this
        envelope."""
        limit = getattr(controller, "speed_limit", None)
        if limit is None:
            return self
        return replace(self, w_max=max(self.w_max, 1.5 * float(limit) + 50.0), e_max=math.inf)

    def check(self, r: Any) -> str | None:
        """None, or which bound a cycle's row (:func:`gateway.cycle.row_type`) crossed. The
        estimate checks apply to the controllers that log an estimate (``w_hat``,
        ``psi_r_mod_hat``, ``psi_rd_hat``/``psi_rq_hat``: the paper's); the truth's where
        the drive sends it."""
        w_ref, w_m = r.w_ref, r.w_m
        w_hat = getattr(r, "w_hat", None)
        psi_hat = getattr(r, "psi_r_mod_hat", None)
        # a standard drive may send no currents or voltages (NaN in the row): not checked
        checks: list[tuple[str, float, float, str]] = [
            (what, value, bound, unit) for what, value, bound, unit in (
                ("stator current |i_s|", math.hypot(r.i_sa, r.i_sb), self.i_max, "A"),
                ("stator voltage |u_s|", math.hypot(r.u_sa, r.u_sb), self.u_max, "V"))
            if not math.isnan(value)]
        if w_hat is not None:
            checks[:0] = [("speed estimate |ω̂|", abs(w_hat), self.w_max, "rad/s"),
                          ("speed error |ω̂ − ω*|", abs(w_hat - w_ref), self.e_max, "rad/s")]
        if psi_hat is not None:
            checks.append(("flux estimate |ψ̂_r|", psi_hat, self.psi_max, "Wb"))
        if math.isfinite(w_m):
            checks.append(("speed |ω|", abs(w_m), self.w_max, "rad/s"))
            if w_hat is not None:
                checks.append(("estimation error |ω̂ − ω|", abs(w_hat - w_m), self.e_max,
                               "rad/s"))
            else:
                checks.append(("speed error |ω − ω*|", abs(w_m - w_ref), self.e_max, "rad/s"))
        for what, value, bound, unit in checks:
            if not value <= bound:  # NaN too
                return f"{what} = {value:.4g} {unit} beyond {bound:.4g} {unit}"
        psi_dq = (getattr(r, "psi_rd_hat", None), getattr(r, "psi_rq_hat", None))
        if r.psi_ref >= self.psi_on and psi_hat is not None and None not in psi_dq:
            angle = math.degrees(math.atan2(psi_dq[1], psi_dq[0]))
            if not (abs(angle) <= self.angle_max and psi_hat >= self.psi_min * r.psi_ref):
                return (f"field orientation lost: the flux estimate is {psi_hat:.3g} "
                        f"Wb at {angle:+.0f}° from the frame's d axis, for ψ* = "
                        f"{r.psi_ref:.3g} Wb (limits ±{self.angle_max:g}°, "
                        f"{self.psi_min:g}·ψ*). The speed estimate cannot be trusted: the "
                        f"usual cause is a load torque the laws are not told (the profile's "
                        f"T_L is {r.T_L:.3g} N·m), else a stator-resistance or current-sensor "
                        f"error at low speed (--estimator rs-adaptive)")
        return None

    def flux_deficit(self, r: Any) -> bool:
        """Whether the flux estimate (where the controller logs one) is below
        ``deficit``·ψ* (once ψ* ≥ psi_on)."""
        psi_hat = getattr(r, "psi_r_mod_hat", None)
        return (psi_hat is not None and r.psi_ref >= self.psi_on
                and not psi_hat >= self.deficit * r.psi_ref)


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
    ``cycles`` cycles in a row, or its flux estimate below the envelope's ``deficit``·ψ* for
    ``deficit_time`` seconds."""

    def __init__(self, envelope: Envelope, cycles: int = 3) -> None:
        if cycles < 1:
            raise ValueError(f"divergence watch: cycles = {cycles!r} must be >= 1")
        self.envelope = envelope
        self.cycles = cycles
        self.outside = 0  # consecutive cycles outside the envelope
        self.reason: str | None = None
        self._start: tuple[float, float] | None = None  # (ω, ω*) of the first row with truth
        self._deficit_since: float | None = None  # t of the first row of a flux deficit

    def check(self, row: Any, k: int) -> bool:
        """Whether cycle ``k`` (its row ``row``) ends the run."""
        if self._start is None and math.isfinite(row.w_m):
            self._start = (row.w_m, row.w_ref)
        why = self.envelope.check(row)
        env = self.envelope
        if not env.flux_deficit(row):
            self._deficit_since = None
        elif self._deficit_since is None:
            self._deficit_since = row.t
        elif not why and row.t - self._deficit_since >= env.deficit_time - 1e-9:
            self.reason = (f"cycle {k} (t = {row.t:.4f} s): flux estimate below "
                           f"{env.deficit:g}·ψ* since t = {self._deficit_since:.4f} s "
                           f"(|ψ̂_r| = {row.psi_r_mod_hat:.3g} Wb, ψ* = {row.psi_ref:.3g} Wb): "
                           f"the drive is not building the flux the controller asks — the "
                           f"frame has lost it (usually a load torque the laws are not told; "
                           f"the profile's T_L is {row.T_L:.3g} N·m) or the drive is at its "
                           f"current or voltage limit")
            return True
        self.outside = self.outside + 1 if why else 0
        if why and self.outside >= self.cycles:
            self.reason = f"cycle {k} (t = {row.t:.4f} s): {why}, {self.outside} cycles in a row"
            if self._start is not None and abs(self._start[0] - self._start[1]) > START_SPEED:
                self.reason += (f"; the motor was already turning at {self._start[0]:.4g} rad/s "
                                "when the run started (the controller starts its estimates "
                                "from rest): let it come to a stop first")
            return True
        return False
