"""Load-torque observer for the sensorless controller when T_L is not known.

Both laws of the paper use the load torque T_L — (15) and (16) through T_L/J, the
full-order law (25)–(27) and φ_q0 of (32) also through dT_L/dt — and treat it as known
(docs/paper.md §E6). A real drive is not told its load. This module estimates T_L (and dT_L/dt)
from what the sensorless controller has each period: the measured stator currents, the
period's average voltage, the frame angle ε0 and ψ*.

Derivation, from model (1):

* Row 1 (mechanics): J·dω/dt = T_e − T_L with T_e = J·μ·(ψ_ra·i_sb − ψ_rb·i_sa)
  = (M/L_r)·Im(conj(ψ_r)·i_s).
* Rows 2–3 (rotor flux): dψ_r/dt = (−α + jω)·ψ_r + αM·i_s. For the angle θ of ψ_r:
  dθ/dt = ω + αM·Im(conj(ψ_r)·i_s)/|ψ_r|² (the slip relation (11), valid for any flux),
  hence a speed "measurement" independent of the speed observer (16):

      ω_m = dθ/dt − αM·Im(conj(ψ_r)·i_s)/|ψ_r|².

* The flux: the voltage model of (24) (docs/paper.md §E1), integrated by the observer itself,
  Δψ_r = (L_r/M)·(T·ū_s − R_s·∫i_s dt − σ·Δi_s), with ∫i_s dt = T·ī·e^{−jΔθ/2} from the
  period's mean current ī = (1 − ρ)·i_s(t_k) + ρ·i_s(t_{k−1}) (the current is held in the
  rotating frame over the period; ρ is the fraction of the period the drive needs to reach
  a new setpoint: 0 for an ideal current source, ≈ 1/(ω_cl·T) for a current loop of
  bandwidth ω_cl), and a low-frequency correction towards field orientation, ψ_r → ψ*·e^{jε0}
  at ω_c = 2 rad/s, as in the drift-free estimator (Hu & Wu 1998). This matters: the
  controller's estimator (24) uses the trapezoid of the two current samples, which for
  currents held over the period leaves a constant offset δ = R_s·T·Δi/2 in the (a, b) frame
  after every current change (9 mWb after magnetisation in the paper's scenario), and an
  offset makes the flux angle, and ω_m, ripple at the stator frequency by ω·|δ|/|ψ_r|
  (±1.7 rad/s at 100 rad/s) — enough to make the loop below unstable.
* A Luenberger observer of the mechanical row with T_L as a slowly varying state
  (dT_L/dt ≈ 0), predicting the period's mean speed with the period's torque and
  correcting with the output error e = ω_m − ω̂_m:

      ω̂_m ← ω̂_m + T·(T_e − T̂_L)/J + T·l1·e,     T̂_L ← T̂_L − T·J·l2·e,

  l1 = 2p, l2 = p²: with T_L constant the errors obey s² + l1·s + l2 = 0, a double pole at
  −p (``bandwidth``). A load step ΔT is followed with ∫(T_L − T̂_L)dt = (l1/l2)·ΔT = 2ΔT/p,
  so the motor loses about 2ΔT/(p·J) of speed before T̂_L catches up (7.7 rad/s for the
  paper's 5.8 N·m step at p = 200 rad/s) — unless the speed loop sees the dip.
* The speed loop of (15) acts on ω̂ of (16), which with T̂_L in place of T_L does not see a
  dip caused by the load estimate's lag (only through v of (20), at the observer's ~40 rad/s).
  So ω̂ is also pulled towards the load observer's ω̂_m, which follows the true speed:
  dω̂/dt of (16) gets the extra output injection k_s·(ω̂_m − ω̂) (``speed_gain``), the
  same kind of term as v. With it the paper scenario with an unknown load tracks about as
  well as with the load known (BENCHMARKS.md).

**Limitation (measured, BENCHMARKS.md).** With the tuning below the loop meets the issue's
target on an exact plant, but runs away with a 10 mA current-sensor offset, 5 mA of noise,
R_s +10 % or R_r +20 %: a DC offset of the observer's flux (R_s·offset/ω_c, or the current
model's error) makes ω_m ripple at the stator frequency, and the fast loop through T̂_L and
the speed injection amplifies it; at low flux (magnetisation) noise on the flux angle is
amplified as 1/|ψ_r|. Lower gains or a larger ω_c trade one failure for another (p = 150,
k_s = 100, ω_c = 20 rad/s survived the offset and the noise, RMS ≈ 1, but not R_r +20 % and
gave 0.77 on the exact plant). Not done: a robust design (e.g. the load estimated inside the
paper's adaptive observer (16), (20) with a Lyapunov term, or gains scheduled with |ψ_r|).

This is the classical disturbance-torque observer of speed-sensored drives (Lorenz &
Patten, IEEE Trans. IA 27(4), 1991) with the speed taken from the rotor-flux angle, the
voltage-model speed estimate of sensorless drives (e.g. Holtz, "Sensorless control of
induction machines — with or without signal injection?", IEEE Trans. IE 53(1), 2006). It
inherits the weakness of every voltage model: R_s errors and offsets near zero stator
frequency.

Tuning (:func:`tuning`, per drive mode, at 1 ms): the observer closes a fast loop through
the current setpoints (T̂_L feeds (15) forward), so an error in ī — the current the drive
really delivered over the period — feeds straight back. Measured on the paper scenario
(sampled 1 ms, delay 1): ideal current source p = 300 rad/s, k_s = 300 s⁻¹, ρ = 0 (robust
in p and k_s: 250–300 × 200–300 all within 10 %, but ρ = 0.03 already diverges); the PI
current loop (1.5 kHz) p = 120 rad/s, k_s = 80 s⁻¹, ρ = 0.12, inside a narrow stable band
(ρ = 0.05 and ρ = 0.2 diverge, so do p = 150 with k_s = 150): the loop is sensitive to how
well ī describes the current the drive delivered. The full-order law with its voltage
drive did not run stably with any tuning tried (p 100–300, k_s 0–100, ρ 0.5, with and
without dT̂_L/dt in φ_q0): refused.

The controller runs the paper's laws with T̂_L and dT̂_L/dt in place of T_L and dT_L/dt
(:meth:`LoadObserver.refs`) and adds :meth:`LoadObserver.speed_injection` to dω̂/dt: a
few-line hook usable by any discrete controller.

While |ψ_r| is below ``psi_min`` (default 0.05 Wb; magnetisation from ψ*(0) = 0.001 Wb)
the flux angle means nothing: the observer holds T̂_L and starts from ω̂_m = ω_m once the
flux is up. Units: SI.
"""

from __future__ import annotations

import cmath
import math
from dataclasses import dataclass
from typing import Protocol

from gateway.control.laws import Refs


class Motor(Protocol):
    J: float
    M: float
    L_r: float
    R_s: float
    alpha: float
    sigma: float


@dataclass(slots=True)
class RefsWithLoad:
    """The references of one instant with the load replaced by its estimate (a plain
    slotted class: built every period, the frozen form costs twice as much)."""

    w_ref: float
    dw_ref: float
    ddw_ref: float
    psi_ref: float
    dpsi_ref: float
    ddpsi_ref: float
    T_L: float
    dT_L: float


class LoadObserver:
    """Estimates T_L and dT_L/dt once per period (see the module docstring).

    ``LoadObserver(motor, period, bandwidth, speed_gain, current_rise)``; :meth:`update`
    each sample; :attr:`T_L`, :attr:`dT_L`, :attr:`w_m` (the observer's speed, rad/s),
    :attr:`w_meas` (the flux-angle speed of the last period) after it.
    """

    def __init__(self, motor: Motor, period: float, bandwidth: float = 300.0,
                 speed_gain: float = 300.0, current_rise: float = 0.0,
                 psi_min: float = 0.05, w_c: float = 2.0) -> None:
        if not bandwidth > 0.0:
            raise ValueError(f"load observer: bandwidth {bandwidth!r} rad/s must be > 0")
        if not period > 0.0:
            raise ValueError(f"load observer: period {period!r} s must be > 0")
        self._J = motor.J
        self._k_t = motor.M / motor.L_r  # T_e = (M/L_r)·Im(conj(ψ_r)·i_s)
        self._k_r = motor.L_r / motor.M
        self._R_s = motor.R_s
        self._sigma = motor.sigma
        self._aM = motor.alpha * motor.M
        self._T = period
        self.bandwidth = bandwidth
        self._l1 = 2.0 * bandwidth
        self._l2 = bandwidth * bandwidth
        self._psi_min = psi_min
        self.k_s = speed_gain
        self.rho = current_rise
        if not (speed_gain >= 0.0 and 0.0 <= current_rise <= 1.0):
            raise ValueError(f"load observer: speed_gain {speed_gain!r} must be ≥ 0 and "
                             f"current_rise {current_rise!r} in [0, 1]")
        self._decay = math.exp(-w_c * period)
        self.reset()

    def reset(self, T_L: float = 0.0) -> None:
        """Back to T̂_L = ``T_L``, zero flux, no previous sample."""
        self.T_L = T_L
        self.dT_L = 0.0
        self.w_m = 0.0
        self.w_meas = 0.0
        self.psi_r_ab = 0j  # the observer's own rotor-flux estimate
        self._i_prev = 0j  # the drive starts from rest: no current before the first period
        self._psi_prev: complex | None = None
        self._running = False
        self._e = 0.0

    def _flux(self, i_s_ab: complex, u_s_ab: complex, eps_0: float, psi_ref: float) -> complex:
        """The rotor flux after this period (see the module docstring)."""
        T = self._T
        i_0 = self._i_prev
        self._i_prev = i_s_ab
        psi = self.psi_r_ab
        turn = psi * self._psi_prev.conjugate() if self._psi_prev else 0j
        half = 1.0  # e^{jΔθ/2} of the last period: (1 + e^{jΔθ})/|1 + e^{jΔθ}|
        if turn:
            half = 1.0 + turn / abs(turn)
            half = half / abs(half) if half else 1j
        i_mean = self._mean_current(i_0, i_s_ab)
        d_psi_s = T * u_s_ab - self._R_s * T * i_mean / half  # ∫i ≈ T·ī·e^{−jΔθ/2}
        psi_new = psi + self._k_r * (d_psi_s - self._sigma * (i_s_ab - i_0))
        psi_cm = psi_ref * cmath.exp(1j * eps_0)  # field orientation (current model)
        psi_new = psi_cm + self._decay * (psi_new - psi_cm)
        self._psi_prev = psi
        self.psi_r_ab = psi_new
        return psi_new

    def _mean_current(self, i_0: complex, i_1: complex) -> complex:
        """The period's mean current from its end samples: (1 − ρ)·i_k + ρ·i_{k−1}."""
        return i_1 + self.rho * (i_0 - i_1)

    def update(self, i_s_ab: complex, u_s_ab: complex, eps_0: float, psi_ref: float) -> float:
        """One sample at t_k: the measured i_s (A) and the period's average voltage u_s (V),
        (a, b) frame; the controller's frame angle ε0 (rad) and ψ* (Wb). Returns T̂_L."""
        psi_0 = self.psi_r_ab
        i_0 = self._i_prev
        psi = self._flux(i_s_ab, u_s_ab, eps_0, psi_ref)
        i_mean = self._mean_current(i_0, i_s_ab)
        cross = psi.real * i_mean.imag - psi.imag * i_mean.real  # Im(conj(ψ)·ī)
        mag2 = psi.real * psi.real + psi.imag * psi.imag
        if mag2 < self._psi_min * self._psi_min:
            self._running = False
            self.dT_L = 0.0
            self._e = 0.0
            return self.T_L
        T = self._T
        T_e = self._k_t * cross
        w_meas = cmath.phase(psi * psi_0.conjugate()) / T - self._aM * cross / mag2
        self.w_meas = w_meas
        if not self._running:
            self._running = True
            self.w_m = w_meas
            return self.T_L
        # predict this period's mean speed with this period's torque, then correct
        w_pred = self.w_m + T * (T_e - self.T_L) / self._J
        e = w_meas - w_pred
        self._e = e
        self.dT_L = -self._J * self._l2 * e
        self.w_m = w_pred + T * self._l1 * e
        self.T_L += T * self.dT_L
        return self.T_L

    def coast(self, w_0: float, T: float) -> None:
        """A period without measurements: the flux turns with the frame (ω0·T), T̂_L is held
        and the speed observer restarts from the next measured speed."""
        turn = cmath.exp(1j * w_0 * T)
        self.psi_r_ab *= turn
        self._i_prev *= turn  # the drive turns the held current with the frame
        self._psi_prev = None
        self._running = False
        self.dT_L = 0.0

    def speed_injection(self, w_hat: float) -> float:
        """k_s·(ω̂_m − ω̂), rad/s²: the term added to dω̂/dt of (16)/(27) that pulls the
        paper's speed estimate towards the load observer's (0 until the flux is up)."""
        return self.k_s * (self.w_m - w_hat) if self._running else 0.0

    def refs(self, refs: Refs, i_s_ab: complex, u_s_ab: complex,
             eps_0: float) -> RefsWithLoad:
        """``refs`` with T_L, dT_L/dt replaced by the estimates after :meth:`update` — the
        hook for a controller whose load is not known."""
        T_L = self.update(i_s_ab, u_s_ab, eps_0, refs.psi_ref)
        return RefsWithLoad(refs.w_ref, refs.dw_ref, refs.ddw_ref, refs.psi_ref,
                            refs.dpsi_ref, refs.ddpsi_ref, T_L, self.dT_L)


#: (bandwidth p in rad/s, speed_gain k_s in 1/s, current_rise ρ) per drive mode, at 1 ms.
TUNING = {"ideal": (300.0, 300.0, 0.0), "current-loop": (120.0, 80.0, 0.12)}


def tuning(drive_mode: str) -> tuple[float, float, float]:
    """The observer's tuning for a drive mode (see the module docstring); ValueError for a
    drive the observer was not found stable with."""
    try:
        return TUNING[drive_mode]
    except KeyError:
        raise ValueError(
            f"the load observer runs with the current-fed law on an ideal or current-loop "
            f"drive; with a '{drive_mode}' drive it was not found stable: use --load "
            f"known") from None


def load_config(load: str, drive: str) -> dict[str, float]:
    """ControllerConfig's load-observer fields for the drive mode ({} when the load is not
    observed, or on the full-order law's voltage drive: its sampled-data design observes
    the load through the inertia filter, docs/robustness.md §10, with no tuning of this
    observer, and ControllerConfig refuses its other designs); ValueError for a drive mode
    the observer has no tuning for."""
    if load != "observed" or drive == "voltage":
        return {}
    p, k_s, rho = tuning(drive)
    return {"load_bandwidth": p, "load_speed_gain": k_s, "load_current_rise": rho}
