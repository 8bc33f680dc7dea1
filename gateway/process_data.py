"""The drive's process data: which PDO and signal carries each role, from its profile and DBC.

A *role* is what the gateway means by a value (the signal names of the built-in
``dbc/drive.dbc``: ``i_sa``, ``statusword``, ``i_sd_ref``, …). A drive profile names, for
each role, the message and signal of *its* DBC that carry it (``[signals]``; roles whose
signal has the role's name in the profile's ``[pdo]`` messages need no entry). Layouts,
COB-IDs, sizes and scalings all come from that DBC; the built-in one is only the
emulator's. Data flows one way: frame → :meth:`ProcessData.decode` → role values →
controller → role values → :meth:`ProcessData.encode` → frames.
"""

from __future__ import annotations

from collections.abc import Iterable, Mapping
from dataclasses import dataclass, replace
from pathlib import Path

from dbc import MessageCodec, parse_dbc
from dbc.modes import SetpointFrame
from dbc.signals import (
    CONTROL,
    CURRENTS,
    FRAME,
    LOAD,
    SETPOINTS,
    STATUS,
    TARGETS,
    TRUTH,
    VOLTAGES,
)
from gateway.drive_profile import DriveProfile
from gateway.errors import UserError

#: Roles a drive sends (TPDOs) and the gateway sends (RPDOs).
TX_ROLES = frozenset((*STATUS, *CURRENTS, *VOLTAGES, *TRUTH))
RX_ROLES = frozenset((*CONTROL, *FRAME, *SETPOINTS[SetpointFrame.DQ],
                      *SETPOINTS[SetpointFrame.AB], *LOAD, *TARGETS))

#: What to look for when a role is missing (for the refusal at bring-up).
ROLE_HINTS: dict[str, str] = {
    "statusword": "the CiA 402 statusword 0x6041",
    "controlword": "the CiA 402 controlword 0x6040",
    "i_sa": "a manufacturer object with the stator current of phase a (fixed frame), signed",
    "i_sb": "a manufacturer object with the stator current along b (fixed frame, 90° ahead "
            "of a), signed",
    "u_sa": "a manufacturer object with the average applied stator voltage along a over the "
            "period",
    "u_sb": "a manufacturer object with the average applied stator voltage along b",
    "eps_0": "a manufacturer object taking the (d, q) frame angle at the start of the period",
    "w_0": "a manufacturer object taking the (d, q) frame speed",
    "target_torque": "the CiA 402 target torque 0x6071 (cyclic synchronous torque)",
    "target_velocity": "the CiA 402 target velocity 0x60FF (cyclic synchronous velocity)",
    "target_position": "the CiA 402 target position 0x607A (cyclic synchronous position)",
    "u_dc": "the DC-link voltage, the CiA 402 DC link circuit voltage 0x6079 (or a "
            "manufacturer object with its mean over the period), or leave "
            "[drive].modulator_dc_link_v out for a drive that compensates its DC link",
    "w_m": "the speed: the CiA 402 velocity actual value 0x606C, or the emulator's truth",
    "psi_ra": "the emulator's true rotor flux (TPDO3); real drives have none: use --flux "
              "estimated",
    "psi_rb": "the emulator's true rotor flux (TPDO3); real drives have none: use --flux "
              "estimated",
}
for _r in (*SETPOINTS[SetpointFrame.DQ], *SETPOINTS[SetpointFrame.AB]):
    ROLE_HINTS[_r] = (f"a manufacturer object taking the {_r[0]}-setpoint "
                      f"{_r[2:4]} in the ({_r[3]}) frame")

#: Standard CiA 402 process data that cannot carry the laws' signals.
STANDARD_ONLY = {0x6071: "target torque", 0x6077: "torque actual value",
                 0x6078: "current actual value", 0x6079: "DC link circuit voltage"}


@dataclass(frozen=True)
class Pdo:
    """One PDO of the drive: its DBC message, COB-ID, and a codec keyed by role.

    signals: (DBC signal name, role) in frame order. tx: sent by the drive (a TPDO).
    """

    name: str
    cob_id: int
    codec: MessageCodec
    signals: tuple[tuple[str, str], ...]
    tx: bool

    @property
    def roles(self) -> tuple[str, ...]:
        return tuple(role for _, role in self.signals)

    @property
    def length(self) -> int:
        return self.codec.length


class ProcessData:
    """The PDOs of one drive at one node (see the module docstring)."""

    def __init__(self, pdos: Iterable[Pdo], source: str = "",
                 modulator_dc_link: float | None = None) -> None:
        self.pdos: tuple[Pdo, ...] = tuple(pdos)
        self.source = source
        #: the DC link the drive's modulator assumes where it does not compensate its DC
        #: link, V (the profile's ``modulator_dc_link_v``; None: it does): its voltages are
        #: scaled by its u_dc, which it must send (:func:`gateway.cycle.sample_from`)
        self.modulator_dc_link = modulator_dc_link
        self.tpdos = tuple(p for p in self.pdos if p.tx)
        self.rpdos = tuple(p for p in self.pdos if not p.tx)
        self.by_cob_id = {p.cob_id: p for p in self.tpdos}
        self.roles = frozenset(r for p in self.pdos for r in p.roles)
        self.setpoint_frame = (SetpointFrame.AB if self.roles & set(SETPOINTS[SetpointFrame.AB])
                               else SetpointFrame.DQ)

    def pdo(self, role: str) -> Pdo:
        """The PDO carrying ``role`` (KeyError if none)."""
        for p in self.pdos:
            if role in p.roles:
                return p
        raise KeyError(role)

    def decode(self, pdo: Pdo, data: bytes | bytearray) -> dict[str, float]:
        """Frame data of ``pdo`` → role values (SI)."""
        return pdo.codec.decode(data)

    def encode(self, values: Mapping[str, float]) -> list[tuple[int, str, bytes]]:
        """Role values → the RPDO frames (COB-ID, message name, data)."""
        return [(p.cob_id, p.name, p.codec.encode(values)) for p in self.rpdos]

    def quantize(self, values: Mapping[str, float], tx: bool) -> dict[str, float]:
        """What the receiver of the TPDOs (``tx``) or RPDOs sees of ``values``."""
        out: dict[str, float] = {}
        for p in self.tpdos if tx else self.rpdos:
            c = p.codec
            out.update(c.phys(c.raw(values)))
        return out

    def require(self, roles: Iterable[str], why: str, eds_objects: Iterable[int] = ()
                ) -> None:
        """Refuse, by name, the roles the chosen law needs and the drive does not map."""
        missing = [r for r in roles if r not in self.roles]
        if not missing:
            return
        lines = "; ".join(f"{r}: map {ROLE_HINTS.get(r, 'an object carrying it')}"
                          for r in missing)
        standard = [f"0x{i:04X} {what}" for i, what in STANDARD_ONLY.items()
                    if i in set(eds_objects)]
        hint = ""
        if standard:
            hint = (f" The drive's EDS has the standard CiA 402 process data "
                    f"({', '.join(standard)}), which cannot run these laws: they need the "
                    "stator current vector in a fixed frame and the applied voltage, or a "
                    "drive that turns a (d, q) frame from eps_0/w_0; look in the drive's "
                    "manual for manufacturer-specific objects carrying them.")
        raise UserError(f"{self.source}: {why} needs {', '.join(missing)}, which the drive "
                        f"profile does not map to any PDO ({lines}). Add them to [signals] "
                        f"(role = \"MESSAGE.signal\" of the profile's DBC).{hint}")


def _pdo_names(profile: DriveProfile, frame: SetpointFrame | None) -> list[tuple[str, bool]]:
    """(message, is TPDO) of the profile's [pdo] table; the setpoint message by frame."""
    setpoints = profile.setpoints
    if setpoints and frame == SetpointFrame.AB and not setpoints.upper().endswith("_AB"):
        setpoints = f"{setpoints}_AB"
    rx = [n for n in (profile.control, setpoints, profile.load) if n]
    tx = [n for n in (profile.currents, profile.voltages, profile.truth) if n]
    return [(n, False) for n in rx] + [(n, True) for n in tx]


def process_data(profile: DriveProfile, node: int | None = None,
                 frame: SetpointFrame | None = None) -> ProcessData:
    """The process data of the drive a profile describes, at ``node`` (default the
    profile's). COB-IDs are the DBC's frame ids, moved by the node difference when they are
    in the pre-defined connection set of the profile's ``dbc_node``."""
    node = node or profile.node
    try:
        messages, _ = parse_dbc(Path(profile.dbc))
    except ValueError as exc:
        raise UserError(f"{profile.source}: {exc}") from None
    explicit: dict[str, list[tuple[str, str]]] = {}  # message → [(signal, role)]
    for role, (msg, sig) in profile.signals.items():
        explicit.setdefault(msg, []).append((sig, role))
    names = _pdo_names(profile, frame)
    wanted = dict(names)
    for msg in explicit:
        if msg not in wanted:
            wanted[msg] = any(r in TX_ROLES for _, r in explicit[msg])
    pdos = []
    base = profile.dbc_node or profile.node
    for msg, tx in wanted.items():
        m = messages.get(msg)
        if m is None:
            raise UserError(f"{profile.source}: message {msg!r} is not in the DBC "
                            f"{profile.dbc}; its messages are {', '.join(sorted(messages))}")
        by_signal = {s.name: s for s in m.signals}
        roles = dict(explicit.get(msg, ()))
        for s in m.signals:  # a signal named like a role is that role, unless mapped
            if s.name not in roles and s.name not in profile.signals and (
                    s.name in (TX_ROLES if tx else RX_ROLES)):
                roles[s.name] = s.name
        for sig in roles:
            if sig not in by_signal:
                raise UserError(f"{profile.source}: [signals] names {msg}.{sig}, but the DBC "
                                f"message {msg} has {', '.join(by_signal)}")
        unknown = [s.name for s in m.signals if s.name not in roles]
        if unknown and not tx:
            raise UserError(
                f"{profile.source}: the gateway would send {msg} without values for "
                f"{', '.join(unknown)}: give each signal of an RPDO a role in [signals]")
        signals = tuple((s.name, roles.get(s.name, f"{msg}.{s.name}")) for s in m.signals)
        specs = [replace(s, name=role) for s, (_, role) in zip(m.signals, signals, strict=True)]
        cob_id = m.frame_id
        if (cob_id & 0x7F) == base and 0x180 <= cob_id < 0x580:
            cob_id += node - base
        pdos.append(Pdo(msg, cob_id, MessageCodec(msg, cob_id, specs, m.length), signals, tx))
    return ProcessData(pdos, profile.source, profile.modulator_dc_link_v)
