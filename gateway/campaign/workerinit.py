"""Preloaded into the local cluster's worker processes (Dask's ``preload``): Ctrl-C at the
terminal reaches every process of the campaign, and it is the campaign's to handle (it
records what came back, then closes the cluster); a worker ignores it instead of dying
with a traceback."""

from __future__ import annotations

import signal
from typing import Any


def dask_setup(worker: Any) -> None:
    """Dask's preload hook, in the worker process's main thread."""
    signal.signal(signal.SIGINT, signal.SIG_IGN)
