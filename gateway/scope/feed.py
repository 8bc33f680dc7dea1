"""What the live scope shows: rows of a run, decimated to the display rate, fanned out to
each watching browser through a bounded queue.

The loop never waits for the scope: the loop appends rows to its record as it always does;
a feed thread reads the new rows every :data:`POLL_S` (a list read, no lock the loop
takes), keeps every k-th row so that at most :data:`DISPLAY_RATE` rows per second of run
time are sent, and puts one batch per poll into each client's queue. A client too slow to
take its batches loses the oldest ones; the rows lost are counted (:meth:`ScopeFeed.stats`,
``scope.dropped_rows`` in summary.json).

A batch is JSON: ``{"t": [...], "columns": {name: [...]}, "cycles": n}``; non-finite
values are ``null``. The feed also holds a decimated history (the last
:data:`HISTORY_ROWS` rows) that a browser joining late receives first, and the run's state
(running, or stopped with its reason), sent as its own event.
"""

from __future__ import annotations

import json
import math
import queue
import threading
from collections import deque
from collections.abc import Iterable, Sequence
from typing import Any

__all__ = ["DISPLAY_RATE", "HISTORY_ROWS", "POLL_S", "Client", "LatestValues", "ScopeFeed"]

#: How often the feed reads new rows, s.
POLL_S = 0.05
#: Rows per second of run time sent at most (per signal).
DISPLAY_RATE = 500.0
#: Rows of decimated history kept for a browser that joins late.
HISTORY_ROWS = 20000
#: Batches a client may have waiting before the oldest is dropped.
CLIENT_QUEUE = 64


def _finite(x: Any) -> Any:
    """A JSON-safe value: floats that are not finite become None."""
    if isinstance(x, float) and not math.isfinite(x):
        return None
    return x


class Client:
    """One watching browser: a bounded queue of events (name, JSON text)."""

    def __init__(self) -> None:
        self.queue: queue.Queue[tuple[str, str]] = queue.Queue(CLIENT_QUEUE)
        self.dropped_rows = 0

    def put(self, event: str, data: str, rows: int = 0) -> None:
        """Queue an event; when full, drop the oldest queued event (counting its rows)."""
        while True:
            try:
                self.queue.put_nowait((event, data))
                return
            except queue.Full:
                try:
                    old_event, old = self.queue.get_nowait()
                except queue.Empty:
                    continue
                if old_event == "rows":
                    self.dropped_rows += int(json.loads(old).get("n", 0))


class ScopeFeed:
    """The live view's source (a :class:`gateway.session.Watcher`): ``attach`` a record,
    or ``load`` finished columns; :meth:`subscribe` a client; :meth:`close` at the end."""

    def __init__(self, title: str = "", display_rate: float = DISPLAY_RATE) -> None:
        self.title = title
        self.display_rate = display_rate
        self.columns: tuple[str, ...] = ()
        self._rows: Sequence[tuple] | None = None
        self._read = 0  # rows of the record read so far
        self._step = 1  # keep every step-th row
        self._history: deque[list[Any]] = deque(maxlen=HISTORY_ROWS)
        self._clients: list[Client] = []
        self._lock = threading.Lock()
        self._take_lock = threading.Lock()
        self._state: dict[str, Any] = {"running": False, "cycles": 0}
        self._sent_rows = 0
        self._dropped_gone = 0  # rows dropped for clients since gone
        self._stop = threading.Event()
        self._thread: threading.Thread | None = None

    # ---------------------------------------------------------------- sources

    def attach(self, record: Any) -> None:
        """A run's record (:class:`gateway.report.Record`), before its first row: the feed
        thread starts reading it."""
        self._start(tuple(record.columns), record._rows)
        self._state = {"running": True, "cycles": 0}
        self._publish_meta()
        self._thread = threading.Thread(target=self._poll, name="scope-feed", daemon=True)
        self._thread.start()

    def load(self, columns: dict[str, Any]) -> None:
        """A finished run's columns (name → array, ``t`` first): all of it at once."""
        names = tuple(columns)
        rows = list(zip(*(list(map(float, columns[n])) for n in names), strict=True))
        self._start(names, rows)
        self._step = max(self._step, math.ceil(len(rows) / HISTORY_ROWS))  # all of it
        self._take(len(rows))
        self._state = {"running": False, "cycles": len(rows), "stop": "finished run"}

    def _start(self, columns: tuple[str, ...], rows: Sequence[tuple]) -> None:
        self.columns, self._rows, self._read = columns, rows, 0
        self._step = 1
        if "t" in columns and len(rows) >= 2:
            self._set_step(rows)

    def _set_step(self, rows: Sequence[tuple]) -> None:
        k = self.columns.index("t")
        dt = rows[1][k] - rows[0][k]
        if dt > 0:
            self._step = max(1, math.ceil(1.0 / (dt * self.display_rate)))

    # ---------------------------------------------------------------- the thread

    def _poll(self) -> None:
        while not self._stop.wait(POLL_S):
            self._take()
        self._take()

    def _take(self, upto: int | None = None) -> None:
        """Read the rows appended since the last read, decimate, send one batch (one reader
        at a time: the feed thread, or the end of the run)."""
        with self._take_lock:
            self._take_locked(upto)

    def _take_locked(self, upto: int | None) -> None:
        rows = self._rows
        if rows is None:
            return
        n = len(rows) if upto is None else upto
        if n <= self._read:
            return
        if self._read < 2 <= n and self._step == 1:
            self._set_step(rows)
        first = -(-self._read // self._step) * self._step  # the next multiple of step
        kept = [[_finite(x) for x in rows[i]] for i in range(first, n, self._step)]
        self._read = n
        self._state["cycles"] = n
        if not kept:
            return
        data = json.dumps(self._batch(kept, n))
        with self._lock:  # a client subscribing now gets this batch in its history or here
            self._history.extend(kept)
            self._sent_rows += len(kept)
            for c in self._clients:
                c.put("rows", data, len(kept))

    def _batch(self, kept: Iterable[list[Any]], cycles: int) -> dict[str, Any]:
        cols = list(zip(*kept, strict=True))
        return {"n": len(cols[0]) if cols else 0, "cycles": cycles,
                "columns": {name: list(col) for name, col in zip(self.columns, cols,
                                                                   strict=True)}}

    # ---------------------------------------------------------------- clients

    def subscribe(self) -> Client:
        """A new client, given the meta, the history so far and the state first."""
        c = Client()
        with self._lock:  # meta, history and state first, then the batches that follow
            c.put("meta", self._meta())
            if self._history:
                c.put("rows", json.dumps(self._batch(self._history,
                                                     self._state.get("cycles", 0))))
            c.put("state", json.dumps(self._state, default=str))
            self._clients.append(c)
        return c

    def unsubscribe(self, c: Client) -> None:
        with self._lock:
            if c in self._clients:
                self._clients.remove(c)
                self._dropped_gone += c.dropped_rows

    def _meta(self) -> str:
        return json.dumps({"title": self.title, "columns": list(self.columns),
                           "display_rate": self.display_rate, "step": self._step})

    def _publish_meta(self) -> None:
        """The columns (and the state) to the clients that came before the run began."""
        meta, state = self._meta(), json.dumps(self._state, default=str)
        with self._lock:
            for c in self._clients:
                c.put("meta", meta)
                c.put("state", state)

    def _publish_state(self) -> None:
        data = json.dumps(self._state, default=str)
        with self._lock:
            for c in self._clients:
                c.put("state", data)

    # ---------------------------------------------------------------- the end

    def stats(self) -> dict[str, Any]:
        """The feed's account: rows sent (decimated), rows dropped for slow clients, the
        decimation and the clients watching."""
        self._stop.set()
        if self._thread is not None:
            self._thread.join(timeout=2.0)
        with self._lock:
            dropped = self._dropped_gone + sum(c.dropped_rows for c in self._clients)
            clients = len(self._clients)
        return {"sent_rows": self._sent_rows, "dropped_rows": dropped,
                "decimation": self._step, "clients": clients}

    def finish(self, summary: dict[str, Any]) -> None:
        """The run ended: its last rows, then its stop reason and errors, to every
        client."""
        self._take()
        run = summary.get("run", {})
        speed = summary.get("speed_error", {})
        self._state = {"running": False, "cycles": self._state.get("cycles", 0),
                       "stop": run.get("stop"), "stop_reason": run.get("stop_reason"),
                       "speed_error_rms": speed.get("rms")}
        self._publish_state()

    def close(self) -> None:
        """Stop the feed thread (the clients see no more rows)."""
        self._stop.set()


class LatestValues:
    """Rows for the scope from decoded frames (``hil-gateway log --scope``): the latest value
    of every signal, one row per ``period`` of bus time at most (``columns``, ``t`` first,
    time from the first frame), so that the feed sees a regular record."""

    def __init__(self, signals: Iterable[str], period: float = 1.0 / DISPLAY_RATE) -> None:
        self.columns: tuple[str, ...] = ("t", *signals)
        self._index = {name: k for k, name in enumerate(self.columns)}
        self._latest: list[float] = [math.nan] * len(self.columns)
        self._rows: list[tuple] = []
        self._period = period
        self._t0: float | None = None
        self._next = 0.0

    def update(self, t: float, values: dict[str, Any]) -> None:
        """A decoded frame at time ``t`` (s) with its signals' values."""
        if self._t0 is None:
            self._t0 = t
        for name, value in values.items():
            k = self._index.get(name)
            if k is not None and isinstance(value, int | float):
                self._latest[k] = float(value)
        rel = t - self._t0
        if rel >= self._next:
            self._latest[0] = rel
            self._rows.append(tuple(self._latest))
            self._next = rel + self._period
