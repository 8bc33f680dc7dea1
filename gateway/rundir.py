"""A run's directory: made before the run, never reused by accident, gone again if the run
fails to start."""

from __future__ import annotations

import itertools
from collections.abc import Iterator, Sequence
from contextlib import contextmanager, suppress
from datetime import datetime
from pathlib import Path

from gateway.errors import UserError

#: The marker a bus run writes into its directory before the loop starts (the run's
#: configuration, ``run.status = "running"``); removed once summary.json is written, so a
#: crash leaves it behind.
RUNNING_MARKER = "running.json"
#: A run's own report in its directory (`hil-gateway report RUN_DIR`).
REPORT_FILE = "report.html"
#: The files a run writes into its directory (besides the bus log named by --log), and its
#: report (`hil-gateway report`): what --force removes before it reuses a directory.
RUN_FILES = ("summary.json", RUNNING_MARKER, "signals.csv", "fig1_references.png",
             "fig2_errors.png", "fig3_currents_voltages.png", "fig4_controller.png",
             REPORT_FILE)


def run_labels(paths: Sequence[Path]) -> list[str]:
    """How to name each of several run directories: its own name, or the path as given
    where two share a name (``a/run`` and ``b/run``)."""
    names = [p.name or str(p) for p in paths]
    return [str(p) if names.count(n) > 1 else n for p, n in zip(paths, names, strict=True)]


def out_dir(arg: str | None, kind: str, force: bool = False,
             extra_files: Sequence[str] = ()) -> Path:
    """The run directory, created: ``--out`` DIR, or a new ``runs/<time>-<kind>[-n]``.

    A default directory is never reused: two runs started in the same second get ``-2``,
    ``-3``… (created atomically). An existing non-empty ``--out`` is refused unless
    ``force``; then the files of the earlier run (:data:`RUN_FILES`, ``extra_files``) are
    removed first so that nothing stale is mixed with the new run (symbolic links are kept
    and written through: someone put them there on purpose).
    """
    try:
        if arg:
            path = Path(arg)
            if path.exists() and not path.is_dir():
                raise UserError(f"--out {arg!r} is a file, not a directory: choose a new "
                                "directory name")
            if path.is_dir() and any(path.iterdir()):
                if not force:
                    names = sorted(p.name for p in path.iterdir())
                    raise UserError(
                        f"--out {arg!r} exists and is not empty ({', '.join(names[:4])}"
                        f"{', …' if len(names) > 4 else ''}): a run never overwrites another; "
                        "choose a new directory, or pass --force to reuse this one (the "
                        "earlier run's files are removed)")
                for name in (*RUN_FILES, *extra_files):
                    old = path / name
                    if not old.is_symlink():  # a link placed on purpose is written through
                        old.unlink(missing_ok=True)
            path.mkdir(parents=True, exist_ok=True)
        else:
            base = Path("runs") / f"{datetime.now():%Y%m%d-%H%M%S}-{kind}"
            for n in itertools.count(1):
                path = base if n == 1 else base.with_name(f"{base.name}-{n}")
                try:
                    path.mkdir(parents=True, exist_ok=False)
                    break
                except FileExistsError:
                    continue
        probe = path / ".write-test"
        probe.write_text("")
        probe.unlink()
    except OSError as exc:
        raise UserError(
            f"cannot write the run directory {str(arg or 'runs/')!r}: "
            f"{exc.strerror or exc}. Choose a writable place with --out DIR."
        ) from exc
    return path


@contextmanager
def run_dir(arg: str | None, kind: str, force: bool = False,
             extra_files: Sequence[str] = ()) -> Iterator[Path]:
    """:func:`out_dir`, removed again if the run fails to start (an error raised before it
    wrote its results: a failed start leaves no directory, not even the bus log of its
    configuration). A directory that existed before is left as it was."""
    existed = bool(arg) and Path(arg).exists()
    parent_existed = Path(arg).parent.exists() if arg else Path("runs").exists()
    path = out_dir(arg, kind, force, extra_files)
    try:
        yield path
    except BaseException:
        if not existed and not (path / "signals.csv").exists():
            with suppress(OSError):
                for name in (*RUN_FILES, *extra_files):
                    (path / name).unlink(missing_ok=True)
                path.rmdir()  # only when empty: nothing else of the user's is removed
                if not parent_existed:
                    path.parent.rmdir()
        raise
