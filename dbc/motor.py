"""Motor parameters of model (1) (pure: no I/O except the explicit TOML reader).

:class:`MotorParams` holds the physical parameters of model (1) of Marino, Tomei & Verrelli
(IFAC 2002) for a motor with one pole pair, with the paper's reparametrisation of section 2
(α, β, μ, σ) as derived properties. The defaults are the paper's 0.6 kW motor of section 6.
They are what the emulated drive's object 0x2200 holds and what the controller believes,
so both sides take them from here. It validates on construction and raises
:class:`ParamsError`, a :class:`ValueError` whose message says where (file), what (key,
value) and how to fix it. The helpers (``check_keys``, ``positive``, ``read_toml``,
``build_params``) serve every parameter dataclass of the project.

Units: SI (kg·m², Ω, H).
"""

from __future__ import annotations

import math
import tomllib
from collections.abc import Mapping
from dataclasses import dataclass, fields
from pathlib import Path
from typing import Any, TypeVar


class ParamsError(ValueError):
    """Invalid parameters: the message names the source, the key and the fix."""


def check_keys(source: str, data: Mapping[str, Any], valid: tuple[str, ...]) -> None:
    for key in data:
        if key not in valid:
            raise ParamsError(
                f"{source}: unknown key {key!r}; valid keys are {', '.join(valid)} "
                f"(fix the spelling or remove the key)"
            )


def positive(source: str, key: str, value: Any, allow_inf: bool = False) -> float:
    """``value`` as a float > 0 (finite unless ``allow_inf``), else :class:`ParamsError`."""
    if isinstance(value, bool) or not isinstance(value, int | float):
        raise ParamsError(
            f"{source}: {key} = {value!r} is not a number; give {key} as a positive number "
            f"in SI units"
        )
    x = float(value)
    if not (x > 0.0) or (math.isinf(x) and not allow_inf):
        raise ParamsError(
            f"{source}: {key} = {value!r} must be a positive finite number (SI units); "
            f"set {key} to a value > 0"
        )
    return x


def read_toml(path: str | Path, table: str | None) -> tuple[str, dict[str, Any]]:
    source = str(path)
    try:
        with open(path, "rb") as f:
            data = tomllib.load(f)
    except OSError as exc:
        raise ParamsError(f"{source}: cannot read the file ({exc.strerror})") from exc
    except tomllib.TOMLDecodeError as exc:
        raise ParamsError(f"{source}: not valid TOML ({exc}); fix the syntax") from exc
    if table is not None:
        if not isinstance(data.get(table), dict):
            raise ParamsError(f"{source}: no [{table}] table; add one with the parameters")
        data = data[table]
        source = f"{source} [{table}]"
    return source, data


_P = TypeVar("_P")


def build_params(cls: type[_P], valid: tuple[str, ...], values: Mapping[str, Any],
                 source: str) -> _P:
    """A frozen params dataclass from checked ``values`` (defaults for the rest), validated
    with ``source`` named in the messages (construction itself would name no file)."""
    obj = cls.__new__(cls)
    defaults = cls()
    for name in valid:
        object.__setattr__(obj, name, values.get(name, getattr(defaults, name)))
    obj._validate(source)  # type: ignore[attr-defined]
    return obj


#: The motor file's table of what commissioning measured besides model (1)'s parameters.
COMMISSIONING = "commissioning"


def commissioning(path: str | Path) -> dict[str, Any]:
    """A motor file's ``[commissioning]`` table (empty when it has none)."""
    _, data = read_toml(path, None)
    table = data.get(COMMISSIONING, {})
    if not isinstance(table, dict):
        raise ParamsError(f"{path}: [{COMMISSIONING}] must be a table")
    return table


@dataclass(frozen=True)
class MotorParams:
    """Parameters of model (1): one pole pair, linear magnetics, SI units.

    J: rotor moment of inertia, kg·m².  R_s, R_r: stator and rotor resistances, Ω.
    L_s, L_r: stator and rotor self-inductances, H.  M: mutual inductance, H.
    Defaults: the paper's 0.6 kW motor (section 6).
    """

    J: float = 0.0075
    R_s: float = 5.3
    R_r: float = 3.3
    L_s: float = 0.365
    L_r: float = 0.375
    M: float = 0.34

    def __post_init__(self) -> None:
        self._validate("MotorParams")

    def _validate(self, source: str) -> None:
        for f in fields(self):
            positive(source, f.name, getattr(self, f.name))
        if self.L_s * self.L_r - self.M * self.M <= 0.0:
            raise ParamsError(
                f"{source}: M = {self.M} with L_s = {self.L_s}, L_r = {self.L_r} gives "
                f"M² ≥ L_s·L_r (leakage σ ≤ 0, not a physical motor); lower M or raise "
                f"L_s and L_r so that M² < L_s·L_r"
            )

    # ---- reparametrisation of section 2 -------------------------------------------------
    @property
    def sigma(self) -> float:
        """σ = L_s(1 − M²/(L_s·L_r)) = L_s − M²/L_r (§E1), H: stator transient inductance."""
        return self.L_s - self.M * self.M / self.L_r

    @property
    def alpha(self) -> float:
        """α = R_r/L_r, s⁻¹: inverse rotor time constant."""
        return self.R_r / self.L_r

    @property
    def beta(self) -> float:
        """β = M/(σ·L_r), 1/H."""
        return self.M / (self.sigma * self.L_r)

    @property
    def mu(self) -> float:
        """μ = M/(J·L_r), 1/(kg·m²) (T_e = J·μ·(ψ_ra·i_sb − ψ_rb·i_sa))."""
        return self.M / (self.J * self.L_r)

    @property
    def R_eff(self) -> float:
        """R_s + R_r·(M/L_r)², Ω: the resistance seen by the stator current in (1)."""
        return self.R_s + self.sigma * self.beta * self.alpha * self.M

    # ---- construction ---------------------------------------------------------------------
    @classmethod
    def paper(cls) -> MotorParams:
        """The paper's 0.6 kW motor (section 6)."""
        return cls()

    @classmethod
    def from_mapping(cls, data: Mapping[str, Any], source: str = "motor parameters") -> MotorParams:
        """From a mapping of field names to values; missing keys take the paper's values."""
        valid = tuple(f.name for f in fields(cls))
        check_keys(source, data, valid)
        values = {k: positive(source, k, v) for k, v in data.items()}
        return build_params(cls, valid, values, source)

    @classmethod
    def from_toml(cls, path: str | Path, table: str | None = None) -> MotorParams:
        """From a TOML file: top-level keys, or the keys of ``[table]`` if given. A motor
        file's ``[commissioning]`` table (what `hil-gateway identify` measured besides the
        motor: sensor offsets, inverter voltage error; :func:`commissioning`) is not a
        parameter of model (1)."""
        source, data = read_toml(path, table)
        if table is None:
            data = {k: v for k, v in data.items() if k != COMMISSIONING}
        return cls.from_mapping(data, source)
