"""What every benchmark shares: a run that did not complete is a failed measurement.

A benchmark collects its figures in a :class:`Figures`. The code that runs the system under
measurement (a gateway run, a simulation, the emulated drive) sits inside :func:`the_run`,
which turns what that system raises (a :class:`dbc.errors.UserError`, a missing output file,
a timeout, any other exception) into :class:`RunError` with a one-line reason; a run that
ended without an exception but did not complete (a stop reason other than the end of the
profile, an operating point lost) raises :class:`RunError` itself. :meth:`Figures.measure`
records a figure, or, when its run failed, the figure as failed with the reason, and the
benchmark goes on with its other measurements. A bug in the benchmark's own code (outside
:func:`the_run`) is not caught: it still ends in a traceback.

Output: the human table shows ``FAILED: <reason>`` in place of a failed figure
(:meth:`Figures.show`); ``--json`` (:func:`add_json_option`) prints the figures as one JSON
line on stdout, or writes them to a file, a failed figure as ``null`` and every failure in
``"failed": {"<figure name>": "<reason>"}`` (empty when none failed); non-finite numbers
are the strings ``"inf"``, ``"-inf"``, ``"nan"``. The exit status is 1 when a measurement
failed (:meth:`Figures.exit_status`).
"""

from __future__ import annotations

import argparse
import json
import math
import os
import resource
import subprocess
import sys
import time
from collections.abc import Callable, Iterable, Iterator
from contextlib import contextmanager
from pathlib import Path
from typing import Any, TypeVar

T = TypeVar("T")


class RunError(Exception):
    """A run that did not complete; ``str()`` is the reason, printed in place of its figure."""


def reason_of(exc: BaseException) -> str:
    """One line saying why: a UserError's message as it is, other exceptions with their type."""
    from dbc.errors import UserError

    text = " ".join(str(exc).split())
    if isinstance(exc, UserError | RunError):
        return text or type(exc).__name__
    return f"{type(exc).__name__}: {text}" if text else type(exc).__name__


@contextmanager
def the_run(what: str = "") -> Iterator[None]:
    """Around the code that runs the system under measurement: what it raises becomes
    :class:`RunError` (``what``, if given, prefixes the reason). KeyboardInterrupt and
    SystemExit pass."""
    try:
        yield
    except RunError as exc:
        if what:
            raise RunError(f"{what}: {exc}") from exc
        raise
    except Exception as exc:
        raise RunError(f"{what}: {reason_of(exc)}" if what else reason_of(exc)) from exc


def require_completed(summary: dict[str, Any], out: Path | None = None,
                      files: Iterable[str] = ()) -> None:
    """A gateway run's summary (summary.json): RunError unless it stopped at the end of the
    profile (``run.stop`` END_OF_PROFILE) and ``files`` exist in ``out``."""
    run = summary.get("run") or {}
    stop = run.get("stop")
    if stop != "END_OF_PROFILE":
        where = f" in cycle {run['stop_cycle']}" if run.get("stop_cycle") is not None else ""
        why = " ".join(str(run.get("stop_reason") or stop or "no stop reason").split())
        raise RunError(f"run stopped{where}: {why}")
    for name in files:
        if out is None or not (out / name).exists():
            raise RunError(f"the run completed but wrote no {name}")


def warm_env(**extra: str) -> dict[str, str]:
    """The environment of a timed command: this one's without ``PYTHONDONTWRITEBYTECODE``
    (a user's would not have it; without bytecode caches every start compiles the
    project's modules again), plus ``extra``."""
    env = {k: v for k, v in os.environ.items() if k != "PYTHONDONTWRITEBYTECODE"}
    env.update(extra)
    return env


def run_command(cmd: list[str], cwd: Path, env: dict[str, str], timeout: float
                ) -> tuple[float, float]:
    """Run ``cmd`` to its end, output captured: (wall s, CPU s of it and the processes it
    waited for). RunError for no end within ``timeout`` s or an exit status other than 0
    (with the last line of its stderr)."""
    before = resource.getrusage(resource.RUSAGE_CHILDREN)
    t0 = time.perf_counter()
    try:
        done = subprocess.run(cmd, env=env, cwd=cwd, capture_output=True, text=True,
                              stdin=subprocess.DEVNULL, timeout=timeout)
    except subprocess.TimeoutExpired as exc:
        raise RunError(f"no end after {exc.timeout:g} s") from exc
    wall = time.perf_counter() - t0
    after = resource.getrusage(resource.RUSAGE_CHILDREN)
    cpu = (after.ru_utime - before.ru_utime) + (after.ru_stime - before.ru_stime)
    if done.returncode != 0:
        why = " ".join((done.stderr.strip().splitlines() or ["no message"])[-1].split())
        raise RunError(f"exit status {done.returncode}: {why}")
    return wall, cpu


def read_summary(out: Path) -> dict[str, Any]:
    """The run directory ``out``'s summary.json; RunError where there is none to read."""
    try:
        return json.loads((out / "summary.json").read_text())
    except (OSError, ValueError) as exc:
        raise RunError(f"no readable summary.json ({exc})") from exc


def failed_text(reason: str) -> str:
    return f"FAILED: {reason}"


def _plain(x: Any) -> Any:
    """JSON-safe: numpy scalars and arrays as Python values, non-finite floats as strings."""
    if isinstance(x, dict):
        return {str(k): _plain(v) for k, v in x.items()}
    if isinstance(x, list | tuple):
        return [_plain(v) for v in x]
    if hasattr(x, "tolist") and not isinstance(x, str):  # numpy scalar or array
        return _plain(x.tolist())
    if isinstance(x, float) and not math.isfinite(x):
        return "nan" if math.isnan(x) else ("inf" if x > 0 else "-inf")
    return x


class Figures:
    """A benchmark's figures by name, and the failed ones with their reasons."""

    def __init__(self, **info: Any) -> None:
        self.values: dict[str, Any] = dict(info)
        self.failed: dict[str, str] = {}

    def put(self, name: str, value: T) -> T:
        self.values[name] = value
        return value

    def fail(self, names: str | Iterable[str], reason: str) -> None:
        """Record ``names`` as failed (figure ``None``) for ``reason``."""
        for name in [names] if isinstance(names, str) else names:
            self.values[name] = None
            self.failed[name] = reason

    def measure(self, name: str, fn: Callable[..., T], *args: Any, **kw: Any) -> T | None:
        """``fn(*args, **kw)`` as the figure ``name``; None (and the figure failed) when it
        raises :class:`RunError`."""
        try:
            value = fn(*args, **kw)
        except RunError as exc:
            self.fail(name, str(exc))
            return None
        return self.put(name, value)

    def measure_all(self, names: Iterable[str], fn: Callable[..., dict[str, Any]],
                    *args: Any, **kw: Any) -> dict[str, Any] | None:
        """Several figures from one measurement: ``fn`` returns them by name; all of
        ``names`` fail together when it raises :class:`RunError`."""
        names = list(names)
        try:
            values = fn(*args, **kw)
        except RunError as exc:
            self.fail(names, str(exc))
            return None
        for name in names:
            self.put(name, values[name])
        return values

    def ok(self, name: str) -> bool:
        return name not in self.failed

    def show(self, name: str, fmt: str | Callable[[Any], str] = "{}") -> str:
        """The figure formatted with ``fmt`` (a format string or a function), or
        ``FAILED: <reason>``."""
        if name in self.failed:
            return failed_text(self.failed[name])
        value = self.values[name]
        return fmt(value) if callable(fmt) else fmt.format(value)

    def as_json(self) -> dict[str, Any]:
        return _plain({**self.values, "failed": dict(self.failed)})

    def emit(self, dest: str | None) -> None:
        """``--json``: one line on stdout for ``-``, the same into the file ``dest``."""
        if dest is None:
            return
        line = json.dumps(self.as_json(), ensure_ascii=False)
        if dest == "-":
            print(line, flush=True)
        else:
            Path(dest).write_text(line + "\n")

    def report_failures(self) -> None:
        """A closing summary of what failed (stderr keeps stdout's JSON line last)."""
        if not self.failed:
            return
        by_reason: dict[str, list[str]] = {}
        for name, why in self.failed.items():
            by_reason.setdefault(why, []).append(name)
        print(f"FAILED: {len(self.failed)} figure(s), {len(by_reason)} reason(s):",
              file=sys.stderr)
        for why, names in by_reason.items():
            print(f"  {why} [{'; '.join(names)}]", file=sys.stderr)

    def exit_status(self, ok: bool = True) -> int:
        """1 when a measurement failed (or ``ok`` is false: a target the benchmark checks
        was missed), 0 otherwise."""
        return 1 if self.failed or not ok else 0


def add_json_option(ap: argparse.ArgumentParser) -> None:
    ap.add_argument("--json", nargs="?", const="-", metavar="FILE",
                    help="also give the figures as JSON: one line on stdout (--json), or "
                         "written to FILE (--json FILE); a failed figure is null and named "
                         "with its reason in \"failed\"")
