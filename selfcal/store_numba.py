"""Optional numba kernel of the pose store's running sums: the same values, faster.

Every add to a :class:`selfcal.poses.PoseStore` gates its windows against their cells'
running statistics (:func:`selfcal.poses._running_sums`): one ``cumsum`` per cell in the
batch, or one vectorised step per position in a cell. A store that has grown for months
makes ~57 000 of those calls a year of wear (~5 % of a year's replay). The kernel
(:mod:`selfcal._store_jit`) does a batch's sums in one call, the same additions in the
same order, so the store, its gate and every fit after it are the same bit for bit.

It is used once loaded (:func:`load`: the replays, and the bench, load it); its first load
compares it with the numpy code (:func:`_same_as_numpy`) and refuses it, with a warning,
if one bit differs. numba is optional (``pip install 'selfcal[fast]'``); ``SELFCAL_NUMBA=0``
turns it off.
"""

from __future__ import annotations

import numpy as np

from selfcal.numba_check import CheckedKernel, same_bits


def _load_running_sums():
    from selfcal import _store_jit

    return _store_jit.running_sums


def kernel():
    """The running-sums kernel if it is loaded and usable here, else None (no load)."""
    from selfcal.detect_numba import enabled

    if not enabled() or not RUNNING_SUMS.loaded():
        return None
    return RUNNING_SUMS.get()


def load() -> bool:
    """Load and check the kernel now (a process about to add many windows); whether it is used."""
    from selfcal.detect_numba import enabled

    return enabled() and RUNNING_SUMS.get() is not None


def _same_as_numpy(kern) -> bool:
    """Whether ``kern`` gives :func:`selfcal.poses._running_sums`' numpy values bit for bit
    in both of its ways (few long groups: a cumsum each; many short ones: a step per
    position), with zeros of both signs, inf and NaN among the rows."""
    from selfcal.poses import _running_sums

    rng = np.random.default_rng(2026)
    for n_groups, longest in ((2, 40), (60, 4), (1, 1), (25, 25)):
        sizes = rng.integers(1, longest + 1, n_groups)
        k = int(sizes.sum())
        first = np.zeros(k, dtype=bool)
        first[np.r_[0, np.cumsum(sizes)[:-1]]] = True
        rows = rng.normal(0.0, 1.0, (k, 7)) * 10.0 ** rng.integers(-8, 8, (k, 1))
        rows[rng.random((k, 7)) < 0.1] = -0.0
        rows[rng.random((k, 7)) < 0.02] = np.inf
        rows[rng.random((k, 7)) < 0.02] = np.nan
        start = rng.normal(0.0, 1.0, (k, 7))
        start[rng.random((k, 7)) < 0.2] = -0.0
        with np.errstate(all="ignore"):
            want = _running_sums(start, rows, first, accelerate=False)
            got = _running_sums(start, rows, first, accelerate=kern)
        if not same_bits(got, want):
            return False
    return True


#: The kernel, loaded and checked once per process.
RUNNING_SUMS = CheckedKernel("the pose store's numba kernel", _load_running_sums, _same_as_numpy)
