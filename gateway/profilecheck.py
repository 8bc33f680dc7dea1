"""`hil-gateway profile check DRIVE.toml`: a drive profile checked off line, before any bus.

The profile loads (its EDS and DBC exist and read; the messages it names are in the DBC),
then every PDO signal is held against the EDS object it maps (:func:`gateway.eds.object_for`):
the object exists, is PDO-mappable, has the DBC signal's size, and can be written (a signal
the gateway sends) or read (one the drive sends). Then, for each drive mode, whether the
roles a run in it needs are mapped — which controllers the drive can run. The same
checks a run makes at bring-up, without the drive.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import canopen
from canopen.objectdictionary import ODVariable

from dbc.busload import CycleLoad
from dbc.cia402 import SUPPORTED_DRIVE_MODES_OBJECT, describe_mode, mode_bit
from dbc.edsfile import configured, read_eds
from dbc.modes import DriveMode
from dbc.timing import Sampling
from gateway.bustime import profile_load
from gateway.control.interface import ControllerChoice
from gateway.drive_profile import DriveProfile, load_drive_profile
from gateway.eds import object_for
from gateway.errors import UserError
from gateway.process_data import ProcessData, process_data

#: The controller each drive mode is checked with, and the law for the paper's.
MODE_CONTROLLERS: dict[DriveMode, tuple[str, str]] = {
    DriveMode.CURRENT_LOOP: ("paper", "current-fed"),
    DriveMode.VOLTAGE: ("paper", "full-order"),
    DriveMode.TORQUE: ("speed-pi", "current-fed"),
    DriveMode.VELOCITY: ("stream", "current-fed"),
    DriveMode.POSITION: ("stream", "current-fed"),
}


@dataclass
class SignalCheck:
    """One PDO signal against its EDS object; ``problem`` is "" when it fits."""

    pdo: str
    cob_id: int
    signal: str
    role: str
    bits: int
    obj: str
    problem: str = ""


@dataclass
class ProfileReport:
    """What ``profile check`` found: the signals, and per drive mode the roles missing."""

    profile: DriveProfile
    signals: list[SignalCheck] = field(default_factory=list)
    modes: dict[DriveMode, list[str]] = field(default_factory=dict)
    #: drive mode → why the drive does not offer its 0x6060 value (0x6502 of the EDS)
    not_offered: dict[DriveMode, str] = field(default_factory=dict)
    #: the bus time of one cycle of its mapping (:func:`gateway.bustime.profile_load`)
    bus: CycleLoad | None = None

    @property
    def ok(self) -> bool:
        """Every signal fits its object, at least one drive mode can run, and the profile's
        default mode (if it names one) can."""
        runs = [m for m, missing in self.modes.items()
                if not missing and m not in self.not_offered]
        default = self.profile.default_mode
        return (not any(s.problem for s in self.signals) and bool(runs)
                and (default is None or default in runs))


def is_drive_profile(path: str | Path) -> bool:
    """The TOML file has a [drive] table (else it is taken for a reference profile)."""
    import tomllib

    try:
        return "drive" in tomllib.loads(Path(path).read_text(encoding="utf-8"))
    except (OSError, UnicodeDecodeError, tomllib.TOMLDecodeError):
        return False


def check_drive_profile(path: str | Path) -> ProfileReport:
    """Load the drive profile at ``path`` (a :class:`UserError` for what keeps it from
    loading) and check its signals and modes (see the module docstring)."""
    prof = load_drive_profile(path)
    try:
        od = read_eds(prof.eds, prof.node).od
    except UserError as exc:  # checked by the loader already; a node id can still fail
        raise UserError(f"{prof.source}: {exc} (node {prof.node})") from None
    pd = process_data(prof)
    report = ProfileReport(prof, _signals(od, pd, prof.objects), bus=profile_load(prof, pd))
    mapped = {s.role for s in report.signals if not s.problem}
    for mode in MODE_CONTROLLERS:
        report.modes[mode] = [r for r in roles_needed(mode, pd) if r not in mapped]
    supported = _default(od, SUPPORTED_DRIVE_MODES_OBJECT)
    for mode in MODE_CONTROLLERS:
        value = prof.mode_of(mode)
        bit = mode_bit(value, emulator=prof.emulator)
        if isinstance(supported, int) and bit is not None and not supported & bit:
            report.not_offered[mode] = (f"[modes] gives {describe_mode(value)}, which the "
                                        f"EDS's 0x6502 (0x{supported:08X}) does not offer")
    return report


def _default(od: canopen.ObjectDictionary, index: int) -> Any:
    """An object's value in the file (a DCF's ParameterValue first), or None."""
    obj = od.get(index)
    return configured(obj) if isinstance(obj, ODVariable) else None


def _signals(od: canopen.ObjectDictionary, pd: ProcessData, objects: dict[str, tuple[int, int]]
             ) -> list[SignalCheck]:
    out = []
    for pdo in (*pd.rpdos, *pd.tpdos):
        for (signal, role), spec in zip(pdo.signals, pdo.codec.signals, strict=True):
            var = object_for(od, signal, role, objects.get(f"{pdo.name}.{signal}"))
            check = SignalCheck(pdo.name, pdo.cob_id, signal, role, spec.bits,
                                "—" if var is None else f"0x{var.index:04X}.{var.subindex}")
            check.problem = _problem(var, spec.bits, pdo.tx, signal)
            out.append(check)
    return out


def _problem(var: canopen.objectdictionary.ODVariable | None, bits: int, tx: bool,
             signal: str) -> str:
    """What keeps ``var`` from carrying a ``bits``-bit signal in a TPDO (``tx``) or an
    RPDO; "" when nothing does."""
    if var is None:
        return (f"the EDS has no object named {signal!r}: name the object in [objects] "
                "(\"MESSAGE.signal\" = \"0xIIII.S\"), or the object like the DBC signal")
    if not var.pdo_mappable:
        return f"{var.name!r} is not PDO-mappable (PDOMapping=0 in the EDS)"
    if len(var) != bits:
        return (f"{var.name!r} is {len(var)} bits in the EDS, the DBC signal {bits}: make "
                "the DBC signal's size the object's")
    if tx and not var.readable:
        return f"{var.name!r} cannot be read (AccessType {var.access_type})"
    if not tx and not var.writable:
        return (f"{var.name!r} cannot be written (AccessType {var.access_type}): the gateway "
                "sends it")
    return ""


def roles_needed(mode: DriveMode, pd: ProcessData) -> list[str]:
    """The roles a run in ``mode`` needs of the drive (:func:`gateway.runner.required_roles`
    with the controller of :data:`MODE_CONTROLLERS`)."""
    from gateway.control.interface import controller_factory
    from gateway.runner import required_roles
    from gateway.spec import RunSpec

    name, law = MODE_CONTROLLERS[mode]
    spec = RunSpec(controller=ControllerChoice(name), law=law, drive_mode=mode,
                   sampling=Sampling(1e-3, 1, pd.setpoint_frame))
    requires = tuple(getattr(controller_factory(name), "requires", ()))
    return list(required_roles(spec, pd, requires))


def render(report: ProfileReport, period: float = 1e-3) -> str:
    """The report as text: one line per signal, one per drive mode, the bus time of a cycle
    and its load at ``period`` (s), the verdict."""
    prof = report.profile
    lines = [f"{prof.source}: drive profile {prof.name!r}, node {prof.node}, EDS "
             f"{prof.eds.name}, DBC {prof.dbc.name}",
             f"  {'PDO':<10}{'COB-ID':<8}{'signal':<18}{'role':<16}{'bits':>4}  object"]
    for s in report.signals:
        lines.append(f"  {s.pdo:<10}0x{s.cob_id:03X}   {s.signal:<18}{s.role:<16}{s.bits:>4}  "
                     f"{s.obj}" + (f"  ERROR: {s.problem}" if s.problem else ""))
    for mode, missing in report.modes.items():
        name, _ = MODE_CONTROLLERS[mode]
        ctl = f"the {name} controller" if name != "paper" else "the paper's laws"
        why = (f"no {', '.join(missing)}" if missing else report.not_offered.get(mode))
        default = " (the profile's default)" if mode is prof.default_mode else ""
        lines.append(f"  --drive-mode {mode:<13}" + (
            f"runs {ctl}{default}" if not why else f"cannot run {ctl}{default}: {why}"))
    if report.bus is not None:
        bus = report.bus
        lines.append(f"  {bus.describe(period)}")
        verdict = ("fits" if bus.fits(period) else "does NOT fit: `sim` and `run` refuse it")
        lines.append(f"  at {period * 1e6:g} us the cycle {verdict}; shortest period it fits: "
                     f"{bus.min_period() * 1e6:.0f} us")
    lines.append("ok: the profile loads, every signal fits its object" if report.ok else
                 "not ok: fix the errors above (or map the roles a drive mode needs, or "
                 "choose a [modes] value the drive offers)")
    return "\n".join(lines)
