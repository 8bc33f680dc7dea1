"""Where a campaign's batches of points run: in this process, or on Dask.

:class:`InProcess` runs each batch here, one after the other (for debugging: a breakpoint
or a traceback is where it looks). :class:`DaskEngine` runs them on a `distributed`
cluster: a LocalCluster sized to the machine (worker processes of one thread each: the
simulation is pure Python, threads would only share the GIL, and a `sim` point's emulator
and gateway must have their process to themselves), bound to 127.0.0.1, or an existing
scheduler (``--scheduler tcp://HOST:PORT``) whose workers the user started.

A worker that dies while it runs a batch fails the batch with Dask's KilledWorker (at
once on the local cluster: its scheduler retries nothing, ``allowed-failures`` 0; an
existing scheduler after its own retries); :class:`Done` says so (``died``) and the runner
runs the batch's points again one by one, so that only a point that kills its worker
again becomes a row, and the innocent ones of its batch run.
"""

from __future__ import annotations

import contextlib
import logging
import os
from collections import deque
from collections.abc import Sequence
from dataclasses import dataclass
from typing import Any, Protocol

from gateway.campaign.options import Command
from gateway.campaign.points import PointConfig
from gateway.campaign.runpoint import BatchResult, Limits, run_batch
from gateway.errors import UserError

log = logging.getLogger(__name__)


@dataclass
class Done:
    """A batch that came back: its ``result``, or ``died`` (why its worker is gone)."""

    batch: Sequence[PointConfig]
    result: BatchResult | None = None
    died: str = ""
    worker: str = ""


class Engine(Protocol):
    """What the runner needs of an engine."""

    description: str
    dashboard: str | None

    @property
    def capacity(self) -> int:
        """How many points run at once."""
        ...

    def submit(self, batch: Sequence[PointConfig], limits: Limits) -> Any: ...

    def wait(self, timeout: float) -> list[tuple[Any, Done]]: ...

    def cancel(self, handle: Any) -> None: ...

    def restart(self, worker: str) -> None: ...

    def threads(self) -> int:
        """How many points could run at once now (0: no worker at the moment)."""
        ...

    def close(self) -> None: ...


class InProcess:
    """Batches run here, in submission order."""

    description = "in this process"
    dashboard = None

    def __init__(self) -> None:
        self._queue: deque[tuple[int, Sequence[PointConfig], Limits]] = deque()
        self._n = 0

    @property
    def capacity(self) -> int:
        return 1

    def submit(self, batch: Sequence[PointConfig], limits: Limits) -> Any:
        self._n += 1
        self._queue.append((self._n, batch, limits))
        return self._n

    def wait(self, timeout: float) -> list[tuple[Any, Done]]:
        if not self._queue:
            return []
        handle, batch, limits = self._queue.popleft()
        return [(handle, Done(batch, run_batch(batch, limits), worker="in-process"))]

    def cancel(self, handle: Any) -> None:
        self._queue = deque(q for q in self._queue if q[0] != handle)

    def restart(self, worker: str) -> None:
        """A run left behind here goes on in its daemon thread until the campaign ends."""

    def threads(self) -> int:
        return 1

    def close(self) -> None:
        self._queue.clear()


def _on_worker(batch: Sequence[PointConfig], limits: Limits) -> tuple[BatchResult, str]:
    """The task a Dask worker runs: the batch, and the worker's address."""
    from distributed import get_worker

    return run_batch(batch, limits), get_worker().address


def machine_workers() -> int:
    """The local cluster's default size: the cores this process may use."""
    try:
        return max(1, len(os.sched_getaffinity(0)))
    except AttributeError:  # pragma: no cover - not Linux
        return max(1, os.cpu_count() or 1)


class DaskEngine:
    """Batches on a Dask cluster: ``scheduler`` (an address; None: a LocalCluster of
    ``workers`` processes, default :func:`machine_workers`, its dashboard at
    ``dashboard``, [HOST:]PORT on 127.0.0.1)."""

    def __init__(self, command: Command, scheduler: str | None = None,
                 workers: int | None = None, dashboard: str = "127.0.0.1:0",
                 connect_timeout: float = 30.0) -> None:
        try:
            import dask
            import distributed
        except ImportError as exc:
            raise UserError("running a campaign on Dask needs the optional extra 'campaign' "
                            "(distributed): pip install 'can-drive-hil[campaign]' "
                            "(scripts/bootstrap installs it), or run it here with "
                            "--in-process") from exc
        self._distributed = distributed
        # what matters of Dask's errors (a worker that died) becomes the table's rows; its
        # workers' complaints while the cluster closes are noise (--debug shows them all)
        quiet = logging.DEBUG if logging.getLogger().isEnabledFor(logging.DEBUG) else (
            logging.CRITICAL)
        logging.getLogger("distributed").setLevel(quiet)
        self.cluster: Any = None
        self.command = command
        if scheduler is not None:
            try:
                self.client = distributed.Client(scheduler, timeout=connect_timeout)
            except (OSError, TimeoutError) as exc:
                raise UserError(f"--scheduler {scheduler}: no Dask scheduler answered "
                                f"({exc}); start one (dask scheduler) and its workers (dask "
                                "worker ADDRESS --nthreads 1), or leave --scheduler out for "
                                "a local cluster") from exc
            self.description = f"Dask scheduler {scheduler}"
        else:
            n = workers or machine_workers()
            config = {"distributed.scheduler.allowed-failures": 0,
                      "distributed.scheduler.worker-saturation": 1.0,
                      "distributed.worker.memory.target": False,
                      "distributed.worker.memory.spill": False,
                      # the workers' statistical profiler samples every thread's stack
                      # every 10 ms for the dashboard's Profile page: 10 % of a worker's
                      # time on short points (bench/bench_campaign.py, 1 worker)
                      "distributed.worker.profile.enabled": False}
            with dask.config.set(config):
                self.cluster = distributed.LocalCluster(
                    n_workers=n, threads_per_worker=1, processes=True, host="127.0.0.1",
                    dashboard_address=dashboard, silence_logs=quiet,
                    preload=["gateway.campaign.workerinit"])
            self.client = distributed.Client(self.cluster)
            self.description = (f"local Dask cluster of {n} worker process"
                                f"{'es' if n > 1 else ''}, one thread each")
        self.dashboard = self.client.dashboard_link if self._has_dashboard() else None
        self._futures: dict[Any, Sequence[PointConfig]] = {}
        self._wait_for_workers(connect_timeout)

    def _has_dashboard(self) -> bool:
        with contextlib.suppress(Exception):
            return bool(self.client.scheduler_info().get("services", {}).get("dashboard"))
        return False

    def _wait_for_workers(self, timeout: float) -> None:
        try:
            self.client.wait_for_workers(1, timeout=timeout)
        except (TimeoutError, OSError) as exc:
            self.close()
            raise UserError(f"{self.description}: no worker joined within {timeout:g} s; "
                            "start workers (dask worker ADDRESS --nthreads 1)") from exc
        threads = self.client.nthreads()
        if self.command is Command.SIM and any(n > 1 for n in threads.values()):
            self.close()
            raise UserError(f"{self.description}: a sim point needs its worker process to "
                            "itself (its emulator and gateway run there), and some workers "
                            "run several threads; start them with dask worker ADDRESS "
                            "--nthreads 1")

    @property
    def capacity(self) -> int:
        return max(1, sum(self.client.nthreads().values()))

    def submit(self, batch: Sequence[PointConfig], limits: Limits) -> Any:
        future = self.client.submit(_on_worker, list(batch), limits, pure=False)
        self._futures[future] = batch
        return future

    def wait(self, timeout: float) -> list[tuple[Any, Done]]:
        d = self._distributed
        pending = list(self._futures)
        if not pending:
            return []
        try:
            finished = d.wait(pending, timeout=timeout, return_when="FIRST_COMPLETED").done
        except TimeoutError:
            return []
        out = []
        for fut in finished:
            batch = self._futures.pop(fut)
            if fut.status == "finished":
                result, worker = fut.result()
                out.append((fut, Done(batch, result, worker=worker)))
            elif fut.status == "error":
                exc = fut.exception()
                if isinstance(exc, d.KilledWorker):
                    out.append((fut, Done(batch, died=str(exc))))
                else:
                    raise UserError(f"{self.description}: a batch failed on its worker, not "
                                    f"in a run ({type(exc).__name__}: {exc}); the workers "
                                    "need can-drive-hil importable (the same environment, "
                                    "PYTHONPATH)") from exc
        return out

    def cancel(self, handle: Any) -> None:
        self._futures.pop(handle, None)
        with contextlib.suppress(Exception):
            handle.cancel()

    def restart(self, worker: str) -> None:
        """A run was left behind in ``worker``: restart the process (its nanny's)."""
        try:
            self.client.restart_workers([worker], timeout=60)
        except Exception as exc:
            log.warning("could not restart %s (%s); its run left behind goes on there",
                        worker, exc)

    def threads(self) -> int:
        return sum(self.client.nthreads().values())

    def close(self) -> None:
        with contextlib.suppress(Exception):
            for fut in list(self._futures):
                fut.cancel()
            self._futures.clear()
            self.client.close(timeout=10)
        if self.cluster is not None:
            with contextlib.suppress(Exception):
                self.cluster.close(timeout=10)
