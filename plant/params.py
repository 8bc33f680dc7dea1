"""Drive parameters (pure: no I/O except the explicit TOML reader).

:class:`DriveParams` holds the inverter: operating mode, internal (PWM) rate, DC link,
over-current trip, current-loop bandwidth and the current-sensor errors. The motor's
parameters are :class:`dbc.motor.MotorParams` (shared with the gateway).

It validates on construction and raises :class:`ParamsError`, a :class:`ValueError` whose
message says where (file), what (key, value) and how to fix it.

Units: SI (kg·m², Ω, H, V, A, Hz, rad/s).
"""

from __future__ import annotations

import cmath
import math
from collections.abc import Mapping
from dataclasses import dataclass, fields
from pathlib import Path
from typing import Any

from dbc.modes import DriveMode
from dbc.motor import ParamsError, build_params, check_keys, positive, read_toml

__all__ = ["DriveParams", "ParamsError"]


@dataclass(frozen=True)
class DriveParams:
    """The inverter around the motor (see :class:`plant.drive.Drive`).

    mode: :class:`DriveMode` — IDEAL (stator currents equal the setpoints: current-fed
        model, first three equations of (1)), CURRENT_LOOP (PI current control at
        ``f_pwm``) or VOLTAGE (voltage setpoints applied).
    f_pwm: internal rate (PWM/current-control frequency), Hz.
    u_dc: DC-link voltage, V; the voltage vector is limited to ``u_lim`` = u_dc/√3.
    i_trip: over-current trip level of |i_s|, A (``math.inf`` disables the trip).
    w_max: over-speed limit of |ω|, rad/s: the emulated device faults (EMCY 0x8400) beyond
        it (``math.inf`` disables it; the pure model does not check it). Default 600 rad/s:
        3× the highest speed of the paper's test (200 rad/s, field weakening; one pole
        pair) and well inside the TPDO's ±1024 rad/s.
    current_loop_bw: closed-loop bandwidth of the current controller, rad/s.
    i_offset_ab: current-sensor offset, A (complex a + jb).
    i_gain_error: relative current-sensor gain error (0.01 = +1 %).
    i_noise_rms: current-sensor white noise, A rms per axis (Gaussian).
    seed: seed of the sensor-noise generator owned by each Drive.
    i_gain_phase: relative gain errors (a, b) of the two phase-current sensors of a
        three-phase drive (phases a and b measured, i_c = −i_a − i_b; amplitude-invariant
        Clarke transform to the (a, b) frame of (1)): 0.02 = the sensor reads 2 % high.
    dead_time: inverter dead time, s: each phase voltage is off by −dead_time·f_pwm·u_dc·
        sign(i_phase) (the classic dead-time voltage error), unseen by the drive's report.
    u_dc_ripple, u_dc_ripple_hz: DC-link voltage ripple, relative amplitude and frequency:
        the applied voltage is scaled by 1 + u_dc_ripple·sin(2π·u_dc_ripple_hz·t) while the
        modulator assumes the nominal u_dc (the reported voltage is the commanded one; the
        reported DC link, the period's mean, carries the ripple).
    """

    mode: DriveMode = DriveMode.CURRENT_LOOP
    f_pwm: float = 10e3
    u_dc: float = 560.0
    i_trip: float = 25.0
    w_max: float = 600.0
    current_loop_bw: float = 2.0 * math.pi * 1500.0
    i_offset_ab: complex = 0j
    i_gain_error: float = 0.0
    i_noise_rms: float = 0.0
    seed: int = 0
    i_gain_phase: tuple[float, float] = (0.0, 0.0)
    dead_time: float = 0.0
    u_dc_ripple: float = 0.0
    u_dc_ripple_hz: float = 300.0

    def __post_init__(self) -> None:
        self._validate("DriveParams")

    def _validate(self, source: str) -> None:
        try:
            object.__setattr__(self, "mode", DriveMode(self.mode))
        except ValueError:
            raise ParamsError(
                f"{source}: mode = {self.mode!r} is not a drive mode; use one of "
                f"{', '.join(DriveMode)}"
            ) from None
        positive(source, "f_pwm", self.f_pwm)
        positive(source, "u_dc", self.u_dc)
        positive(source, "i_trip", self.i_trip, allow_inf=True)
        positive(source, "w_max", self.w_max, allow_inf=True)
        bw = positive(source, "current_loop_bw", self.current_loop_bw)
        if bw >= math.pi * self.f_pwm:
            raise ParamsError(
                f"{source}: current_loop_bw = {bw:g} rad/s is not below the Nyquist rate "
                f"π·f_pwm = {math.pi * self.f_pwm:g} rad/s; lower it or raise f_pwm"
            )
        if not isinstance(self.i_offset_ab, int | float | complex) or not cmath.isfinite(
            complex(self.i_offset_ab)
        ):
            raise ParamsError(
                f"{source}: i_offset_ab = {self.i_offset_ab!r} must be a finite complex "
                f"number a + jb (in TOML: [a, b]), A"
            )
        g = self.i_gain_error
        if isinstance(g, bool) or not isinstance(g, int | float) or not (-1.0 < g < 1.0):
            raise ParamsError(
                f"{source}: i_gain_error = {g!r} must be a relative error in (−1, 1), "
                f"e.g. 0.01 for +1 %"
            )
        n = self.i_noise_rms
        if isinstance(n, bool) or not isinstance(n, int | float) or not (0.0 <= n < math.inf):
            raise ParamsError(
                f"{source}: i_noise_rms = {n!r} must be a finite number ≥ 0, A rms"
            )
        if isinstance(self.seed, bool) or not isinstance(self.seed, int):
            raise ParamsError(f"{source}: seed = {self.seed!r} must be an integer")
        gp = self.i_gain_phase
        if not (isinstance(gp, tuple) and len(gp) == 2 and all(
                isinstance(x, int | float) and not isinstance(x, bool) and -1.0 < x < 1.0
                for x in gp)):
            raise ParamsError(
                f"{source}: i_gain_phase = {gp!r} must be two relative errors (a, b), each "
                f"in (−1, 1), e.g. (0.0, 0.02) for phase b reading 2 % high"
            )
        for key, hi in (("dead_time", 0.5 / self.f_pwm), ("u_dc_ripple", 1.0),
                        ("u_dc_ripple_hz", math.inf)):
            x = getattr(self, key)
            if isinstance(x, bool) or not isinstance(x, int | float) or not (0.0 <= x < hi):
                raise ParamsError(
                    f"{source}: {key} = {x!r} must be a number ≥ 0 and below {hi:g} "
                    f"(dead_time in s, below half a PWM period; u_dc_ripple relative; "
                    f"u_dc_ripple_hz in Hz)"
                )

    @property
    def u_lim(self) -> float:
        """u_dc/√3, V: the largest voltage vector of linear space-vector PWM (circular limit)."""
        return self.u_dc / math.sqrt(3.0)

    @property
    def h(self) -> float:
        """1/f_pwm, s: the internal step."""
        return 1.0 / self.f_pwm

    @classmethod
    def from_mapping(cls, data: Mapping[str, Any], source: str = "drive parameters") -> DriveParams:
        """From a mapping of field names to values; ``i_offset_ab`` may be ``[a, b]``."""
        valid = tuple(f.name for f in fields(cls))
        check_keys(source, data, valid)
        values = dict(data)
        off = values.get("i_offset_ab")
        if isinstance(off, list | tuple):
            if len(off) != 2 or not all(
                isinstance(x, int | float) and not isinstance(x, bool) for x in off
            ):
                raise ParamsError(
                    f"{source}: i_offset_ab = {off!r} must be two numbers [a, b], A"
                )
            values["i_offset_ab"] = complex(off[0], off[1])
        if isinstance(values.get("i_gain_phase"), list):
            values["i_gain_phase"] = tuple(values["i_gain_phase"])
        for key in ("f_pwm", "u_dc", "i_trip", "w_max", "current_loop_bw", "i_gain_error",
                    "i_noise_rms",
                    "dead_time", "u_dc_ripple", "u_dc_ripple_hz"):
            if isinstance(values.get(key), int) and not isinstance(values.get(key), bool):
                values[key] = float(values[key])
        return build_params(cls, valid, values, source)

    @classmethod
    def from_toml(cls, path: str | Path, table: str | None = None) -> DriveParams:
        """From a TOML file: top-level keys, or the keys of ``[table]`` if given."""
        source, data = read_toml(path, table)
        return cls.from_mapping(data, source)

