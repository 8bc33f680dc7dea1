"""One control cycle at the PDO level, shared by `simulate` and the CANopen loop.

Data flows one way: TPDO signal values → :func:`sample_from_tpdos` → controller →
:func:`rpdos_from_command` → RPDO signal values. The signal names and scalings are the
contract of ``dbc/drive.dbc``; both the sampled simulation and the bus loop go through the
same functions and the same codec, so their results agree to the last bit.
"""

from __future__ import annotations

from collections.abc import Mapping
from typing import Literal

from gateway.control.controller import Command, Sample

SetpointFrame = Literal["dq", "ab"]
SETPOINT_FRAMES: tuple[str, ...] = ("dq", "ab")

#: SYNC counter overflow (0x1019) the gateway configures: the counter runs 1..240 (CiA 301).
SYNC_OVERFLOW = 240


def sync_counter(k: int) -> int:
    """The SYNC counter of cycle k (k = 1, 2, …): 1..SYNC_OVERFLOW, then 1 again."""
    return ((k - 1) % SYNC_OVERFLOW) + 1


# CiA 402 controlword commands (CiA 402-2, device control).
CW_DISABLE_VOLTAGE = 0x0000  #: → Switch on disabled (power stage off)
CW_SHUTDOWN = 0x0006  #: → Ready to switch on
CW_SWITCH_ON = 0x0007  #: → Switched on
CW_ENABLE_OPERATION = 0x000F  #: → Operation enabled
CW_FAULT_RESET = 0x0080  #: rising edge of bit 7: Fault → Switch on disabled


def rpdo2_name(frame: SetpointFrame) -> str:
    """The DBC message carrying the setpoints in that frame."""
    return "RPDO2" if frame == "dq" else "RPDO2_AB"


def rpdos_from_command(
    cmd: Command, T_L: float, frame: SetpointFrame, controlword: int = CW_ENABLE_OPERATION
) -> dict[str, dict[str, float]]:
    """The RPDO signal values (SI) for one command.

    RPDO1: controlword, frame angle ε0 at the start of the interval the setpoints act on,
    frame speed ω0. RPDO2: current and voltage setpoints in the (d, q) frame, or, for
    drives that hold (a, b) setpoints, in the fixed frame (RPDO2_AB). RPDO3: the load torque
    for the emulated dynamometer, N·m.
    """
    if frame == "dq":
        i, u = cmd.i_s_dq_ref, cmd.u_s_dq_ref
        rpdo2 = {"i_sd_ref": i.real, "i_sq_ref": i.imag, "u_sd_ref": u.real, "u_sq_ref": u.imag}
    else:
        i, u = cmd.i_s_ab_ref, cmd.u_s_ab_ref
        rpdo2 = {"i_sa_ref": i.real, "i_sb_ref": i.imag, "u_sa_ref": u.real, "u_sb_ref": u.imag}
    return {
        "RPDO1": {"controlword": controlword, "eps_0": cmd.eps_0, "w_0": cmd.w_0},
        rpdo2_name(frame): rpdo2,
        "RPDO3": {"T_L": T_L},
    }


def sample_from_tpdos(
    tpdo1: Mapping[str, float], tpdo2: Mapping[str, float], tpdo3: Mapping[str, float] | None
) -> Sample:
    """The controller's input from decoded TPDO1 (currents), TPDO2 (voltages), TPDO3 (truth).

    TPDO3 is the emulator's truth; only the comparison mode ``flux="true"`` reads its flux.
    """
    psi = None if tpdo3 is None else complex(tpdo3["psi_ra"], tpdo3["psi_rb"])
    return Sample(
        i_s_ab=complex(tpdo1["i_sa"], tpdo1["i_sb"]),
        u_s_ab=complex(tpdo2["u_sa"], tpdo2["u_sb"]),
        psi_r_ab=psi,
    )
