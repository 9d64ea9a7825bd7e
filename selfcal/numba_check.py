"""An optional numba kernel, loaded once per process and used only where it gives the
numpy code's results bit for bit.

Each accelerated part of selfcal (the error models' fits, the pose store) keeps one
:class:`CheckedKernel`: at its first use it imports the kernel (numba compiles it, or loads
it from its cache), compares it with the numpy code on the part's own cases, and from then
on hands out the kernel, or None (numba missing, its JIT switched off, a compiler error, or
one differing bit), with one warning when something went wrong. ``SELFCAL_NUMBA=0`` turns
every kernel off (:func:`selfcal.detect_numba.enabled`).
"""

from __future__ import annotations

import threading
import warnings
from typing import Any, Callable


class CheckedKernel:
    """A kernel (or a bundle of them) loaded and checked once, thread-safely.

    Parameters
    ----------
    label : str
        What it is, for the warnings ("the error models' numba kernel").
    load : callable () -> kernel
        Imports the kernel module and returns the kernel (ImportError without numba).
    same : callable (kernel) -> bool
        Whether the kernel gives the numpy code's results bit for bit.
    reference, fallback : str
        For the warnings: the code it is checked against, and what runs instead.
    """

    def __init__(self, label: str, load: Callable[[], Any], same: Callable[[Any], bool],
                 reference: str = "the numpy code", fallback: str = "running the numpy code"):
        self.label = label
        self._load = load
        self._same = same
        self.reference = reference
        self.fallback = fallback
        self._lock = threading.Lock()
        self._found: list = []  # [kernel or None] once loaded and checked

    def get(self):
        """The kernel, or None when it cannot be used here (loaded and checked at the first call)."""
        if not self._found:
            with self._lock:
                if not self._found:  # a thread that waited for another's check takes its result
                    self._found.append(self.load_and_check())
        return self._found[0]

    def available(self, load: bool = False):
        """The kernel if ``SELFCAL_NUMBA`` allows kernels and it is loaded and usable, else
        None; ``load``: load and check it now if it is not yet (a caller whose work pays
        for the first load), else an unloaded kernel gives None."""
        from selfcal.detect_numba import enabled

        if not enabled() or not (load or self.loaded()):
            return None
        return self.get()

    def loaded(self) -> bool:
        """Whether it was loaded and checked (or found unusable) in this process."""
        return bool(self._found)

    def reset(self) -> None:
        """Forget it (tests): the next :meth:`get` loads and checks it again."""
        with self._lock:
            self._found.clear()

    def load_and_check(self):
        """Load and check now, whatever was found before: the kernel or None (warned)."""
        try:
            import numba

            if numba.config.DISABLE_JIT:  # it would run as plain Python, far slower than numpy
                return None
            kern = self._load()
            ok = self._same(kern)
        except ImportError:  # no numba
            return None
        except Exception as exc:  # noqa: BLE001 - a compiler error, no cache location: never stop the caller
            warnings.warn(f"selfcal: {self.label} is not used ({exc!r}); {self.fallback}",
                          RuntimeWarning, stacklevel=2)
            return None
        if not ok:
            warnings.warn(f"selfcal: {self.label} gave other results than {self.reference} on this machine; "
                          f"{self.fallback}", RuntimeWarning, stacklevel=2)
            return None
        return kern


def same_bits(a, b) -> bool:
    """Equal shapes and values, NaN at the same places, the same signs (of zeros too)."""
    import numpy as np

    return (a.shape == b.shape and np.array_equal(a, b, equal_nan=True)
            and np.array_equal(np.signbit(a), np.signbit(b)))
