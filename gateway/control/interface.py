"""The controller interface: what the loop needs of any controller, and where it finds one.

Every cycle the loop decodes the drive's TPDOs into a :class:`Sample` (currents, voltages,
the drive's speed where it sends one), takes the references of the profile at t_k, calls
the controller's :meth:`DriveController.step` and sends the :class:`Command` it returns
(setpoints in the (d, q) frame and its angle and speed, or in the (a, b) frame). The
paper's laws (:mod:`gateway.control.controller`, :mod:`gateway.control.sampled`) implement
this interface as any other controller does; the loop, `simulate`, the record, the figures
and `compare` know nothing else of them. docs/controllers.md has a worked example.

A controller is found by name (:func:`controller_factory`): a name registered in the
entry-point group ``can_drive_hil.controllers`` (the built-ins ``paper`` and ``ifoc``, and
any installed package's), or ``package.module:Class``. The factory is called as
``factory(context, params)`` with the run's :class:`ControllerContext` and the parameters of
``--controller-params FILE.toml`` (a table of names to values).
"""

from __future__ import annotations

import importlib
import math
import sys
from collections.abc import Callable, Mapping
from dataclasses import dataclass, field
from importlib import metadata
from typing import Any, Protocol, runtime_checkable

from dbc.errors import UserError
from dbc.filecache import FileMemo
from dbc.modes import DriveMode, SetpointFrame
from dbc.motor import MotorParams
from dbc.timing import Sampling
from gateway.control.laws import Refs

#: The entry-point group in which packages register controllers (name = factory).
CONTROLLER_GROUP = "can_drive_hil.controllers"
#: The default controller: the paper's laws (Marino, Tomei & Verrelli).
DEFAULT_CONTROLLER = "paper"


@dataclass(frozen=True, slots=True)
class Sample:
    """What the drive reports at t_k (decoded from its TPDOs, SI units).

    i_s_ab: stator currents sampled at t_k, A (complex a + jb).
    u_s_ab: average applied stator voltage over (t_{k−1}, t_k], V.
    psi_r_ab: the true rotor flux at t_k, Wb, where the drive sends it (the emulator's
        truth; read only in the comparison mode ``--flux true``), else None.
    w_m: the rotor speed at t_k, rad/s, where the drive sends one (a speed sensor; the
        emulator's truth), else None. A sensorless controller must not use it.
    """

    i_s_ab: complex
    u_s_ab: complex
    psi_r_ab: complex | None = None
    w_m: float | None = None


@dataclass(frozen=True, slots=True)
class Command:
    """A controller's output at t_k.

    i_s_dq_ref, u_s_dq_ref: setpoints in the (d, q) frame, A and V.
    eps_0: frame angle at the start of the interval they act on, rad, in [−π, π).
    w_0: frame speed, rad/s (the drive turns the frame at w_0 over the interval).
    i_s_ab_ref, u_s_ab_ref: the same setpoints in the (a, b) frame, rotated with the angle
        of the interval's midpoint, for drives that hold (a, b) setpoints.
    i_limited: the controller's current limit clipped the setpoint.
    logged: the values of the controller's :attr:`DriveController.signals`, in order.
    target_torque, target_velocity, target_position: for a standard drive (CiA 402 torque,
        velocity or position mode, ``drive_mode`` TORQUE, VELOCITY or POSITION): the target
        torque, N·m, speed, rad/s, or position, rad, it applies over the interval; a vector
        drive ignores them, a standard drive the vector setpoints.
    """

    i_s_dq_ref: complex = 0j
    u_s_dq_ref: complex = 0j
    eps_0: float = 0.0
    w_0: float = 0.0
    i_s_ab_ref: complex = 0j
    u_s_ab_ref: complex = 0j
    i_limited: bool = False
    logged: tuple[float, ...] = ()
    target_torque: float = 0.0
    target_velocity: float = 0.0
    target_position: float = 0.0


# A Command for every cycle: the generated __init__ of a frozen dataclass calls
# object.__setattr__ per field; writing the slots through their member descriptors on a bare
# instance gives an equal object in half the time (as References in
# gateway.reference.signals).
_SET_COMMAND = tuple(Command.__dict__[f].__set__ for f in (
    "i_s_dq_ref", "u_s_dq_ref", "eps_0", "w_0", "i_s_ab_ref", "u_s_ab_ref", "i_limited",
    "logged", "target_torque", "target_velocity", "target_position"))


def make_command(i_s_dq_ref: complex, u_s_dq_ref: complex, eps_0: float, w_0: float,
                 i_s_ab_ref: complex, u_s_ab_ref: complex, i_limited: bool,
                 logged: tuple[float, ...], _new: Any = object.__new__,
                 _cls: type = Command, _s: tuple = _SET_COMMAND) -> Command:
    """``Command(i_s_dq_ref, u_s_dq_ref, eps_0, w_0, i_s_ab_ref, u_s_ab_ref, i_limited,
    logged)`` (no standard drive's targets: 0.0), built faster: a vector controller's
    every cycle."""
    c = _new(_cls)
    _s[0](c, i_s_dq_ref); _s[1](c, u_s_dq_ref); _s[2](c, eps_0); _s[3](c, w_0)  # noqa: E702
    _s[4](c, i_s_ab_ref); _s[5](c, u_s_ab_ref); _s[6](c, i_limited)  # noqa: E702
    _s[7](c, logged); _s[8](c, 0.0); _s[9](c, 0.0); _s[10](c, 0.0)  # noqa: E702
    return c


@runtime_checkable
class DriveController(Protocol):
    """What the loop needs of a controller.

    signals: the names of the values :attr:`Command.logged` carries, in order; they become
        columns of ``signals.csv`` after the cycle's own and are drawn in the figures.
        Conventional names the divergence guard and the figures understand: ``w_hat``
        (a speed estimate, rad/s), ``psi_r_mod_hat``, ``psi_rd_hat``, ``psi_rq_hat`` (a
        rotor-flux estimate and its components in the controller's frame, Wb).
    """

    signals: tuple[str, ...]

    def step(self, refs: Refs, sample: Sample) -> Command:
        """One cycle: the references at t_k and the drive's sample at t_k → the setpoints
        for the interval the drive applies them over (one period later with delay 1)."""
        ...

    def withhold(self) -> None:
        """The command of the last :meth:`step` was not sent (ready after the SYNC it was
        for): the drive holds its previous setpoints; the controller's model says so."""
        ...

    def coast(self) -> None:
        """A cycle without measurements (missed on the bus): the drive holds the last
        setpoints and keeps turning their frame; advance the controller's state over it.

        Optional, not part of the protocol: ``delayed(n)``, called instead of ``n`` coasts
        when the real-time SYNC thread skipped ``n`` slots right after the last step's
        sample: the drive held its previous setpoints through them and latches the last
        step's at the SYNC after, as sent (their ε0 ``n`` periods old). A controller
        without it is coasted."""
        ...


def checked_params(name: str, params: Mapping[str, Any], defaults: Mapping[str, Any]
            ) -> dict[str, Any]:
    """A controller's ``--controller-params`` over its ``defaults``: ValueError naming an
    unknown key (and what controller ``name`` takes) or a bad value (a default that is a
    bool takes true or false, a number a finite number > 0)."""
    unknown = sorted(set(params) - set(defaults))
    if unknown:
        takes = ", ".join(defaults) or "no parameters"
        raise ValueError(f"unknown parameter(s) {', '.join(unknown)}; {name} takes {takes}")
    p = {**defaults, **params}
    for key, default in defaults.items():
        if isinstance(default, bool):
            if not isinstance(p[key], bool):
                raise ValueError(f"{key} = {p[key]!r} must be true or false")
        elif not (isinstance(p[key], int | float) and not isinstance(p[key], bool)
                  and math.isfinite(p[key]) and p[key] > 0):
            raise ValueError(f"{key} = {p[key]!r} must be a number > 0")
    return p


@dataclass(frozen=True)
class ControllerContext:
    """What a run tells a controller when it makes one.

    motor: the motor the controller may believe (nameplate, motor file), model (1).
    sampling: the cycle period, the delay and the setpoint frame.
    refs_at: the reference profile as a function of time (looking ahead is allowed).
    drive_mode: what the drive does with the setpoints (current or voltage vector), or a
        standard drive's cyclic mode (TORQUE, VELOCITY: it takes :attr:`Command.target_torque`
        or :attr:`Command.target_velocity`). A controller that cannot drive it raises
        ValueError from its factory, saying what to choose.
    current_lag: the drive's current response time, s (0: an ideal current source).
    paper: the options of the paper's laws from the command line (law, flux source,
        estimator, gains, discretisation, load, identification); other controllers may
        ignore it. A :class:`gateway.control.controller.ControllerConfig`.
    eps_0, w_hat_0: the initial frame angle and speed estimate (``simulate`` options).
    correction: the commissioning's sensor and inverter corrections (a
        :class:`gateway.control.correction.SensorCorrection`, from the motor file's
        ``[commissioning]``), put around the controller by :meth:`ControllerChoice.make`
        for a vector drive; None: none.
    """

    motor: MotorParams
    sampling: Sampling
    refs_at: Callable[[float], Refs]
    drive_mode: DriveMode = DriveMode.IDEAL
    current_lag: float = 0.0
    paper: Any = None
    eps_0: float = 0.0
    w_hat_0: float = 0.0
    correction: Any = None


#: What makes a controller: a class or a function called as ``factory(context, params)``.
ControllerFactory = Callable[[ControllerContext, Mapping[str, Any]], DriveController]


@dataclass(frozen=True)
class ControllerChoice:
    """``--controller`` and ``--controller-params``: a name (registered, or
    ``module:Class``) and its parameters."""

    name: str = DEFAULT_CONTROLLER
    params: Mapping[str, Any] = field(default_factory=dict)

    @property
    def is_paper(self) -> bool:
        return self.name == DEFAULT_CONTROLLER

    def make(self, context: ControllerContext) -> DriveController:
        """The controller, checked against the interface."""
        factory = controller_factory(self.name)
        try:
            ctl = factory(context, dict(self.params))
        except (TypeError, ValueError, KeyError) as exc:
            raise ControllerError(f"controller {self.name!r} refused its parameters or the "
                                  f"run: {exc}") from exc
        check_controller(ctl, self.name)
        if context.drive_mode.standard:  # no vector setpoints: nothing to correct
            return ctl
        from gateway.control.correction import CorrectedController, IdentifiedCorrection

        s = context.sampling
        turning = s.setpoint_frame is SetpointFrame.DQ
        if getattr(ctl, "commissioning", None) is not None:  # the run's own identification
            ctl = IdentifiedCorrection(ctl, s.period, s.delay, turning=turning)
        if context.correction is not None:  # the motor file's
            ctl = CorrectedController(ctl, context.correction, s.period, s.delay,
                                      turning=turning)
        return ctl


class ControllerError(UserError):
    """A controller that cannot be found, made or used (the message says what and how)."""


def registered() -> dict[str, metadata.EntryPoint]:
    """The controllers registered in :data:`CONTROLLER_GROUP`, by name. Reading the
    installed packages' metadata takes milliseconds (a campaign's points each look up
    their controller): kept while ``sys.path`` and its directories are unchanged (an
    installed or removed package changes its directory)."""
    path = tuple(sys.path)
    return dict(_REGISTERED.get(path, lambda: (
        {ep.name: ep for ep in metadata.entry_points(group=CONTROLLER_GROUP)}, path)))


#: :func:`registered`'s scans, by ``sys.path``.
_REGISTERED: FileMemo[dict[str, metadata.EntryPoint]] = FileMemo(4)


def controller_factory(name: str) -> ControllerFactory:
    """The factory named ``name``: a registered name, or ``package.module:Class``."""
    if ":" in name:
        module_name, _, attr = name.partition(":")
        try:
            module = importlib.import_module(module_name)
        except ImportError as exc:
            raise ControllerError(f"--controller {name}: cannot import {module_name!r} "
                                  f"({exc}); is its package installed, or on PYTHONPATH?"
                                  ) from exc
        factory = module
        for part in attr.split("."):
            factory = getattr(factory, part, None)
            if factory is None:
                raise ControllerError(f"--controller {name}: {module_name} has no {attr!r}")
        if not callable(factory):
            raise ControllerError(f"--controller {name}: {attr!r} is not a class or function")
        return factory  # type: ignore[return-value]
    eps = registered()
    if name not in eps:
        raise ControllerError(
            f"--controller {name}: no controller of that name; registered: "
            f"{', '.join(sorted(eps)) or 'none'} (entry-point group {CONTROLLER_GROUP}), "
            "or give package.module:Class")
    try:
        return eps[name].load()
    except Exception as exc:
        raise ControllerError(f"--controller {name}: loading {eps[name].value} failed: "
                              f"{exc!r}") from exc


def check_controller(ctl: object, name: str) -> None:
    """``ctl`` has what the loop needs (:class:`DriveController`), or ControllerError."""
    missing = [a for a in ("signals", "step", "withhold", "coast") if not hasattr(ctl, a)]
    if missing:
        raise ControllerError(f"controller {name!r} ({type(ctl).__name__}) lacks "
                              f"{', '.join(missing)}: see docs/controllers.md")
    signals = ctl.signals  # type: ignore[attr-defined]
    if not (isinstance(signals, tuple) and all(isinstance(s, str) and s.isidentifier()
                                               for s in signals)):
        raise ControllerError(f"controller {name!r}: signals must be a tuple of names "
                              f"(identifiers), got {signals!r}")
    if len(set(signals)) != len(signals):
        raise ControllerError(f"controller {name!r}: signals {signals!r} repeat a name")


def summary_of(ctl: object) -> dict[str, Any] | None:
    """What a controller found during the run for summary.json (its optional ``summary()``,
    e.g. the paper's standstill identification), or None."""
    fn = getattr(ctl, "summary", None)
    return fn() if callable(fn) else None


def finite_or_nan(x: float | None) -> float:
    """A logged value: a float, NaN for None."""
    return math.nan if x is None else float(x)
