"""The options a campaign sets: those of `simulate` or `sim`, as on their command line.

A campaign's ``[base]`` and its axes name a command's long options without the dashes
(``period``, ``delay``, ``profile``, ``k-w`` or ``k_w``); a flag (``no-quantize``,
``identify``) takes true or false. The options that choose where and how a single run
writes (``out``, ``force``, ``progress``, ``scope``) belong to the campaign, not to a point.
"""

from __future__ import annotations

import argparse
import functools
from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from enum import StrEnum
from typing import Any, NoReturn

from gateway.errors import UserError


class Command(StrEnum):
    """The command a campaign's points run."""

    SIMULATE = "simulate"  #: the loop without CAN, in the worker's process
    SIM = "sim"  #: over CANopen against the emulator started in the worker's process


#: Options a point may not set, and why.
RESERVED = {
    "out": "each point's run directory is the campaign's (DIR/runs/, --keep-runs)",
    "force": "the campaign decides where its points write",
    "progress": "the campaign shows its own progress",
    "scope": "a live scope of thousands of runs is not what it is for",
    "plotjuggler": "streaming thousands of runs to PlotJuggler is not what it is for",
    "debug": "give --debug to `hil-gateway campaign` itself",
    "help": "not an option of a run",
}

#: Options whose value is a file the worker reads (made absolute before a point is sent,
#: and hashed by content).
FILE_OPTIONS = ("reference", "motor")
#: Options resolved by the campaign itself: the plant scenario (merged with ``plant.*``
#: axes) and the controller's parameters (merged with ``controller.*`` axes).
PLANT_OPTION = "plant"
PARAMS_OPTION = "controller-params"


@dataclass(frozen=True)
class Option:
    """One long option of a command: ``name`` (its first spelling, without the dashes),
    ``flag`` (takes no value), ``choices`` (the values it takes, if listed)."""

    name: str
    flag: bool
    choices: tuple[str, ...] | None = None
    negatable: bool = False  #: a flag with a ``--no-`` form (on by default, e.g. identify)

    def argv(self, value: Any) -> list[str]:
        """The command-line words of ``value`` (``--name=value``; a flag: ``--name``, or
        nothing or ``--no-name`` for false)."""
        if self.flag:
            if value:
                return [f"--{self.name}"]
            return [f"--no-{self.name}"] if self.negatable else []
        return [f"--{self.name}={text(value)}"]


def text(value: Any) -> str:
    """A value as a command line spells it: floats with full precision."""
    if isinstance(value, float):
        return repr(value)
    return str(value)


class _Raising(argparse.ArgumentParser):
    """argparse whose errors raise :class:`UserError` instead of exiting."""

    def error(self, message: str) -> NoReturn:
        raise UserError(message)


def build_parser() -> argparse.ArgumentParser:
    """The parser of `hil-gateway simulate` and `sim` as the command line defines them
    (its own functions; the other commands left out: a worker builds one per batch),
    raising UserError on a bad option."""
    from gateway.cli import _add_sim, _add_simulate

    parser = _Raising(prog="hil-gateway")
    sub = parser.add_subparsers(dest="command")
    _add_simulate(sub)
    _add_sim(sub)
    return parser


@functools.lru_cache(maxsize=1)
def shared_parser() -> argparse.ArgumentParser:
    """:func:`build_parser`'s parser, built once per process (5 ms, a quarter of a short
    point's overhead when built per batch) and only read after: parsing makes a new
    namespace and leaves the parser as it was."""
    return build_parser()


def _subparser(parser: argparse.ArgumentParser, command: Command) -> argparse.ArgumentParser:
    for action in parser._actions:
        if isinstance(action, argparse._SubParsersAction):
            return action.choices[command.value]
    raise LookupError(command)  # pragma: no cover - the CLI always has its subcommands


def command_options(command: Command, parser: argparse.ArgumentParser | None = None
                    ) -> dict[str, Option]:
    """Every spelling of every long option of ``command`` (``profile`` and ``reference``,
    ``k-w`` and ``k_w``) → its :class:`Option`."""
    sub = _subparser(parser or build_parser(), command)
    out: dict[str, Option] = {}
    for action in sub._actions:
        negatable = isinstance(action, argparse.BooleanOptionalAction)
        longs = [s[2:] for s in action.option_strings
                 if s.startswith("--") and not (negatable and s.startswith("--no-"))]
        if not longs:
            continue
        opt = Option(longs[0], negatable or isinstance(action, argparse._StoreTrueAction),
                     None if negatable or not action.choices
                     else tuple(str(c) for c in action.choices), negatable)
        for name in (*longs, action.dest):
            out[name] = opt
            out[name.replace("_", "-")] = opt
            out[name.replace("-", "_")] = opt
    return out


def option(options: Mapping[str, Option], key: str, where: str) -> Option:
    """The option ``key`` names; UserError for a reserved or unknown one (``where``: the
    campaign file and table, for the message)."""
    bare = key.replace("_", "-")
    if bare in RESERVED:
        raise UserError(f"{where}: {key!r} cannot be set by a campaign: {RESERVED[bare]}; "
                        "remove it")
    if key not in options:
        names = sorted({o.name for o in options.values()} - set(RESERVED))
        raise UserError(f"{where}: {key!r} is not an option of the command, nor a plant "
                        "scenario key (plant.<table>.<key>), a controller parameter "
                        "(controller.<name>) or a table of settings; the options are "
                        f"{', '.join(names)}")
    return options[key]


def check_value(opt: Option, key: str, value: Any, where: str) -> Any:
    """``value`` checked for ``opt``: a flag takes true/false, any other option a string
    or a number (lists belong in [grid])."""
    if opt.flag:
        if not isinstance(value, bool):
            raise UserError(f"{where}: {key} = {value!r}: --{opt.name} is a flag: give true "
                            "or false")
        return value
    if isinstance(value, bool) or not isinstance(value, str | int | float):
        raise UserError(f"{where}: {key} = {value!r}: give a string or a number, as on the "
                        f"command line (--{opt.name} VALUE)")
    if opt.choices is not None and text(value) not in opt.choices:
        raise UserError(f"{where}: {key} = {value!r}: --{opt.name} takes one of "
                        f"{', '.join(opt.choices)}")
    return value


def parse_args(parser: argparse.ArgumentParser, command: Command, argv: Sequence[str]
               ) -> argparse.Namespace:
    """The options of one point, parsed by the command line's own parser."""
    return parser.parse_args([command.value, *argv])
