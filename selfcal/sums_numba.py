"""Optional numba kernels of the running and per-group sums: the same values, faster.

Every add to a :class:`selfcal.poses.PoseStore` gates its windows against their cells'
running statistics (:func:`selfcal.poses._running_sums`: a ``cumsum`` per cell in the
batch, or a vectorised step per position in a cell) and adds them to their cells
(:func:`selfcal.groupsum.sum_by_group`: one ``np.bincount`` per statistic, ~20 a call),
and every robust fit sums its scores by cluster the same way. A store that has grown for
months makes tens of thousands of these calls a year of wear. The kernels
(:mod:`selfcal._sums_jit`) do a call's sums in one pass, the same additions in the same
order, so the store, its gate and every fit are the same bit for bit.

They are used once loaded (:func:`load`: the replays, and the bench, load them); the first
load compares them with the numpy code (:func:`_same_as_numpy`) and refuses them, with a
warning, if one bit differs. numba is optional (``pip install 'selfcal[fast]'``);
``SELFCAL_NUMBA=0`` turns them off.
"""

from __future__ import annotations

from types import SimpleNamespace

import numpy as np

from selfcal.numba_check import CheckedKernel, same_bits


def _load() -> SimpleNamespace:
    from selfcal import _sums_jit

    return SimpleNamespace(running_sums=_sums_jit.running_sums, sum_by_group=_sums_jit.sum_by_group)


def kernels() -> SimpleNamespace | None:
    """``running_sums`` and ``sum_by_group`` if they are loaded and usable here, else None
    (this never loads them)."""
    return SUMS.available()


def load() -> bool:
    """Load and check the kernels now (a process about to add many windows); whether they are used."""
    return SUMS.available(load=True) is not None


def _same_as_numpy(k: SimpleNamespace) -> bool:
    """Whether the kernels give the numpy code's values bit for bit: the running sums in
    both of their ways (few long groups: a cumsum each; many short ones: a step per
    position), the group sums with rows in any group order (a few rows and many), with
    zeros of both signs, inf and NaN among the values."""
    from selfcal.groupsum import sum_by_group
    from selfcal.poses import _running_sums

    rng = np.random.default_rng(2026)

    def values(shape):
        v = rng.normal(0.0, 1.0, shape) * 10.0 ** rng.integers(-8, 8, (shape[0], 1))
        v[rng.random(shape) < 0.1] = -0.0
        v[rng.random(shape) < 0.02] = np.inf
        v[rng.random(shape) < 0.02] = np.nan
        return v

    for n_groups, longest in ((2, 40), (60, 4), (1, 1), (25, 25)):
        sizes = rng.integers(1, longest + 1, n_groups)
        n = int(sizes.sum())
        first = np.zeros(n, dtype=bool)
        first[np.r_[0, np.cumsum(sizes)[:-1]]] = True
        rows, start = values((n, 7)), values((n, 7))
        group = rng.integers(0, n_groups, n)
        with np.errstate(all="ignore"):
            want = _running_sums(start, rows, first, accelerate=False)
            got = _running_sums(start, rows, first, accelerate=k.running_sums)
            by_group = (sum_by_group(group, rows, n_groups, accelerate=False),
                        sum_by_group(group, rows, n_groups, accelerate=k.sum_by_group))
        if not (same_bits(got, want) and same_bits(*by_group)):
            return False
    return True


#: The kernels, loaded and checked once per process.
SUMS = CheckedKernel("the sums' numba kernels", _load, _same_as_numpy)
