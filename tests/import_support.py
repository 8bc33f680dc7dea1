"""What a fresh interpreter imports: the tests that keep heavy packages (python-can,
canopen, cantools, matplotlib, scipy.signal) out of a command's start-up."""

from __future__ import annotations

import json
import os
import subprocess
import sys
from collections.abc import Iterable, Mapping
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]


def loaded_after(code: str, names: Iterable[str], env: Mapping[str, str] | None = None
                 ) -> list[str]:
    """Run ``code`` in a new interpreter (in the repository, with ``env`` added to this
    process's environment); the ``names`` (packages or modules) it has then imported,
    sorted: a name counts when it or one of its submodules is in ``sys.modules``."""
    probe = (f"{code}\nimport json, sys\nprint(json.dumps(sorted(n for n in "
             f"{sorted(set(names))!r} if any(m == n or m.startswith(n + '.') "
             "for m in sys.modules))))")
    done = subprocess.run([sys.executable, "-c", probe], capture_output=True, text=True,
                          check=True, cwd=ROOT, env={**os.environ, **(env or {})})
    return json.loads(done.stdout.strip().splitlines()[-1])
