"""A run's figures drawn by a worker process that got ready while the run went on.

Most of what `hil-gateway simulate` costs is the figures, and a third of that is
matplotlib's import and the font. :meth:`FigureWorker.start` forks a child before the run
(Linux, a process with no other thread, matplotlib installed; otherwise there is no worker
and the figures are drawn in the process as before): it imports matplotlib and loads the
font while the parent simulates, then waits. When the figures are due
(:func:`gateway.figures.plot_figures` with ``worker=``), the parent pickles the job to a
temporary file, tells the worker where, and waits for the answer; the worker draws Fig. 3 in
a process forked from itself (nothing to import again) beside the other figures, so the
two cores draw at once.

Nothing is lost and nothing is reported written that is not: each figure is written under
a temporary name and renamed when complete (:func:`gateway.figures.draw`); the worker
ignores SIGINT and SIGTERM (the parent decides when a run stops, and waits for its files as
it would for figures drawn in process: a second Ctrl-C cannot lose them); a worker that
died or answered nothing makes the parent draw the figures itself; a figure that failed is
the parent's exception, as in process (an OSError where a file could not be written); a
parent that goes away leaves the worker an end of file, and it exits.
"""

from __future__ import annotations

import contextlib
import importlib.util
import logging
import os
import pickle
import signal
import struct
import sys
import tempfile
import threading
from pathlib import Path
from typing import Any

from gateway import figures
from gateway.figures import FigureJob

log = logging.getLogger(__name__)

#: Drawn in a process of its own beside the others: the figure that takes longest.
APART = "fig3_currents_voltages.png"

Outcome = tuple[str, Any] | None  # None: written; else (exception type, details)


class FigureWorker:
    """A child process ready to draw a run's figures (:meth:`start`); one job, then it
    exits. Close it (:meth:`close`) whether it drew or not."""

    def __init__(self, pid: int, to_child: int, from_child: int) -> None:
        self.pid = pid
        self._to = to_child
        self._from = from_child

    @classmethod
    def start(cls, nice: int = 0) -> FigureWorker | None:
        """Fork the worker, at ``nice`` (a bus run's: its loop comes first); None where this
        process cannot (not Linux, another thread running, no matplotlib)."""
        if (sys.platform != "linux" or threading.active_count() > 1
                or importlib.util.find_spec("matplotlib") is None):
            return None
        down_r, down_w = os.pipe()  # parent → worker: where the job is
        up_r, up_w = os.pipe()  # worker → parent: the outcome
        for stream in (sys.stdout, sys.stderr):  # not written twice by the child
            with contextlib.suppress(Exception):
                stream.flush()
        pid = os.fork()
        if pid == 0:  # the worker: never returns into the caller's code
            code = 1
            try:
                os.close(down_w)
                os.close(up_r)
                code = _serve(down_r, up_w, nice)
            finally:
                os._exit(code)
        os.close(down_r)
        os.close(up_w)
        return cls(pid, down_w, up_r)

    def draw(self, job: FigureJob) -> list[Path]:
        """The figures of ``job``, drawn by the worker (by this process if the worker is
        gone); the paths written. Raises what drawing raised."""
        answer = None
        try:
            fd, name = tempfile.mkstemp(prefix="hil-figures-", suffix=".pickle")
            try:
                with os.fdopen(fd, "wb") as f:
                    pickle.dump(job, f, protocol=pickle.HIGHEST_PROTOCOL)
                _send(self._to, name.encode())
                answer = _receive(self._from)
            finally:
                Path(name).unlink(missing_ok=True)
        except Exception as exc:  # not handed over (a full temp dir, a worker gone): here
            log.debug("figure worker: %s", exc)
        finally:
            self.close()
        if answer is None:
            log.info("the figure worker did not answer: drawing the figures here")
            return figures.draw(job)
        ready, outcomes = pickle.loads(answer)
        if not ready:  # no matplotlib there: none here either
            return []
        names = figures.figure_names(job.sig)
        for name, outcome in zip(names, outcomes, strict=True):
            if outcome is not None:
                raise _exception(name, job.out_dir, outcome)
        return [job.out_dir / n for n in names]

    def close(self) -> None:
        """End the worker (unused: killed; used: it has exited) and reap it."""
        if self.pid is None:
            return
        for fd in (self._to, self._from):
            with contextlib.suppress(OSError):
                os.close(fd)
        with contextlib.suppress(ProcessLookupError):
            os.kill(self.pid, signal.SIGKILL)
        with contextlib.suppress(ChildProcessError):
            os.waitpid(self.pid, 0)
        self.pid = None  # type: ignore[assignment]

    def __enter__(self) -> FigureWorker:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()


# --------------------------------------------------------------------------- the worker


def _serve(down: int, up: int, nice: int) -> int:
    """The worker's life: get ready, wait for the job's file, draw, answer."""
    signal.signal(signal.SIGINT, signal.SIG_IGN)
    signal.signal(signal.SIGTERM, signal.SIG_IGN)
    if nice:
        os.nice(nice)
    ready = figures.warm_up()
    where = _receive(down)
    if where is None:  # the parent is done without figures, or gone
        return 0
    with open(where, "rb") as f:
        job: FigureJob = pickle.load(f)
    names = figures.figure_names(job.sig)
    outcomes: list[Outcome] = []
    if ready:
        apart = APART in names and len(names) > 1
        helper = _fork_drawing(job, [APART]) if apart else None
        mine = _draw_each(job, [n for n in names if not (apart and n == APART)])
        theirs = _join(helper) if helper is not None else None
        by_name = dict(zip([n for n in names if not (apart and n == APART)], mine,
                           strict=True))
        if helper is not None:
            by_name[APART] = theirs[0] if theirs is not None else ("RuntimeError", (
                "the process drawing it ended without an answer",))
        outcomes = [by_name[n] for n in names]
    _send(up, pickle.dumps((ready, outcomes)))
    return 0


def _draw_each(job: FigureJob, names: list[str]) -> list[Outcome]:
    """Draw ``names`` one by one; each one's outcome (a failure does not stop the next)."""
    out: list[Outcome] = []
    for name in names:
        try:
            figures.draw(job, [name])
            out.append(None)
        except OSError as exc:
            out.append(("OSError", (exc.errno, exc.strerror, exc.filename)))
        except Exception as exc:
            out.append((type(exc).__name__, (str(exc),)))
    return out


def _fork_drawing(job: FigureJob, names: list[str]) -> tuple[int, int]:
    """Draw ``names`` in a process forked from this one: (its pid, the pipe it answers
    on)."""
    r, w = os.pipe()
    pid = os.fork()
    if pid == 0:
        code = 1
        try:
            os.close(r)
            _send(w, pickle.dumps(_draw_each(job, names)))
            code = 0
        finally:
            os._exit(code)
    os.close(w)
    return pid, r


def _join(helper: tuple[int, int]) -> list[Outcome] | None:
    pid, r = helper
    try:
        answer = _receive(r)
    finally:
        os.close(r)
        os.waitpid(pid, 0)
    return None if answer is None else pickle.loads(answer)


def _exception(name: str, out_dir: Path, outcome: tuple[str, Any]) -> Exception:
    """The parent's exception for a figure the worker could not draw."""
    kind, details = outcome
    if kind == "OSError":
        errno, strerror, filename = details
        return OSError(errno, strerror, filename or str(out_dir / name))
    return RuntimeError(f"drawing {name} failed: {kind}: {details[0]}")


# --------------------------------------------------------------------------- messages


def _send(fd: int, data: bytes) -> None:
    """One message: its length (8 bytes), then the bytes."""
    view = memoryview(struct.pack("<Q", len(data)) + data)
    while view:
        view = view[os.write(fd, view):]


def _receive(fd: int) -> bytes | None:
    """One message, or None at an end of file."""
    head = _read_exactly(fd, 8)
    if head is None:
        return None
    return _read_exactly(fd, struct.unpack("<Q", head)[0])


def _read_exactly(fd: int, n: int) -> bytes | None:
    parts = []
    while n:
        chunk = os.read(fd, n)
        if not chunk:
            return None
        parts.append(chunk)
        n -= len(chunk)
    return b"".join(parts)
