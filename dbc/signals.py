"""The PDO signal groups: which signals carry what, by the names of ``drive.dbc``.

Drive → gateway (TPDOs): the CiA 402 statusword and the SYNC-counter echo, the sampled
stator currents, the average applied voltages and the DC link, and (emulator only) the
truth of the model. Gateway → drive (RPDOs): the controlword with the frame (ε0, ω0),
the current and voltage setpoints in the (d, q) or the (a, b) frame, and the load torque
for the emulated dynamometer.
"""

from __future__ import annotations

from dbc.modes import SetpointFrame

STATUS: tuple[str, ...] = ("statusword", "sync_counter")
CURRENTS: tuple[str, ...] = ("i_sa", "i_sb")
VOLTAGES: tuple[str, ...] = ("u_sa", "u_sb", "u_dc")
TRUTH: tuple[str, ...] = ("w_m", "psi_ra", "psi_rb", "T_e")
#: Every signal the drive transmits, in the order of the default TPDOs.
TX: tuple[str, ...] = (*STATUS[:1], *CURRENTS, *STATUS[1:], *VOLTAGES, *TRUTH)

CONTROL: tuple[str, ...] = ("controlword",)
FRAME: tuple[str, ...] = ("eps_0", "w_0")
SETPOINTS: dict[SetpointFrame, tuple[str, ...]] = {
    SetpointFrame.DQ: ("i_sd_ref", "i_sq_ref", "u_sd_ref", "u_sq_ref"),
    SetpointFrame.AB: ("i_sa_ref", "i_sb_ref", "u_sa_ref", "u_sb_ref"),
}
LOAD: tuple[str, ...] = ("T_L",)
#: The targets of a standard drive (CiA 402 0x6071 in CST, 0x60FF in CSV, 0x607A in CSP), in
#: N·m, rad/s and rad.
TARGETS: tuple[str, ...] = ("target_torque", "target_velocity", "target_position")

#: Every role: what the gateway means by a value (a signal name of ``drive.dbc``).
ROLES: frozenset[str] = frozenset((*TX, *CONTROL, *FRAME, *SETPOINTS[SetpointFrame.DQ],
                                   *SETPOINTS[SetpointFrame.AB], *LOAD, *TARGETS))

#: The default DBC message carrying the setpoints in each frame (they share a COB-ID).
SETPOINT_MESSAGE: dict[SetpointFrame, str] = {
    SetpointFrame.DQ: "RPDO2",
    SetpointFrame.AB: "RPDO2_AB",
}


def setpoint_frame_of(signal_names: set[str] | frozenset[str] | tuple[str, ...]) -> SetpointFrame:
    """The frame a mapping's setpoint signals are in: AB if any (a, b) setpoint is mapped."""
    return (SetpointFrame.AB if set(signal_names) & set(SETPOINTS[SetpointFrame.AB])
            else SetpointFrame.DQ)
