"""Reference profiles: what the gateway asks the motor to follow (not the drive profile of
:mod:`gateway.drive_profile`).

* :mod:`gateway.reference.signals`: the C² reference signals ω*(t), ψ*(t), T_L(t) and their
  derivatives (``Signal``, ``Step``, ``Profile``, ``References``, ``SetPoint``); pure.
* :mod:`gateway.reference.toml`: the TOML file format (``parse_profile``, ``load_profile``,
  ``paper_profile``, line-precise ``ProfileError`` messages) and what a reference must stay
  within to run (``reference_limits``, ``ReferenceLimit``: the PDO ranges of ``drive.dbc``,
  the emulated drive's over-speed limit).
* :mod:`gateway.reference.demand`: the peaks a reference profile demands of a motor
  (``demand``, ``demand_trace``, ``Demand``); pure.
"""

from gateway.reference.demand import Demand, MotorLike, demand, demand_trace, sample_times
from gateway.reference.signals import (
    REFERENCE_KEYS,
    Profile,
    ProfileError,
    References,
    SetPoint,
    Signal,
    Step,
)
from gateway.reference.toml import (
    ReferenceLimit,
    load_profile,
    paper_profile,
    parse_profile,
    reference_limits,
    resolve_profile,
    shipped_profiles,
)

__all__ = [
    "REFERENCE_KEYS",
    "Demand",
    "MotorLike",
    "Profile",
    "ProfileError",
    "ReferenceLimit",
    "References",
    "SetPoint",
    "Signal",
    "Step",
    "demand",
    "demand_trace",
    "load_profile",
    "paper_profile",
    "parse_profile",
    "reference_limits",
    "resolve_profile",
    "sample_times",
    "shipped_profiles",
]
