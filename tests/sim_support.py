"""RunSpec from the command line's words, for tests written against them."""

from __future__ import annotations

from gateway.spec import RunSpec


def sim_config(period: float | None = 1e-3, delay: int = 1, setpoint_frame: str = "dq",
               drive: str | None = None, discretisation: str = "euler", **kw) -> RunSpec:
    """A RunSpec (period None: continuous time). The Euler design and no standstill
    identification by default: the plant scenario and robustness figures
    (docs/robustness.md) were first measured so (the Euler design's load observer is §2's;
    the sampled-data design's, §10, needs ``discretisation="exact"``)."""
    kw.setdefault("identify", False)
    return RunSpec.from_words(period, delay, setpoint_frame, drive,
                                discretisation=discretisation, **kw)
