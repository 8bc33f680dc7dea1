"""Tracking on the paper scenario: the Euler design against the sampled-data design.

Run: .venv/bin/python bench/bench_sampled.py [--markdown] [--quick]

For each target configuration of the sampled-data design the paper scenario (the
embedded `paper_profile()`) runs through `gateway.simulate` — the drive model, the PDO
codec and the controller exactly as over the bus — once with `discretisation="euler"`
(the laws stepped with forward Euler) and once with `"exact"` (docs/sampled-control.md),
and prints the speed error ω − ω* (RMS, max |·|, final) side by side with the target.
The simulations are deterministic: the figures do not depend on the machine.

`--markdown` prints the README's results table instead (both designs, every metric).
`--quick`: only the 1 ms rows.

A simulation that fails (an exception from the run) is a failed measurement: ``FAILED:
<reason>`` in place of its figures, the other configurations go on, exit status 1
(bench/_common.py). ``--json [FILE]`` keys: ``"<configuration> [euler]"`` and
``"<configuration> [exact]"`` (the continuous-time rows: ``[exact]`` only), each
``{"rms", "max", "final"}`` of the speed error in rad/s or null; ``targets``
(configuration -> target); ``failed``.
"""

from __future__ import annotations

import argparse
import sys
import time
from dataclasses import dataclass, field
from typing import Any

from _common import Figures, add_json_option, failed_text, the_run

from dbc.motor import MotorParams
from gateway import report
from gateway.reference import paper_profile
from gateway.session import run
from gateway.spec import RunSpec


def sim_config(*args, **kw) -> RunSpec:
    """RunSpec from the command line's words, without the standstill identification (the
    designs compared as they are; ``identify=True`` where a configuration asks for it)."""
    kw.setdefault("identify", False)
    return RunSpec.from_words(*args, **kw)




@dataclass(frozen=True)
class Case:
    """One configuration: a label, the RunSpec keywords, the target (RMS, rad/s)."""

    label: str
    kw: dict[str, Any] = field(default_factory=dict)
    target: str = ""
    quick: bool = True


CASES: tuple[Case, ...] = (
    Case("current-fed, true flux, ideal, 1 ms, dq, delay 1",
         dict(flux="true"), "≤ 0.01"),
    Case("current-fed, estimated, ideal, 1 ms, dq, delay 1", {}, "≤ 0.02"),
    Case("current-fed, estimated, ideal, 1 ms, ab, delay 1",
         dict(setpoint_frame="ab"), "≤ 2× dq"),
    Case("current-fed, true flux, current loop, 1 ms, dq, delay 1",
         dict(flux="true", drive="current-loop"), ""),
    Case("current-fed, estimated, current loop, 1 ms, dq, delay 1",
         dict(drive="current-loop"), "≤ 0.03"),
    Case("current-fed, true flux, ideal, 1 ms, dq, delay 0",
         dict(flux="true", delay=0), ""),
    Case("full-order, estimated, voltage, 1 ms, dq, delay 1",
         dict(law="full-order", drive="voltage"), "≤ 0.03"),
    Case("current-fed, estimated, ideal, 250 µs, dq, delay 1",
         dict(period=250e-6), "", quick=False),
    Case("current-fed, estimated, ideal, 2 ms, dq, delay 1",
         dict(period=2e-3), "≤ 0.1", quick=False),
    Case("current-fed, estimated, ideal, 5 ms, dq, delay 1",
         dict(period=5e-3), "stable", quick=False),
    Case("full-order, estimated, voltage, 2 ms, dq, delay 1",
         dict(law="full-order", drive="voltage", period=2e-3), "", quick=False),
)

CONTINUOUS: tuple[Case, ...] = (
    Case("current-fed, true flux, ideal, continuous",
         dict(flux="true", period=None), "1.2e-4 (unchanged)", quick=False),
    Case("full-order, estimated, voltage, continuous",
         dict(law="full-order", drive="voltage", period=None), "unchanged", quick=False),
)


def simulate(case: Case, discretisation: str) -> dict[str, Any]:
    """The run's metrics; RunError when it fails."""
    with the_run():
        cfg = sim_config(**case.kw, discretisation=discretisation)
        return report.metrics(run(cfg, paper_profile(), MotorParams.paper()).sig)


def measure(fig: Figures, case: Case, discretisation: str) -> dict[str, Any] | None:
    """The metrics of one configuration and design (None when its run failed); the speed
    error's RMS, max and final as the figure ``"<label> [<design>]"``."""
    name = f"{case.label} [{discretisation}]"
    m = fig.measure(name, simulate, case, discretisation)
    if m is not None:
        fig.put(name, {k: m["speed_error"][k] for k in ("rms", "max", "final")})
    return m


def _g(x: float) -> str:
    return f"{x:.3g}"


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--markdown", action="store_true",
                    help="print the README's results table (both designs, every metric)")
    ap.add_argument("--quick", action="store_true", help="only the 1 ms configurations")
    add_json_option(ap)
    args = ap.parse_args(argv)
    cases = [c for c in CASES if c.quick or not args.quick]
    conts = [] if args.quick else list(CONTINUOUS)
    fig = Figures(targets={c.label: c.target for c in (*cases, *conts)})
    t0 = time.perf_counter()
    results = []
    for case in cases:
        results.append((case, measure(fig, case, "euler"), measure(fig, case, "exact")))
    cont = [(case, measure(fig, case, "exact")) for case in conts]
    if args.markdown:
        print(markdown(results, cont, fig))
    else:
        print(table(results, cont, fig))
        print(f"({time.perf_counter() - t0:.1f} s)")
    fig.report_failures()
    fig.emit(args.json)
    return fig.exit_status()


def table(results, cont, fig: Figures) -> str:
    lines = ["paper scenario, speed error ω − ω* in rad/s: euler (forward Euler) | exact "
             "(sampled-data design)"]
    head = (f"{'configuration':58s} {'target RMS':>18s} | {'RMS':>8s} {'max':>8s} "
            f"{'final':>9s} | {'RMS':>8s} {'max':>8s} {'final':>9s}")
    lines += [head, "-" * len(head)]

    def cells(case: Case, design: str, m: dict[str, Any] | None) -> str:
        if m is None:
            return f"{failed_text(fig.failed[f'{case.label} [{design}]']):>27s}"
        e = m["speed_error"]
        return f"{e['rms']:8.3g} {e['max']:8.3g} {e['final']:9.2g}"

    for case, old, new in results:
        lines.append(f"{case.label:58s} {case.target:>18s} | {cells(case, 'euler', old)} | "
                     f"{cells(case, 'exact', new)}")
    for case, m in cont:
        lines.append(f"{case.label:58s} {case.target:>18s} | "
                     f"{'(the same: no sampling)':>27s} | {cells(case, 'exact', m)}")
    return "\n".join(lines)


def markdown(results, cont, fig: Figures | None = None) -> str:
    """The README's results table: one row per configuration and design (a failed run:
    FAILED and its reason in the row)."""
    lines = [
        "| configuration | design | speed error max | RMS | final | flux error max | "
        "estimation error max | peak i | peak u |",
        "|---|---|---|---|---|---|---|---|---|",
    ]

    def row(label: str, design: str, m: dict[str, Any] | None, key: str = "exact") -> str:
        if m is None:
            why = fig.failed.get(f"{label} [{key}]", "") if fig is not None else ""
            return f"| {label} | {design} | {failed_text(why)} |" + " |" * 6
        s, f, e = m["speed_error"], m["flux_error"], m["estimation_error"]
        return (f"| {label} | {design} | {_g(s['max'])} | {_g(s['rms'])} | "
                f"{s['final']:.2g} | {_g(f['max'])} | {_g(e['max'])} | "
                f"{m['peak_current']:.3g} | {m['peak_voltage']:.3g} |")

    for case, m in cont:
        lines.append(row(case.label, "—", m))
    for case, old, new in results:
        lines.append(row(case.label, "euler", old, "euler"))
        lines.append(row(case.label, "**exact**", new))
    return "\n".join(lines)


if __name__ == "__main__":
    sys.exit(main())
