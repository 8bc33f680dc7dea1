"""The import graph: `plant` and `gateway` stand side by side on the contract (`dbc`).

* `dbc` imports nothing of ours but itself;
* `plant` never imports `gateway`;
* `gateway` imports `plant` only where it assembles the emulator beside the gateway
  (`gateway/sim.py` for `hil-gateway sim`, `gateway/simulate.py` for `simulate`);
* the pure modules (control math, motor model, the contract's vocabulary) import neither
  python-can nor python-canopen.
"""

from __future__ import annotations

import ast
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
PACKAGES = ("dbc", "gateway", "plant")
ASSEMBLERS = {"gateway/sim.py", "gateway/simulate.py"}
PURE = ("dbc/cia301.py", "dbc/cia402.py", "dbc/modes.py", "dbc/signals.py", "dbc/timing.py",
        "dbc/motor.py", "plant/params.py", "plant/motor.py", "plant/drive.py",
        "plant/timing.py", "plant/cia402.py", "plant/profile.py", "plant/units.py",
        "plant/servo.py", "gateway/cycle.py", "gateway/control",
        "gateway/reference/signals.py", "gateway/reference/demand.py")


def _modules() -> list[Path]:
    return sorted(p for pkg in PACKAGES for p in (ROOT / pkg).rglob("*.py"))


def imports(path: Path) -> set[str]:
    """The top-level names of everything ``path`` imports (at any depth of the file)."""
    tree = ast.parse(path.read_text(encoding="utf-8"), str(path))
    out: set[str] = set()
    for node in ast.walk(tree):
        if isinstance(node, ast.Import):
            out |= {a.name for a in node.names}
        elif isinstance(node, ast.ImportFrom) and node.module and node.level == 0:
            out.add(node.module)
    return out


def _tops(path: Path) -> set[str]:
    return {name.split(".")[0] for name in imports(path)}


def _rel(p: Path) -> str:
    return p.relative_to(ROOT).as_posix()


def test_the_graph_is_what_the_checks_look_at():
    mods = [_rel(p) for p in _modules()]
    assert "gateway/loop.py" in mods and "plant/device.py" in mods and "dbc/codec.py" in mods
    assert "plant" in _tops(ROOT / "gateway/simulate.py")  # the check can see a violation


@pytest.mark.parametrize("path", _modules(), ids=_rel)
def test_layering(path):
    rel, tops = _rel(path), _tops(path)
    if rel.startswith("dbc/"):
        assert not tops & {"gateway", "plant"}, f"{rel} must import nothing of ours but dbc"
    elif rel.startswith("plant/"):
        assert "gateway" not in tops, f"{rel}: the plant never imports the gateway"
    elif rel not in ASSEMBLERS:
        assert "plant" not in tops, (f"{rel}: the gateway knows the drive through dbc and the "
                                     f"bus; only {sorted(ASSEMBLERS)} assemble the emulator")


@pytest.mark.parametrize("path", [p for p in _modules()
                                  if _rel(p).startswith(PURE)], ids=_rel)
def test_pure_modules_do_no_bus_io(path):
    assert not _tops(path) & {"can", "canopen", "cantools", "socket", "threading"}, _rel(path)


#: The optional extra 'campaign' (Dask, Parquet): imported by these campaign modules only,
#: so that everything else runs without it.
CAMPAIGN_EXTRA = {"dask", "distributed", "pyarrow"}
CAMPAIGN_EXTRA_USERS = {"gateway/campaign/engine.py", "gateway/campaign/table.py"}


@pytest.mark.parametrize("path", _modules(), ids=_rel)
def test_the_campaign_extra_stays_in_the_campaign_engine_and_table(path):
    if _rel(path) not in CAMPAIGN_EXTRA_USERS:
        assert not _tops(path) & CAMPAIGN_EXTRA, _rel(path)


@pytest.mark.parametrize("path", _modules(), ids=_rel)
def test_only_the_command_line_imports_the_campaigns(path):
    """Campaigns stand above the runs: they use the command line's inputs and the session,
    and nothing below imports them (gateway/cli.py only adds their command)."""
    rel = _rel(path)
    if not rel.startswith("gateway/campaign/") and rel != "gateway/cli.py":
        assert not any(n == "gateway.campaign" or n.startswith("gateway.campaign.")
                       for n in imports(path)), rel


def test_a_can_run_does_not_load_the_simulation():
    assert not {"gateway.simulate", "gateway.sim"} & imports(ROOT / "gateway/runner.py")


@pytest.mark.parametrize("path", sorted((ROOT / "examples").glob("*/src/**/*.py")), ids=_rel)
def test_example_controllers_use_the_interface_alone(path):
    """A user's controller package needs nothing of ours but the controller interface
    (docs/controllers.md): the example shows that."""
    ours = {n for n in imports(path) if n.split(".")[0] in PACKAGES}
    assert ours <= {"gateway.control.interface"}, ours
