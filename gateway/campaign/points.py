"""A campaign's points: the values of its axes, the configuration a worker runs, the content
hash that names it, and the command that reproduces it alone.

Points are numbered in a fixed order: each grid table's combinations (the first axis
slowest), each crossed with the random draws 0 … n−1. Draw j takes its values from a
generator seeded with (seed, j), so the same draw has the same values at every grid point
(paired comparisons) and raising n keeps the earlier draws. Two points with the same
configuration (hash) run once.

Files named by options (profile, motor) are relative to the current directory, as on the
command line; the worker gets them by absolute path (a cluster on other machines needs
them at the same path). The plant scenario and the controller's parameters travel with
the point as text: the ``plant`` option's scenario (a file or a shipped name; nominal when
none) with the point's ``plant.*`` keys set in it, the ``controller-params`` file's table
with its ``controller.*`` keys.
"""

from __future__ import annotations

import copy
import hashlib
import itertools
import json
import shlex
import tomllib
from collections.abc import Iterator, Mapping, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from gateway.campaign import tomltext
from gateway.campaign.model import Axis, AxisKind, Campaign, Settings
from gateway.campaign.options import (
    FILE_OPTIONS,
    PARAMS_OPTION,
    PLANT_OPTION,
    Command,
    Option,
)
from gateway.errors import UserError

PROG = "hil-gateway"


@dataclass(frozen=True)
class PointConfig:
    """One point: what a worker runs and what the table records of it.

    ``argv``: the command's options for the worker (files by absolute path; the plant and
    controller parameters apart); ``plant``: the plant scenario's (TOML text, source) or
    None (nominal); ``controller_params``: the controller's parameters or None (its
    file's, or none); ``values``: each axis's value (a settings table by its label);
    ``options``: the options as written, for the command that reproduces the point;
    ``plant_changed``: the point sets plant.* keys (reproducing it needs the scenario
    written to a file)."""

    index: int
    hash: str
    command: Command
    argv: tuple[str, ...]
    plant: tuple[str, str] | None = None
    controller_params: Mapping[str, Any] | None = None
    values: Mapping[str, Any] = field(default_factory=dict)
    options: tuple[str, ...] = ()
    plant_changed: bool = False
    params_changed: bool = False


def _combinations(campaign: Campaign) -> Iterator[dict[str, Any]]:
    """Every point's axis values, in the fixed order."""
    draws = []
    for j in range(campaign.n):
        rng = np.random.default_rng([campaign.seed, j])
        draws.append({ax.key: ax.dist.draw(rng) for ax in campaign.random if ax.dist})
    for grid in campaign.grids:
        for combo in itertools.product(*(ax.values for ax in grid)):
            at = {ax.key: v for ax, v in zip(grid, combo, strict=True)}
            for d in draws:
                yield {**at, **d}


def _settings(campaign: Campaign, values: Mapping[str, Any]) -> dict[str, Any]:
    """[base] with the point's axes set over it: option name, ``plant.<t>.<k>`` or
    ``controller.<k>`` → value."""
    out = dict(campaign.base)
    by_key = {ax.key: ax for ax in campaign.axes}
    for key, v in values.items():
        ax: Axis = by_key[key]
        if ax.kind is AxisKind.SETTINGS:
            assert isinstance(v, Settings)
            out.update(v.values)
        elif ax.kind is AxisKind.OPTION:
            out[ax.target] = v
        else:
            out[key] = v
    return out


class _Files:
    """What the planner reads once per file: digests, scenario and parameter documents."""

    def __init__(self, cwd: Path) -> None:
        self.cwd = cwd
        self._digests: dict[str, str] = {}
        self._plants: dict[str, tuple[dict[str, Any], str]] = {}
        self._params: dict[str, dict[str, Any]] = {}

    def path(self, value: str) -> Path:
        p = Path(value).expanduser()
        return p if p.is_absolute() else self.cwd / p

    def digest(self, option: str, value: str) -> str:
        if value not in self._digests:
            try:
                data = self.path(value).read_bytes()
            except OSError as exc:
                raise UserError(f"--{option} {value}: cannot read it "
                                f"({exc.strerror or exc}); paths are relative to the current "
                                "directory, as on the command line") from None
            self._digests[value] = hashlib.sha256(data).hexdigest()
        return self._digests[value]

    def plant(self, arg: str) -> tuple[dict[str, Any], str]:
        """The scenario ``--plant arg`` names, as a document, and its source name."""
        if arg not in self._plants:
            from gateway.sim import scenario_text

            p = self.path(arg)
            text, source = scenario_text(str(p) if p.exists() else arg)
            try:
                self._plants[arg] = (tomllib.loads(text), source)
            except tomllib.TOMLDecodeError as exc:
                raise UserError(f"--plant {arg}: not valid TOML ({exc})") from None
        doc, source = self._plants[arg]
        return copy.deepcopy(doc), source

    def params(self, arg: str) -> dict[str, Any]:
        if arg not in self._params:
            try:
                self._params[arg] = tomllib.loads(self.path(arg).read_text(encoding="utf-8"))
            except OSError as exc:
                raise UserError(f"--controller-params {arg}: cannot read it "
                                f"({exc.strerror or exc})") from None
            except tomllib.TOMLDecodeError as exc:
                raise UserError(f"--controller-params {arg}: not valid TOML: {exc}") from None
        return dict(self._params[arg])


def configure(campaign: Campaign, index: int, values: Mapping[str, Any], files: _Files
              ) -> PointConfig:
    """The configuration of the point with these axis ``values``."""
    settings = _settings(campaign, values)
    options = {k: v for k, v in settings.items() if "." not in k}
    plant_keys = {k[len("plant."):]: v for k, v in settings.items() if k.startswith("plant.")}
    params_keys = {k[len("controller."):]: v for k, v in settings.items()
                   if k.startswith("controller.")}
    bus_keys = {k[len("bus."):]: v for k, v in settings.items() if k.startswith("bus.")}
    plant_arg = options.pop(PLANT_OPTION, None)
    params_arg = options.pop(PARAMS_OPTION, None)
    opts: Mapping[str, Option] = campaign.options
    argv: list[str] = []
    written: list[str] = []
    identity: dict[str, Any] = {}
    for name, value in options.items():
        opt = opts[name]
        written += opt.argv(value)
        if name in FILE_OPTIONS:
            argv += opt.argv(str(files.path(str(value)).resolve()))
            identity[name] = {"sha256": files.digest(name, str(value))}
        else:
            argv += opt.argv(value)
            identity[name] = value
    plant: tuple[str, str] | None = None
    changed = bool(plant_keys or bus_keys)
    if changed or plant_arg is not None:
        doc, source = files.plant(str(plant_arg)) if plant_arg is not None else ({}, "")
        for key, v in plant_keys.items():
            table, _, name = key.partition(".")
            section = doc.setdefault(table, {})
            if not isinstance(section, dict):
                raise UserError(f"--plant {plant_arg}: [{table}] is not a table")
            section[name] = v
        _set_bus_keys(doc, bus_keys, plant_arg)
        if changed:
            source = f"<{campaign.name} point {index}>"
        plant = (tomltext.dumps(doc), source)
        identity["plant"] = doc
        if not changed:
            written.append(f"--plant={plant_arg}")
    params: dict[str, Any] | None = None
    if params_keys or params_arg is not None:
        params = files.params(str(params_arg)) if params_arg is not None else {}
        params.update(params_keys)
        identity["controller_params"] = params
        if not params_keys:
            written.append(f"--{PARAMS_OPTION}={params_arg}")
    identity["command"] = campaign.command.value
    digest = hashlib.sha256(json.dumps(identity, sort_keys=True, default=str)
                            .encode()).hexdigest()[:16]
    return PointConfig(index, digest, campaign.command, tuple(argv), plant, params,
                       {k: (v.label if isinstance(v, Settings) else v)
                        for k, v in values.items()},
                       tuple(written), changed, bool(params_keys))


def _set_bus_keys(doc: dict[str, Any], keys: Mapping[str, Any], plant_arg: Any) -> None:
    """``bus.<key>`` axes: the key set in every [[bus.fault]] of the scenario ``doc``."""
    if not keys:
        return
    bus = doc.get("bus")
    faults = bus.get("fault") if isinstance(bus, dict) else None
    if not isinstance(faults, list) or not faults:
        which = f"--plant {plant_arg}" if plant_arg is not None else "the nominal plant"
        raise UserError(f"bus.{', bus.'.join(keys)}: {which} has no [[bus.fault]] to set it "
                        "in; name a scenario with bus faults in [base] or an axis, e.g. "
                        "plant = \"bus-drop\" (plant/scenarios/bus-*.toml)")
    for fault in faults:
        if isinstance(fault, dict):
            fault.update(keys)


def every_point(campaign: Campaign, cwd: Path | None = None) -> list[PointConfig]:
    """Every point of ``campaign`` in order, identical configurations included (a case
    that two grids share is in both)."""
    files = _Files(cwd or Path.cwd())
    return [configure(campaign, i, values, files)
            for i, values in enumerate(_combinations(campaign))]


def plan(campaign: Campaign, cwd: Path | None = None) -> tuple[list[PointConfig], int]:
    """The points to run: every point of ``campaign``, identical configurations once (the
    first), and how many were identical to an earlier one."""
    points: list[PointConfig] = []
    seen: set[str] = set()
    for point in every_point(campaign, cwd):
        if point.hash not in seen:
            seen.add(point.hash)
            points.append(point)
    return points, campaign.size - len(points)


def reproduce(point: PointConfig | Mapping[str, Any], repro_dir: Path) -> str:
    """The command line that runs ``point`` alone (a point or a table row); the plant
    scenario and controller parameters it sets are written into ``repro_dir`` first."""
    if isinstance(point, Mapping):
        command, index, digest = str(point["command"]), int(point["point"]), str(point["hash"])
    else:
        command, index, digest = point.command.value, point.index, point.hash
    words = [PROG, command, *(_options(point))]
    name = f"{index:05d}-{digest[:8]}"
    for text, suffix, option in ((_plant_text(point), "plant", PLANT_OPTION),
                                 (_params_text(point), "controller", PARAMS_OPTION)):
        if text is None:
            continue
        path = repro_dir / f"{name}-{suffix}.toml"
        repro_dir.mkdir(parents=True, exist_ok=True)
        from gateway.atomicfile import write_text_atomic

        write_text_atomic(path, text)
        words += [f"--{option}", str(path)]
    return shlex.join(words)


def _options(point: PointConfig | Mapping[str, Any]) -> Sequence[str]:
    if isinstance(point, PointConfig):
        return point.options
    return shlex.split(str(point["options"]))


def _plant_text(point: PointConfig | Mapping[str, Any]) -> str | None:
    """The plant scenario a point's reproduction needs written to a file, or None."""
    if isinstance(point, PointConfig):
        return point.plant[0] if point.plant_changed and point.plant else None
    return point.get("plant_toml") or None


def _params_text(point: PointConfig | Mapping[str, Any]) -> str | None:
    if isinstance(point, PointConfig):
        if point.params_changed and point.controller_params is not None:
            return tomltext.dumps(point.controller_params)
        return None
    return point.get("controller_params_toml") or None


def record_fields(point: PointConfig) -> dict[str, Any]:
    """What the table keeps of a point to reproduce it later (``campaign show``)."""
    return {"command": point.command.value, "options": shlex.join(point.options),
            "plant_toml": _plant_text(point), "controller_params_toml": _params_text(point)}
