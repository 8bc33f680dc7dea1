"""The drive model's side of the PDO signals (pure; shared by the emulated device and the
sampled simulation so both turn the same values into exactly the same numbers):
decoded RPDO values → :class:`Setpoints`, and a :class:`Measurement` → TPDO signal values."""

from __future__ import annotations

from collections.abc import Mapping

from dbc.modes import SetpointFrame
from plant.drive import Measurement, Setpoints


def setpoints_from_rpdos(rpdo1: Mapping[str, float], rpdo2: Mapping[str, float]) -> Setpoints:
    """Setpoints from RPDO1 (controlword, eps_0, w_0) and RPDO2 in either mapping.

    RPDO2 with i_sd_ref/i_sq_ref/u_sd_ref/u_sq_ref: the (d, q) frame, which the drive turns
    from eps_0 at w_0. With i_sa_ref/i_sb_ref/u_sa_ref/u_sb_ref: the fixed (a, b) frame, held.
    Missing signals count as zero (a remapped PDO may carry only some of them).
    """
    if "i_sa_ref" in rpdo2 or "u_sa_ref" in rpdo2:
        return Setpoints(
            frame=SetpointFrame.AB,
            i_s_ref=complex(rpdo2.get("i_sa_ref", 0.0), rpdo2.get("i_sb_ref", 0.0)),
            u_s_ref=complex(rpdo2.get("u_sa_ref", 0.0), rpdo2.get("u_sb_ref", 0.0)),
        )
    return Setpoints(
        frame=SetpointFrame.DQ,
        i_s_ref=complex(rpdo2.get("i_sd_ref", 0.0), rpdo2.get("i_sq_ref", 0.0)),
        u_s_ref=complex(rpdo2.get("u_sd_ref", 0.0), rpdo2.get("u_sq_ref", 0.0)),
        eps_0=float(rpdo1.get("eps_0", 0.0)),
        w_0=float(rpdo1.get("w_0", 0.0)),
    )


def tpdo_signals(meas: Measurement, statusword: int, sync_counter: int) -> dict[str, float]:
    """The values of every TPDO signal of ``dbc/drive.dbc`` for one sample (SI units):
    TPDO1 statusword, i_sa, i_sb, sync_counter; TPDO2 u_sa, u_sb, u_dc; TPDO3 (truth) w_m,
    psi_ra, psi_rb, T_e. A codec picks the signals of each message from this one mapping."""
    i, u, psi = meas.i_s_ab, meas.u_s_ab, meas.psi_r_ab
    return {
        "statusword": statusword, "i_sa": i.real, "i_sb": i.imag, "sync_counter": sync_counter,
        "u_sa": u.real, "u_sb": u.imag, "u_dc": meas.u_dc,
        "w_m": meas.w_m, "psi_ra": psi.real, "psi_rb": psi.imag, "T_e": meas.T_e,
    }
