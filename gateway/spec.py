"""What a run is: one specification for `simulate`, `sim` and `run` (and the benchmarks).

:class:`RunSpec` holds the controller's choice and options, the sampling, the drive mode,
the plant scenario, the timing of a bus loop, the limits of what a run tolerates and the
duration; :func:`gateway.session.run` carries one out, in this process or over a bus. The
spec is plain data: it imports nothing of the plant (the plant scenario is resolved by the
modules that assemble the emulator, :mod:`gateway.simulate` and :mod:`gateway.sim`) and
nothing of the bus, so every command checks it before anything runs.
"""

from __future__ import annotations

from dataclasses import asdict, dataclass, field
from pathlib import PurePath
from typing import Any, Protocol

from dbc.errors import UserError
from dbc.modes import DriveMode
from dbc.timing import Sampling, Timing
from gateway.control.controller import (
    ControllerConfig,
    Discretisation,
    EstimatorKind,
    FluxSource,
    InertiaSource,
    Law,
    LoadSource,
    as_enum,
)
from gateway.control.correction import SensorCorrection
from gateway.control.interface import ControllerChoice
from gateway.control.laws import Gains
from gateway.control.load_observer import load_config
from gateway.logformat import LOG_SUFFIXES


class PlantModel(Protocol):
    """How the plant differs from the controller's model (:class:`plant.scenario.PlantScenario`,
    which the emulator's assemblers resolve from ``--plant``)."""

    name: str
    source: str

    @property
    def continuous_time_ok(self) -> bool: ...

    def describe(self) -> dict[str, Any]: ...

    def known(self, default: bool) -> bool: ...


def default_drive_mode(controller: str, law: Law = Law.CURRENT_FED) -> DriveMode:
    """The drive mode a run takes when none is given: the first the controller names (its
    ``drive_modes``), else the paper's law's (current-fed: ideal, full-order: voltage)."""
    from gateway.control.interface import controller_factory

    modes = getattr(controller_factory(controller), "drive_modes", None)
    return modes[0] if modes else as_enum(Law, law, "law").drive_modes[0]


def default_load(plant: PlantModel | None, drive_applies_load: bool | None = None
                 ) -> LoadSource:
    """The load torque the laws are told when the run does not say: the plant scenario's
    ``[load].known`` (told, else observed); else told where the drive applies the profile's
    load (``drive_applies_load`` True: a drive profile that maps a T_L signal, a
    dynamometer the gateway commands; None: the emulator) and untold where it cannot ("not
    told against a real drive": the laws then assume no load rather than feed forward one
    the shaft may not carry). A scenario that does not tell its load is observed: in the
    sampled-data design from the measured flux (docs/robustness.md §10), bounded on every
    plant of the robustness matrix; a real drive's stays untold until that observer has met
    real drives (at zero stator frequency under load it is not observable: §10)."""
    if plant is not None and not plant.known(True):
        return LoadSource.OBSERVED
    return LoadSource.UNTOLD if drive_applies_load is False else LoadSource.KNOWN


_ENUMS = (("law", Law, "law"), ("flux", FluxSource, "flux source"),
          ("estimator", EstimatorKind, "estimator"), ("drive_mode", DriveMode, "drive mode"),
          ("timing", Timing, "timing"), ("discretisation", Discretisation, "discretisation"),
          ("load", LoadSource, "load mode"), ("inertia", InertiaSource, "inertia"))


@dataclass(frozen=True)
class RunSpec:
    """One run's specification. Strings are accepted for the enums; every inconsistency is a
    :class:`UserError` saying what to choose, raised when the spec is made.

    The controller: ``controller`` (:class:`ControllerChoice`, the paper's laws by default)
    and the paper's options: ``law``, ``flux``, ``estimator``, ``gains``, ``w_c`` (the
    drift-free estimator's corner, rad/s), ``discretisation`` (EXACT, the sampled-data
    design of docs/sampled-control.md, or EULER), ``load`` (:class:`LoadSource`: the T_L the
    laws are told), ``identify`` (R_s, R_r from the standstill magnetisation; None: in every
    sampled run, :attr:`identifies`), ``inertia`` (:class:`InertiaSource`: tracked on
    line by the sampled-data design, the default, or the motor file's J), ``correction`` (the
    commissioning's sensor offsets, gain and dead time, corrected around the controller;
    None: none), and the controller's state at t = 0: ``w_hat_0`` (rad/s), ``eps_0`` (rad).

    The drive and the sampling: ``drive_mode`` (:class:`DriveMode`); ``sampling`` (period,
    delay, setpoint frame; None: continuous time, in-process simulation of the paper's laws
    only); ``quantize``: the signals pass the INT16 codec of dbc/drive.dbc (in-process; on a
    bus they always do).

    The plant (simulated or emulated): ``plant`` (:class:`PlantModel`; None: the nominal
    plant where we emulate it, and unknown on a real drive), ``initial`` (the motor's state
    at t = 0, :class:`plant.drive.MotorState`; None: at rest), ``record_step`` (continuous
    time's record, s).

    A bus loop: ``timing`` (:class:`Timing`), ``bus_log`` (the raw log's file name; its
    suffix picks python-can's writer), ``max_missed`` (consecutive missed cycles that stop
    the loop) and ``max_miss_rate`` (the fraction of any 100 ms that may be missed).

    ``duration``: s; None: the reference profile's.
    """

    controller: ControllerChoice = field(default_factory=ControllerChoice)
    law: Law = Law.CURRENT_FED
    flux: FluxSource = FluxSource.ESTIMATED
    estimator: EstimatorKind = EstimatorKind.OPEN_LOOP
    gains: Gains = field(default_factory=Gains)
    w_c: float = 2.0
    discretisation: Discretisation = Discretisation.EXACT
    load: LoadSource = LoadSource.KNOWN
    identify: bool | None = None
    inertia: InertiaSource = InertiaSource.TRACKED
    correction: SensorCorrection | None = None
    w_hat_0: float = 0.0
    eps_0: float = 0.0
    drive_mode: DriveMode = DriveMode.IDEAL
    sampling: Sampling | None = field(default_factory=Sampling)
    quantize: bool = True
    plant: PlantModel | None = None
    initial: Any = None
    record_step: float = 1e-3
    timing: Timing = Timing.LOCKSTEP
    bus_log: str = "bus.blf"
    max_missed: int = 5
    max_miss_rate: float = 0.2
    duration: float | None = None

    @classmethod
    def from_words(cls, period: float | None = 1e-3, delay: int = 1,
                   setpoint_frame: str = "dq", drive: str | None = None,
                   **kw: Any) -> RunSpec:
        """A RunSpec from the command line's words: sampled with ``period`` (s; None:
        continuous time), ``delay`` periods of SYNC delay, the ``setpoint_frame``, and
        ``drive`` as the drive mode; the other keywords are fields."""
        if drive is not None:
            kw["drive_mode"] = drive
        sampling = None if period is None else Sampling(period, delay, setpoint_frame)
        return cls(sampling=sampling, **kw)

    def __post_init__(self) -> None:
        try:
            for name, enum, what in _ENUMS:
                object.__setattr__(self, name, as_enum(enum, getattr(self, name), what))
        except ValueError as exc:
            raise UserError(str(exc)) from None
        self._check_controller()
        self._check_sampling()
        if PurePath(self.bus_log).suffix.lower() not in LOG_SUFFIXES:
            raise UserError(f"bus log {self.bus_log!r}: the file name must end in one of "
                            f"{', '.join(LOG_SUFFIXES)} (it selects python-can's writer)")
        if isinstance(self.max_missed, bool) or self.max_missed < 1:
            raise UserError(f"--max-missed {self.max_missed}: give a number of cycles >= 1")
        if not 0.0 < self.max_miss_rate <= 1.0:
            raise UserError(f"--max-miss-rate {self.max_miss_rate}: give a fraction in (0, 1]")

    def _check_controller(self) -> None:
        if self.controller.is_paper and self.drive_mode.standard:
            raise UserError(
                f"the paper's laws send current or voltage vectors, which a standard drive in "
                f"'{self.drive_mode}' mode does not take: use --controller speed-pi (a speed "
                "PI over the drive's torque, --drive-mode torque) or --controller stream (the "
                "profile's speed or torque as the target), or a vector --drive-mode")
        if self.controller.is_paper and self.drive_mode not in self.law.drive_modes:
            raise UserError(
                f"the {self.law} law does not drive a '{self.drive_mode}' drive: use "
                f"--drive-mode {' or '.join(self.law.drive_modes)} (the current-fed law sends "
                "currents, the full-order law voltages)")
        try:
            self.controller_config()  # the paper's options together (its design's rules)
        except ValueError as exc:
            raise UserError(str(exc)) from None

    def _check_sampling(self) -> None:
        """Continuous time is the paper's setting: its laws, an ideal or voltage-fed drive,
        the motor factors and the load of a plant scenario, nothing discrete."""
        if self.sampling is not None:
            return
        if not self.controller.is_paper:
            raise UserError(f"continuous time (--period continuous) integrates the paper's laws "
                            f"only; controller {self.controller.name!r} runs sampled: choose "
                            "a --period such as 1ms")
        if self.drive_mode is DriveMode.CURRENT_LOOP:
            raise UserError("continuous time models the drive as ideal (current-fed law) or "
                            "voltage-fed (full-order law): choose --drive-mode ideal or "
                            "voltage, or a sampling --period such as 1ms for the current-loop "
                            "drive")
        if self.correction is not None:
            raise UserError("the commissioning's corrections (the motor file's "
                            "[commissioning]) act around the sampled controller: choose a "
                            "sampling --period such as 1ms, or --no-commissioning")
        if self.identify:  # asked for (by default: where it runs)
            raise UserError("--identify runs in the sampled controller: choose a sampling "
                            "--period such as 1ms")
        if self.load is LoadSource.OBSERVED:
            raise UserError("the load observer is discrete-time: with the load observed "
                            "(--load observed, or a plant scenario with [load].known = "
                            "false) choose a sampling --period such as 1ms, or --load known")
        if self.plant is not None and not self.plant.continuous_time_ok:
            raise UserError(f"plant scenario {self.plant.source}: continuous time models the "
                            "motor factors and the load only (no sensors, inverter or drifts); "
                            "choose a sampling --period such as 1ms")

    @property
    def identifies(self) -> bool:
        """The standstill identification runs: as asked (``identify``), else in every
        sampled run (on by default; docs/robustness.md §5)."""
        return self.identify if self.identify is not None else self.sampling is not None

    @property
    def period(self) -> float:
        """The cycle period T, s (continuous time: the record step)."""
        return self.sampling.period if self.sampling is not None else self.record_step

    @property
    def who(self) -> str:
        """The controller in a few words: the paper's law and flux, or the controller's
        name."""
        if self.controller.is_paper:
            return f"law {self.law}, flux {self.flux}"
        return f"controller {self.controller.name}"

    def controller_config(self, current_lag: float = 0.0) -> ControllerConfig:
        """The paper's controller's part; ``current_lag``: the drive's current response
        time, s (continuous time: the record step stands in for the period, unused)."""
        return ControllerConfig(
            law=self.law, flux=self.flux, estimator=self.estimator, w_c=self.w_c,
            sampling=self.sampling or Sampling(self.record_step), gains=self.gains,
            discretisation=self.discretisation, current_lag=current_lag,
            load=self.load, **load_config(self.load, self.drive_mode),
            identify=self.identifies, inertia=self.inertia)

    def describe(self) -> dict[str, Any]:
        """A JSON-able description (summary.json's configuration)."""
        d = asdict(self)
        for key in ("sampling", "plant", "initial"):
            del d[key]
        d["identify"] = self.identifies  # what ran, not whether it was asked for
        s = self.sampling
        d["period"] = "continuous" if s is None else s.period
        if s is not None:
            d["delay"], d["setpoint_frame"] = s.delay, s.setpoint_frame
        if self.initial is not None:
            d["initial"] = {k: (str(v) if isinstance(v, complex) else v)
                            for k, v in asdict(self.initial).items()}
        d["plant_scenario"] = None if self.plant is None else self.plant.describe()
        return d
