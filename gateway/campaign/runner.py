"""A campaign: skip the points already in the table, run the rest on an engine, record each
batch as it comes back.

Batches are sized to take about a second each (from the points' wall times so far; a
single point at first), never more than keeps every worker busy to the end, and at most
two per worker are in flight: a Ctrl-C, a SIGTERM or a crash loses only those. A batch
whose worker died is split and its points retried alone; a point whose worker dies again
becomes a row (``worker-died``). A batch that does not come back long after its time
limits (a worker that hangs without dying) is cancelled and its points become rows
(``timeout``). Nothing waits for ever.
"""

from __future__ import annotations

import fcntl
import json
import math
import signal
import time
from collections import deque
from collections.abc import Callable, Iterator, Sequence
from contextlib import contextmanager
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from gateway.atomicfile import write_text_atomic
from gateway.campaign.engine import Done, Engine
from gateway.campaign.model import Axis, AxisKind, Campaign, Dist
from gateway.campaign.points import PointConfig, record_fields
from gateway.campaign.runpoint import (
    EXIT_TIMEOUT,
    EXIT_WORKER_DIED,
    Limits,
    PointStatus,
    outcome,
)
from gateway.campaign.table import META, ResultTable
from gateway.errors import UserError

#: A batch's target duration, s, and its largest size.
BATCH_SECONDS = 1.0
BATCH_MAX = 64
#: Batches in flight per point that runs at once.
IN_FLIGHT = 2
#: How often the engine is asked whether it still has workers, s, and how long it may
#: have none (its nannies restarting them) before the campaign stops.
CHECK_EVERY = 5.0
NO_WORKERS_GRACE = 120.0


def param_types(campaign: Campaign) -> dict[str, str]:
    """Each axis's column type: float64, int64, bool or string."""
    out: dict[str, str] = {}
    for ax in campaign.axes:
        out[ax.key] = _axis_type(ax)
    return out


def _axis_type(ax: Axis) -> str:
    if ax.kind is AxisKind.SETTINGS:
        return "string"
    if ax.dist is not None and ax.dist.dist is not Dist.CHOICE:
        return "int64" if ax.dist.dist is Dist.INTEGERS else "float64"
    values = ax.dist.values if ax.dist is not None else ax.values
    if all(isinstance(v, bool) for v in values):
        return "bool"
    if all(isinstance(v, int) and not isinstance(v, bool) for v in values):
        return "int64"
    if all(isinstance(v, int | float) and not isinstance(v, bool) for v in values):
        return "float64"
    return "string"


def campaign_meta(campaign: Campaign) -> dict[str, Any]:
    """What the table keeps of its campaign (campaign.json and the Parquet metadata)."""
    return {"name": campaign.name, "command": campaign.command.value,
            "description": campaign.description, "source": campaign.source,
            "text": campaign.text, "params": param_types(campaign),
            "axes": [{"key": ax.key, "kind": ax.kind.value,
                      "grid": ax.dist is None,
                      "values": [str(v) for v in ax.values]} for ax in campaign.axes],
            "random_n": campaign.n,
            "criteria": [{"metric": c.metric, "op": c.op.value, "threshold": c.threshold}
                         for c in campaign.criteria]}


@dataclass
class Outcome:
    """What a campaign run did: points in the campaign, already done before, run now,
    whether it was interrupted, the final table."""

    total: int
    before: int
    ran: int = 0
    interrupted: bool = False
    table: Any = None
    seconds: float = 0.0
    rows_now: list[dict[str, Any]] = field(default_factory=list)


@contextmanager
def lock(directory: Path) -> Iterator[None]:
    """One campaign at a time in a directory."""
    directory.mkdir(parents=True, exist_ok=True)
    f = (directory / ".lock").open("w")
    try:
        try:
            fcntl.flock(f, fcntl.LOCK_EX | fcntl.LOCK_NB)
        except OSError:
            raise UserError(f"{directory}: another campaign is running there; wait for it, "
                            "or choose another --out DIR") from None
        yield
    finally:
        f.close()


@contextmanager
def interrupts() -> Iterator[None]:
    """SIGTERM stops the campaign as Ctrl-C does (KeyboardInterrupt in the main thread)."""
    def handler(signum: int, frame: Any) -> None:
        raise KeyboardInterrupt

    old = signal.signal(signal.SIGTERM, handler)
    try:
        yield
    finally:
        signal.signal(signal.SIGTERM, old)


class BatchSizer:
    """Batch sizes that take about :data:`BATCH_SECONDS` each, from the wall times of the
    points so far (a running mean), balanced over the workers for the tail (with more
    than one point running at once)."""

    def __init__(self) -> None:
        self.mean: float | None = None

    def observe(self, walls: Sequence[float]) -> None:
        for w in walls:
            if math.isfinite(w):
                self.mean = w if self.mean is None else 0.8 * self.mean + 0.2 * w

    def size(self, remaining: int, capacity: int) -> int:
        if self.mean is None:
            return 1
        ideal = max(1, min(BATCH_MAX, round(BATCH_SECONDS / max(self.mean, 1e-4))))
        if capacity <= 1:  # one point at a time: nothing to balance, small batches cost
            return ideal
        balanced = max(1, math.ceil(remaining / (IN_FLIGHT * capacity)))
        return min(ideal, balanced)


def check_out(out: Path, campaign: Campaign) -> None:
    """``out`` is new, empty, or an earlier run's of this campaign (UserError otherwise)."""
    meta_file = out / META
    if meta_file.exists():
        try:
            old = json.loads(meta_file.read_text(encoding="utf-8"))
        except (OSError, ValueError) as exc:
            raise UserError(f"{meta_file}: cannot read it ({exc}); choose another --out DIR"
                            ) from exc
        if old.get("name") != campaign.name:
            raise UserError(f"--out {out}: holds campaign {old.get('name')!r}, not "
                            f"{campaign.name!r}; choose another directory")
    elif out.exists() and (not out.is_dir() or any(p.name != ".lock" for p in out.iterdir())):
        raise UserError(f"--out {out}: exists and is not a campaign's directory (no {META}); "
                        "choose a new directory, or the one of an earlier run of this campaign")


def prepare(out: Path, campaign: Campaign, retry_failed: bool
            ) -> tuple[ResultTable, set[str]]:
    """The table in ``out`` (a killed run's parts compacted first) and the hashes of the
    points already done (with ``retry_failed``: only those whose run gave a result)."""
    meta_file = out / META
    check_out(out, campaign)
    meta = campaign_meta(campaign)
    table = ResultTable(out, meta, meta["params"])
    table.clean()
    write_text_atomic(meta_file, json.dumps(meta, indent=1, ensure_ascii=False) + "\n")
    existing = table.compact()
    done: set[str] = set()
    if existing is not None:
        for h, status in zip(existing.column("hash").to_pylist(),
                             existing.column("status").to_pylist(), strict=True):
            if not retry_failed or PointStatus(status).ran:
                done.add(h)
    return table, done


def _row(point: PointConfig, out: dict[str, Any]) -> dict[str, Any]:
    return {"point": point.index, "hash": point.hash, **point.values, **out,
            **record_fields(point)}


def run(engine: Engine, todo: Sequence[PointConfig], table: ResultTable, limits: Limits,
        on_rows: Callable[[list[dict[str, Any]]], None]) -> list[dict[str, Any]]:
    """Run ``todo`` on ``engine``; each batch's rows appended to ``table`` as it comes back
    and passed to ``on_rows`` (the progress bar). Returns the rows written."""
    queue: deque[PointConfig] = deque(todo)
    alone: deque[PointConfig] = deque()  # from batches whose worker died: one at a time
    inflight: dict[Any, tuple[Sequence[PointConfig], float, bool]] = {}
    sizer = BatchSizer()
    written: list[dict[str, Any]] = []
    capacity = engine.capacity
    last_check = seen_workers = time.monotonic()
    per_point = limits.timeout + limits.grace

    def record(rows: list[dict[str, Any]]) -> None:
        table.append(rows)
        written.extend(rows)
        on_rows(rows)

    while queue or alone or inflight:
        while (alone or queue) and len(inflight) < IN_FLIGHT * capacity:
            if alone:
                batch, retry = [alone.popleft()], True
            else:
                n = sizer.size(len(queue), capacity)
                batch, retry = [queue.popleft() for _ in range(min(n, len(queue)))], False
            # the scheduler may run it twice (a worker lost), after one batch ahead of it
            deadline = time.monotonic() + 3 * len(batch) * per_point + 60.0
            inflight[engine.submit(batch, limits)] = (batch, deadline, retry)
        for handle, done in engine.wait(0.5):
            _, _, retry = inflight.pop(handle)
            rows = _rows_of(done, retry, alone)
            if done.result is not None:
                sizer.observe([r["wall_time_s"] for r in rows])
                if done.result.abandoned and done.worker:
                    engine.restart(done.worker)
            record(rows)
        now = time.monotonic()
        for handle, (batch, deadline, _) in list(inflight.items()):
            if now > deadline:
                engine.cancel(handle)
                del inflight[handle]
                record([_row(p, outcome(PointStatus.TIMEOUT, "no answer from the cluster "
                                        "long after the time limits of its batch (a worker "
                                        "hung?)", EXIT_TIMEOUT, math.nan)) for p in batch])
        if now - last_check > CHECK_EVERY:
            last_check = now
            threads = engine.threads()
            if threads:
                capacity, seen_workers = threads, now
            elif now - seen_workers > NO_WORKERS_GRACE:
                raise UserError(f"{engine.description}: no worker for "
                                f"{NO_WORKERS_GRACE:g} s; start workers (dask worker ADDRESS "
                                "--nthreads 1) and run the campaign again: it goes on where "
                                "it stopped", exit_code=1)
    return written


def _rows_of(done: Done, retry: bool, alone: deque[PointConfig]) -> list[dict[str, Any]]:
    """The rows of a batch that came back; a batch whose worker died goes back point by
    point, and a point alone whose worker died again is a row."""
    if done.result is not None:
        rows = [_row(p, done.result.outcomes[p.hash]) for p in done.batch
                if p.hash in done.result.outcomes]
        # the points after one left behind in its thread were not run: back in line
        alone.extend(p for p in done.batch if p.hash not in done.result.outcomes)
        return rows
    if len(done.batch) > 1 or not retry:
        alone.extend(done.batch)
        return []
    return [_row(p, outcome(PointStatus.WORKER_DIED, f"the worker process running it died "
                            f"(again when it ran alone): {done.died}", EXIT_WORKER_DIED,
                            math.nan)) for p in done.batch]
