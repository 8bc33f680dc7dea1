"""One control cycle at the role level: the single cycle body of `simulate` and the bus loop.

Data flows one way: the role values the drive sent (decoded from its TPDOs by
:class:`gateway.process_data.ProcessData`) → :class:`gateway.control.controller.Sample` →
controller step → :class:`gateway.control.controller.Command` → the role values for the
RPDOs, plus one named record row. :class:`ControlCycle` is used by
:func:`gateway.simulate.run_sampled` and by :class:`gateway.loop.CycleLoop` alike, with the
same quantisation, so a lockstep run over the bus equals the simulation to the last bit.
Roles are the signal names of ``dbc/drive.dbc`` (:mod:`dbc.signals`).
"""

from __future__ import annotations

import functools
import math
from collections.abc import Mapping
from dataclasses import dataclass
from typing import Any, NamedTuple, Protocol

from dbc.cia402 import SW_INTERNAL_LIMIT, Controlword
from dbc.modes import SetpointFrame
from dbc.signals import SETPOINTS
from dbc.timing import Sampling
from gateway.control.controller import PAPER_SIGNALS
from gateway.control.interface import Command, DriveController, Sample
from gateway.control.laws import Refs


class ReferenceProfile(Protocol):
    """What the cycle needs of a reference profile: the references at a time."""

    def at(self, t: float) -> Refs: ...


#: The cycle's own columns of ``signals.csv``, whatever the controller (SI units; docs in
#: docs/outputs.md). t: sample time t_k, s. w_ref, psi_ref, T_L: references at t_k. w_m,
#: psi_r_mod, T_e: the drive's truth (emulator only; NaN otherwise). i_sa, i_sb, u_sa, u_sb:
#: measured currents and average applied voltages. i_sd_ref … u_sq_ref: setpoints sent.
#: eps_0, w_0: the frame sent. i_limited, u_limit_active: 1.0 when the controller's current
#: limit / the drive's voltage limit acted. The controller's own signals follow
#: (:attr:`gateway.control.interface.DriveController.signals`).
CYCLE_COLUMNS = ("t", "w_ref", "psi_ref", "T_L", "w_m", "psi_r_mod", "i_sa", "i_sb", "u_sa",
                 "u_sb", "i_sd_ref", "i_sq_ref", "u_sd_ref", "u_sq_ref", "eps_0", "w_0", "T_e",
                 "i_limited", "u_limit_active")


#: The bus loop's columns after the controller's (:mod:`gateway.loop`): the drive's
#: statusword and SYNC-counter echo; SYNC period, SYNC → last TPDO and last TPDO → RPDOs sent
#: (reaction), s; missed cycles so far; 1.0 when the cycle's setpoints were withheld.
BUS_COLUMNS = ("statusword", "sync_counter", "sync_period", "sync_to_tpdo", "reaction",
               "missed", "withheld", "faults")


@functools.cache
def row_type(signals: tuple[str, ...], extra: tuple[str, ...] = ()) -> type[Any]:
    """The record's row class for a controller that logs ``signals``: a NamedTuple of the
    cycle's columns, the controller's, then ``extra`` (the bus loop's); every consumer reads
    it by name."""
    clash = sorted(set(signals) & set(CYCLE_COLUMNS + extra))
    if clash:
        raise ValueError(f"the controller logs {', '.join(clash)}, a column of the cycle's "
                         "own: name its signals otherwise")
    return NamedTuple("CycleRow", [(n, float) for n in (*CYCLE_COLUMNS, *signals, *extra)])


#: The row of the paper's controllers.
CycleRow = row_type(PAPER_SIGNALS)


@dataclass(frozen=True, slots=True)
class Truth:
    """What the emulator knows of its motor at a sample (for the record only).

    w_m: speed, rad/s. psi_r_ab: rotor flux, Wb. T_e: electromagnetic torque, N·m.
    """

    w_m: float
    psi_r_ab: complex
    T_e: float


NO_TRUTH = Truth(math.nan, complex(math.nan, math.nan), math.nan)


def truth_from(measured: Mapping[str, float]) -> Truth:
    """The truth the emulator sends (TPDO3, INT16 resolution), or a standard drive's
    measured speed (and torque) without a flux (NaN), or :data:`NO_TRUTH`."""
    if "w_m" not in measured:
        return NO_TRUTH
    nan = math.nan
    return Truth(measured["w_m"],
                 complex(measured.get("psi_ra", nan), measured.get("psi_rb", nan)),
                 measured.get("T_e", nan))


def sample_from(measured: Mapping[str, float], modulator_dc_link: float | None = None
                ) -> Sample:
    """The controller's input from the drive's role values: currents, voltages (NaN where a
    standard drive sends none), the
    emulator's true flux where it sends it (read only in the comparison mode
    ``flux="true"``), and the drive's speed where it sends one.

    ``modulator_dc_link``: a drive without DC-link compensation whose modulator assumes this
    DC link, V (the drive profile's ``modulator_dc_link_v``): it applies the voltage it
    reports scaled by the DC link it reports over the period (``u_dc``), and the sample's
    voltage is that, u_applied = u_reported·u_dc/U_mod (docs/robustness.md §12)."""
    psi = (complex(measured["psi_ra"], measured["psi_rb"]) if "psi_ra" in measured
           else None)
    nan = math.nan
    u = complex(measured.get("u_sa", nan), measured.get("u_sb", nan))
    if modulator_dc_link is not None and "u_dc" in measured:
        u *= measured["u_dc"] / modulator_dc_link
    return Sample(
        i_s_ab=complex(measured.get("i_sa", nan), measured.get("i_sb", nan)),
        u_s_ab=u,
        psi_r_ab=psi,
        w_m=measured.get("w_m"),
    )


def setpoint_values(
    cmd: Command, T_L: float, frame: SetpointFrame,
    controlword: int = Controlword.ENABLE_OPERATION,
) -> dict[str, float]:
    """The role values (SI) the gateway sends for one command.

    controlword; the frame angle ε0 at the start of the interval the setpoints act on and
    the frame speed ω0; the current and voltage setpoints in the (d, q) frame, or, for
    drives that hold (a, b) setpoints, in the fixed frame; the load torque for the emulated
    dynamometer, N·m; a standard drive's target torque (N·m), speed (rad/s) and position
    (rad).
    """
    if frame is SetpointFrame.DQ:
        i, u = cmd.i_s_dq_ref, cmd.u_s_dq_ref
    else:
        i, u = cmd.i_s_ab_ref, cmd.u_s_ab_ref
    n_i1, n_i2, n_u1, n_u2 = SETPOINTS[frame]
    return {"controlword": int(controlword), "eps_0": cmd.eps_0, "w_0": cmd.w_0,
            n_i1: i.real, n_i2: i.imag, n_u1: u.real, n_u2: u.imag, "T_L": T_L,
            "target_torque": cmd.target_torque, "target_velocity": cmd.target_velocity,
            "target_position": cmd.target_position}


class CycleOutput(NamedTuple):
    """What one cycle produces: the role values to send, and the record row (a
    :func:`row_type` row)."""

    setpoints: dict[str, float]
    row: Any


class ControlCycle:
    """Cycle k: the drive's role values at t_k = k·T → one controller step → the role
    values to send and a row.

    The load torque sent (for the emulated dynamometer) is the profile's at the start of
    the interval the setpoints act on, t_k + delay·T (docs/ARCHITECTURE.md).
    ``modulator_dc_link``: :func:`sample_from`'s (the drive profile's
    ``modulator_dc_link_v``); the row records the voltage the drive reported.
    """

    def __init__(self, controller: DriveController, profile: ReferenceProfile,
                 sampling: Sampling, modulator_dc_link: float | None = None) -> None:
        self.controller = controller
        self.modulator_dc_link = modulator_dc_link
        self.profile = profile
        self.sampling = sampling
        self.row_type = row_type(controller.signals)
        self._n_logged = len(controller.signals)

    def step(self, k: int, measured: Mapping[str, float], truth: Truth | None = None
             ) -> CycleOutput:
        """Run cycle k. ``truth`` overrides the one in ``measured`` (simulate records it
        unquantised)."""
        s = self.sampling
        t = k * s.period
        sample = sample_from(measured, self.modulator_dc_link)
        refs = self.profile.at(t)
        cmd = self.controller.step(refs, sample)
        T_L_cmd = self.profile.at(s.t_apply(t)).T_L if s.delay else refs.T_L
        values = setpoint_values(cmd, T_L_cmd, s.setpoint_frame)
        tr = truth if truth is not None else truth_from(measured)
        status = int(measured.get("statusword", 0))
        if len(cmd.logged) != self._n_logged:
            raise ValueError(f"the controller logged {len(cmd.logged)} values for its "
                             f"{self._n_logged} signals {self.controller.signals}")
        u = sample.u_s_ab
        if self.modulator_dc_link is not None:  # the record keeps what the drive reported
            u = complex(measured.get("u_sa", math.nan), measured.get("u_sb", math.nan))
        row = self.row_type(
            t, refs.w_ref, refs.psi_ref, refs.T_L, tr.w_m, abs(tr.psi_r_ab),
            sample.i_s_ab.real, sample.i_s_ab.imag, u.real, u.imag,
            cmd.i_s_dq_ref.real, cmd.i_s_dq_ref.imag, cmd.u_s_dq_ref.real, cmd.u_s_dq_ref.imag,
            cmd.eps_0, cmd.w_0, tr.T_e, float(cmd.i_limited),
            float(bool(status & SW_INTERNAL_LIMIT)), *cmd.logged,
        )
        return CycleOutput(values, row)
