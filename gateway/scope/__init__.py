"""The live scope: a local web page that plots a run's signals while it happens
(``--scope [HOST:]PORT`` on ``simulate``, ``sim``, ``run`` and ``log``), or a finished run
(``hil-gateway scope RUN_DIR``); the same rows streamed to PlotJuggler
(``--plotjuggler [HOST:]PORT``, :mod:`gateway.scope.plotjuggler`).

:mod:`gateway.scope.feed` reads the run's record from its own thread and decimates it;
:mod:`gateway.scope.server` serves the page (``static/``: HTML, JavaScript and CSS, no
library and no network beyond the loopback) and the stream of batches.
"""

from __future__ import annotations

import contextlib
import sys
from collections.abc import Iterator

from gateway.scope.feed import ScopeFeed
from gateway.scope.server import ScopeServer, parse_address

__all__ = ["ScopeFeed", "ScopeServer", "live_scope", "parse_address"]


@contextlib.contextmanager
def live_scope(address: str | None, title: str, plotjuggler: str | None = None
               ) -> Iterator[ScopeFeed | None]:
    """A feed served at ``address`` ([HOST:]PORT) for the duration of the block, its URL
    printed on stderr, and/or streamed to PlotJuggler at ``plotjuggler`` ([HOST:]PORT,
    :mod:`gateway.scope.plotjuggler`); None (nothing watches) when neither is given."""
    if address is None and plotjuggler is None:
        yield None
        return
    feed = ScopeFeed(title)
    server = sink = None
    try:
        if address is not None:
            host, port = parse_address(address)
            server = ScopeServer(feed, host, port)
            print(f"scope: {server.url} (open it in a browser; it shows the run while it "
                  "happens)", file=sys.stderr, flush=True)
        if plotjuggler is not None:
            from gateway.scope.plotjuggler import UdpJsonSink

            sink = UdpJsonSink(feed, *parse_address(plotjuggler, "--plotjuggler"))
            host, port = sink.address
            print(f"plotjuggler: streaming to udp://{host}:{port} (PlotJuggler: UDP Server, "
                  "JSON, timestamp field t)", file=sys.stderr, flush=True)
        yield feed
    finally:
        if sink is not None:
            sink.close()
            print(sink.account(), file=sys.stderr, flush=True)
        if server is not None:
            server.close()
