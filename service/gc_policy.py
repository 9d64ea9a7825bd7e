"""The cyclic garbage collector's policy for a long-running process: freeze what survives.

A full (generation 2) collection scans every tracked object the process holds, while
every thread, the event loop included, waits. :func:`selfcal_service.main.tune_gc`
freezes what exists at start (modules, the app, the store); the embedded service then
builds a calibrator for each device it serves (about 29 tracked objects each), so that
at 10 000 insoles its full collections scanned ~370 000 objects and stalled every
request for ~90 ms, several times a minute (docs/service.md).

:class:`Refreezer` freezes (``gc.freeze()``) what survived each full collection, so the
next one scans only what arrived since. A frozen object is still freed by its reference
count; what the collector alone can free is garbage in reference cycles, and frozen,
such a cycle waits. So every ``unfreeze_every_s`` (wall-clock, monotonic) everything is
unfrozen at the end of a full collection: the next full collection scans it all once
(one long pause per period), frees the cycles that died frozen, and freezes the rest
again. Memory held by cyclic garbage is thereby bounded by what dies in one period.
"""

from __future__ import annotations

import gc
import threading
import time
from collections.abc import Callable


class Refreezer:
    """Freeze the survivors of every full collection; unfreeze all once per ``unfreeze_every_s``.

    Parameters
    ----------
    unfreeze_every_s : float, s (> 0)
        The longest a frozen object's cyclic garbage waits for a full scan, at most
        about one period plus the time to the next full collection.
    clock : callable, optional
        Monotonic seconds (tests pass their own).

    Attributes
    ----------
    freezes, unfreezes : int
        Full collections after which survivors were frozen / everything was unfrozen.
    """

    def __init__(self, unfreeze_every_s: float, clock: Callable[[], float] = time.monotonic):
        if not unfreeze_every_s > 0:
            raise ValueError(f"unfreeze_every_s = {unfreeze_every_s!r}: must be > 0 s")
        self.unfreeze_every_s = float(unfreeze_every_s)
        self._clock = clock
        self._last_unfreeze = clock()
        self._lock = threading.Lock()
        self.freezes = 0
        self.unfreezes = 0
        self._installed = False

    def install(self) -> "Refreezer":
        """Register with :mod:`gc` (the callback runs after every collection)."""
        if not self._installed:
            gc.callbacks.append(self._on_gc)
            self._installed = True
        return self

    def remove(self) -> None:
        """Unregister (at shutdown; tests build many apps in one process)."""
        if self._installed and self._on_gc in gc.callbacks:
            gc.callbacks.remove(self._on_gc)
        self._installed = False

    def _on_gc(self, phase: str, info: dict) -> None:
        # runs in the thread that triggered the collection, after it (phase "stop"): the
        # collector's lists are consistent, and freeze / unfreeze only move them whole
        if phase != "stop" or info.get("generation") != 2:
            return
        if not self._lock.acquire(blocking=False):  # another thread's collection is deciding
            return
        try:
            now = self._clock()
            if now - self._last_unfreeze >= self.unfreeze_every_s:
                gc.unfreeze()  # the next full collection scans everything once
                self._last_unfreeze = now
                self.unfreezes += 1
            else:
                gc.freeze()
                self.freezes += 1
        finally:
            self._lock.release()
