"""SimConfig from the command line's words, for tests written against them."""

from __future__ import annotations

from dbc.timing import Sampling
from gateway.simulate import SimConfig


def sim_config(period: float | None = 1e-3, delay: int = 1, setpoint_frame: str = "dq",
               drive: str | None = None, discretisation: str = "euler", **kw) -> SimConfig:
    """A SimConfig (period None: continuous time). The Euler design by default: the plant
    scenario and robustness figures (docs/robustness.md) were first measured with it, and the
    load observer exists in it only."""
    if drive is not None:
        kw["drive_mode"] = drive
    sampling = None if period is None else Sampling(period, delay, setpoint_frame)
    return SimConfig(sampling=sampling, discretisation=discretisation, **kw)
