"""The references a sampled-data controller's step looks at, each evaluated once.

The sampled-data design (:mod:`gateway.control.sampled`) takes the references at the
starts, midpoints and ends of the intervals from the one just ended to the one it commands:
the instants n·T/2 for n = 2(k − 1) … 2(k + d) + 2 at step k (delay d). Consecutive steps
share all but two of them. :class:`ReferenceWindow` holds them and slides on with the
steps, so that each instant is evaluated once (``refs_at(0.5·n·T)``, the same expression
whatever asks for it: the numbers do not depend on the window).
"""

from __future__ import annotations

from collections.abc import Callable

from gateway.control.laws import Refs


class ReferenceWindow:
    """``refs_at(n·T/2)`` for n = n0 … n0 + size − 1 (:meth:`starting`)."""

    def __init__(self, refs_at: Callable[[float], Refs], T: float, size: int) -> None:
        if size < 1:
            raise ValueError(f"a reference window of {size} instants")
        self._refs_at = refs_at
        self._T = T
        self._size = size
        self._n0 = 0
        self._win: list[Refs] = []
        self._slide = -1  # the n0 of the next step when the window is full: n0 + 2

    def starting(self, n0: int) -> list[Refs]:
        """The references at n·T/2, n = n0 … n0 + size − 1, index n − n0. The list is the
        window's own: read it before the next call."""
        win = self._win
        if n0 == self._slide:  # the next step: two instants leave, two new ones come
            n = n0 + self._size
            self._n0, self._slide = n0, n0 + 2
            del win[:2]
            win.append(self._refs_at(0.5 * (n - 2) * self._T))
            win.append(self._refs_at(0.5 * (n - 1) * self._T))
            return win
        shift = n0 - self._n0
        if shift:
            if 0 < shift < len(win):
                del win[:shift]
            else:
                win.clear()
            self._n0 = n0
        refs_at, T = self._refs_at, self._T
        n = n0 + len(win)
        while len(win) < self._size:
            win.append(refs_at(0.5 * n * T))
            n += 1
        self._slide = n0 + 2
        return win
