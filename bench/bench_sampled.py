"""Tracking on the paper scenario: the Euler design against the sampled-data design.

Run: .venv/bin/python bench/bench_sampled.py [--markdown] [--quick]

For each configuration of issue 13's targets the paper scenario (`profiles/paper.toml`, the
embedded `paper_profile()`) runs through `gateway.simulate` — the drive model, the PDO
codec and the controller exactly as over the bus — once with `discretisation="euler"`
(the laws stepped with forward Euler) and once with `"exact"` (docs/sampled-control.md),
and prints the speed error ω − ω* (RMS, max |·|, final) side by side with the target.
The simulations are deterministic: the figures do not depend on the machine.

`--markdown` prints the README's results table instead (both designs, every metric).
`--quick`: only the 1 ms rows.
"""

from __future__ import annotations

import argparse
import sys
import time
from dataclasses import dataclass, field
from typing import Any

from dbc.motor import MotorParams
from gateway import report
from gateway.reference import paper_profile
from gateway.simulate import SimConfig, run

sim_config = SimConfig.from_words  # SimConfig from the command line's words



@dataclass(frozen=True)
class Case:
    """One configuration: a label, the SimConfig keywords, the target (RMS, rad/s)."""

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
    cfg = sim_config(**case.kw, discretisation=discretisation)
    return report.metrics(run(paper_profile(), MotorParams.paper(), cfg).arrays())


def _g(x: float) -> str:
    return f"{x:.3g}"


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--markdown", action="store_true",
                    help="print the README's results table (both designs, every metric)")
    ap.add_argument("--quick", action="store_true", help="only the 1 ms configurations")
    args = ap.parse_args(argv)
    cases = [c for c in CASES if c.quick or not args.quick]
    conts = [] if args.quick else list(CONTINUOUS)
    t0 = time.perf_counter()
    results = []
    for case in cases:
        results.append((case, simulate(case, "euler"), simulate(case, "exact")))
    cont = [(case, simulate(case, "exact")) for case in conts]
    if args.markdown:
        print(markdown(results, cont))
        return 0
    print("paper scenario, speed error ω − ω* in rad/s: euler (forward Euler) | exact "
          "(sampled-data design)")
    head = (f"{'configuration':58s} {'target RMS':>18s} | {'RMS':>8s} {'max':>8s} "
            f"{'final':>9s} | {'RMS':>8s} {'max':>8s} {'final':>9s}")
    print(head)
    print("-" * len(head))
    for case, old, new in results:
        o, n = old["speed_error"], new["speed_error"]
        print(f"{case.label:58s} {case.target:>18s} | {o['rms']:8.3g} {o['max']:8.3g} "
              f"{o['final']:9.2g} | {n['rms']:8.3g} {n['max']:8.3g} {n['final']:9.2g}")
    for case, m in cont:
        e = m["speed_error"]
        print(f"{case.label:58s} {case.target:>18s} | {'(the same: no sampling)':>27s} | "
              f"{e['rms']:8.3g} {e['max']:8.3g} {e['final']:9.2g}")
    print(f"({time.perf_counter() - t0:.1f} s)")
    return 0


def markdown(results, cont) -> str:
    """The README's results table: one row per configuration and design."""
    lines = [
        "| configuration | design | speed error max | RMS | final | flux error max | "
        "estimation error max | peak i | peak u |",
        "|---|---|---|---|---|---|---|---|---|",
    ]

    def row(label: str, design: str, m: dict[str, Any]) -> str:
        s, f, e = m["speed_error"], m["flux_error"], m["estimation_error"]
        return (f"| {label} | {design} | {_g(s['max'])} | {_g(s['rms'])} | "
                f"{s['final']:.2g} | {_g(f['max'])} | {_g(e['max'])} | "
                f"{m['peak_current']:.3g} | {m['peak_voltage']:.3g} |")

    for case, m in cont:
        lines.append(row(case.label, "—", m))
    for case, old, new in results:
        lines.append(row(case.label, "euler", old))
        lines.append(row(case.label, "**exact**", new))
    return "\n".join(lines)


if __name__ == "__main__":
    sys.exit(main())
