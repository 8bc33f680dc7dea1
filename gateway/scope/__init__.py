"""The live scope: a local web page that plots a run's signals while it happens
(``--scope [HOST:]PORT`` on ``simulate``, ``sim``, ``run`` and ``log``), or a finished run
(``hil-gateway scope RUN_DIR``).

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
def live_scope(address: str | None, title: str) -> Iterator[ScopeFeed | None]:
    """A feed served at ``address`` ([HOST:]PORT) for the duration of the block, its URL
    printed on stderr; None (nothing served) when ``address`` is None."""
    if address is None:
        yield None
        return
    host, port = parse_address(address)
    feed = ScopeFeed(title)
    server = ScopeServer(feed, host, port)
    print(f"scope: {server.url} (open it in a browser; it shows the run while it happens)",
          file=sys.stderr, flush=True)
    try:
        yield feed
    finally:
        server.close()
