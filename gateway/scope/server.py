"""The live scope's web server: the page and its assets (shipped in ``static/``, no network
beyond the loopback) and a server-sent-event stream of the feed's batches.

Routes: ``/`` the page, ``/scope.js``, ``/scope.css``, ``/events`` (``text/event-stream``:
``meta``, ``rows``, ``state`` events, see :mod:`gateway.scope.feed`). Bound to 127.0.0.1
unless told otherwise; port 0 takes a free port (:attr:`ScopeServer.url` says which).
"""

from __future__ import annotations

import http.server
import queue
import threading
from importlib import resources
from typing import Any

from gateway.errors import UserError
from gateway.scope.feed import ScopeFeed

__all__ = ["ScopeServer", "parse_address"]

_STATIC = {"/": ("index.html", "text/html; charset=utf-8"),
           "/index.html": ("index.html", "text/html; charset=utf-8"),
           "/scope.js": ("scope.js", "text/javascript; charset=utf-8"),
           "/scope.css": ("scope.css", "text/css; charset=utf-8")}
#: Seconds between keep-alive comments on an idle stream.
KEEPALIVE_S = 1.0


def parse_address(text: str, option: str = "--scope") -> tuple[str, int]:
    """``[HOST:]PORT`` → (host, port); host 127.0.0.1 by default; port 0..65535."""
    host, _, port = text.rpartition(":")
    host = host or "127.0.0.1"
    try:
        value = int(port)
    except ValueError:
        raise UserError(f"{option} {text}: give [HOST:]PORT, e.g. 8765 or 127.0.0.1:8765 "
                        "(0: any free port)") from None
    if not 0 <= value <= 65535:
        raise UserError(f"{option} {text}: a port is 0..65535")
    return host, value


def _asset(name: str) -> bytes:
    return (resources.files("gateway.scope") / "static" / name).read_bytes()


class _Handler(http.server.BaseHTTPRequestHandler):
    server: _Server
    protocol_version = "HTTP/1.1"

    def log_message(self, format: str, *args: Any) -> None:
        """Quiet: the run's output is the terminal's."""

    def do_GET(self) -> None:
        path = self.path.split("?", 1)[0]
        if path == "/events":
            self._events()
            return
        found = _STATIC.get(path)
        if found is None:
            self.send_error(404, "not a page of the scope")
            return
        body = _asset(found[0])
        self.send_response(200)
        self.send_header("Content-Type", found[1])
        self.send_header("Content-Length", str(len(body)))
        self.send_header("Cache-Control", "no-store")
        self.end_headers()
        self.wfile.write(body)

    def _events(self) -> None:
        feed = self.server.feed
        client = feed.subscribe()
        self.send_response(200)
        self.send_header("Content-Type", "text/event-stream")
        self.send_header("Cache-Control", "no-store")
        self.send_header("Connection", "close")
        self.end_headers()
        self.close_connection = True
        try:
            while not self.server.closing.is_set():
                try:
                    event, data = client.queue.get(timeout=KEEPALIVE_S)
                except queue.Empty:
                    self.wfile.write(b": keep-alive\n\n")
                    self.wfile.flush()
                    continue
                self.wfile.write(f"event: {event}\ndata: {data}\n\n".encode())
                self.wfile.flush()
        except (BrokenPipeError, ConnectionResetError, OSError):
            pass  # the browser went away
        finally:
            feed.unsubscribe(client)


class _Server(http.server.ThreadingHTTPServer):
    daemon_threads = True
    allow_reuse_address = True

    def __init__(self, address: tuple[str, int], feed: ScopeFeed) -> None:
        self.feed = feed
        self.closing = threading.Event()
        super().__init__(address, _Handler)


class ScopeServer:
    """Serves ``feed`` at ``host:port`` from a background thread; :meth:`close` stops it."""

    def __init__(self, feed: ScopeFeed, host: str = "127.0.0.1", port: int = 0) -> None:
        try:
            self._server = _Server((host, port), feed)
        except OSError as exc:
            raise UserError(f"the scope cannot listen on {host}:{port}: "
                            f"{exc.strerror or exc}; choose another port with --scope") from None
        self.feed = feed
        self._thread = threading.Thread(target=self._server.serve_forever,
                                         kwargs={"poll_interval": 0.1}, name="scope-http",
                                         daemon=True)
        self._thread.start()

    @property
    def url(self) -> str:
        host, port = self._server.server_address[:2]
        return f"http://{host}:{port}/"

    def close(self) -> None:
        """Stop serving; open streams end."""
        self._server.closing.set()
        self._server.shutdown()
        self._server.server_close()
        self.feed.close()
