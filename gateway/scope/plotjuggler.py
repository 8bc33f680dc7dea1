"""The live scope's rows streamed to PlotJuggler (``--plotjuggler [HOST:]PORT``).

PlotJuggler's "UDP Server" data streamer with the JSON message protocol plots every numeric
field of the JSON objects it receives. :class:`UdpJsonSink` watches a
:class:`gateway.scope.feed.ScopeFeed` like a browser does (the same decimation, the same
bounded queue: a loop never waits for it) and sends each row as one datagram,
``{"t": 0.123, "w_m": 101.2, ...}`` (non-finite values left out); in PlotJuggler choose
"use field as timestamp": ``t``. The host is 127.0.0.1 unless given.
"""

from __future__ import annotations

import json
import queue
import socket
import threading
from typing import Any

from gateway.scope.feed import ScopeFeed

#: PlotJuggler's default UDP port.
DEFAULT_PORT = 9870


class UdpJsonSink:
    """Rows of ``feed`` as JSON datagrams to ``(host, port)``, from a thread of its own,
    until :meth:`close`."""

    def __init__(self, feed: ScopeFeed, host: str, port: int) -> None:
        self.address = (host, port)
        self.sent = 0  # datagrams sent
        self.errors = 0  # datagrams the system refused (no route, buffer full)
        self._feed = feed
        self._client = feed.subscribe()
        self._sock = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._run, name="plotjuggler", daemon=True)
        self._thread.start()

    def _run(self) -> None:
        while True:
            try:
                event, data = self._client.queue.get(timeout=0.05)
            except queue.Empty:
                if self._stop.is_set():
                    return
                continue
            if event == "rows":
                self._send_rows(json.loads(data))

    def _send_rows(self, batch: dict[str, Any]) -> None:
        columns: dict[str, list[Any]] = batch.get("columns", {})
        names = list(columns)
        for i in range(int(batch.get("n", 0))):
            row = {n: columns[n][i] for n in names if columns[n][i] is not None}
            try:
                self._sock.sendto(json.dumps(row).encode(), self.address)
                self.sent += 1
            except OSError:
                self.errors += 1

    def close(self) -> None:
        """Send what is queued, then stop."""
        self._stop.set()
        self._thread.join(timeout=5.0)
        self._feed.unsubscribe(self._client)
        self._sock.close()

    def account(self) -> str:
        """What was sent, for the terminal."""
        host, port = self.address
        extra = f" ({self.errors} refused by the system)" if self.errors else ""
        return f"plotjuggler: {self.sent} rows sent to udp://{host}:{port}{extra}"
