"""Checks of every cycle that stop a run before it does harm (pure: no I/O).

* :class:`Plausibility` — the drive's measurements against what the drive can report:
  currents within its peak current, the DC link within its range, everything finite. A
  measurement outside is a sensor or bus fault, not a control problem.
* :class:`Envelope` — the divergence guard: speed, currents, flux, voltages and the
  speed estimate against the reference profile's demand plus a margin. A loop outside has
  lost control (e.g. a real-time run that missed too many cycles), whatever the drive says.

Both return None when the cycle is fine, else a one-line reason.
"""

from __future__ import annotations

import math
from collections.abc import Mapping
from dataclasses import dataclass

from gateway.cycle import CycleRow


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
