"""Sums of rows by group: ``np.add.at`` into zeros, bit for bit, without its cost.

``np.add.at(out, idx, values)`` adds each row of ``values`` to ``out[idx[i]]`` in input
order; ``np.bincount`` with weights does the same additions in the same order, one
column at a time, and is several times faster for tables of thousands of rows (the
pose store's batches and merges, the fit's cluster scores).
"""

from __future__ import annotations

import numpy as np


#: At most this many rows are added row by row (each a vector add: fewer calls than one
#: ``np.bincount`` per column); more go column by column.
_FEW_ROWS = 8


def sum_by_group(group: np.ndarray, values: np.ndarray, n_groups: int, accelerate=None) -> np.ndarray:
    """Per-group sums of ``values``, the result of ``np.add.at(zeros, group, values)``.

    Parameters
    ----------
    group : ndarray of int, shape (k,) — group of each row, ``0 <= group < n_groups``
    values : ndarray, shape (k,) or (k, c) — any unit (the sums keep it)
    n_groups : int
    accelerate : None uses the kernel of :mod:`selfcal.sums_numba` once it is loaded (the
        same additions in the same order, in one call), False the numpy code; or a kernel

    Returns
    -------
    ndarray, shape (n_groups,) or (n_groups, c), float64
    """
    values = np.asarray(values, dtype=float)
    group = np.asarray(group)
    if group.shape != values.shape[:1]:
        raise ValueError(f"sum_by_group: {group.shape[0] if group.ndim else 'no'} groups for {values.shape[0]} rows")
    if group.size and (group.min() < 0 or group.max() >= n_groups):
        raise IndexError(f"sum_by_group: groups must be 0 .. {n_groups - 1}, got {group.min()} .. {group.max()}")
    if values.ndim == 1:
        return np.bincount(group, weights=values, minlength=n_groups).astype(float, copy=False)
    if accelerate is None and values.shape[0] > _FEW_ROWS:
        from selfcal.sums_numba import kernels

        found = kernels()
        accelerate = None if found is None else found.sum_by_group
    if accelerate is not None and accelerate is not False:
        out = np.zeros((n_groups, values.shape[1]))
        accelerate(group.astype(np.int64, copy=False), np.ascontiguousarray(values), out)
        return out
    if values.shape[0] <= _FEW_ROWS:  # a service batch's windows: row by row, the same additions
        out = np.zeros((n_groups, values.shape[1]))
        for i, g in enumerate(group.tolist()):
            out[g] += values[i]
        return out
    out = np.empty((n_groups, values.shape[1]))
    if n_groups == 0:
        return out
    cols = np.ascontiguousarray(values.T)
    for j in range(cols.shape[0]):
        out[:, j] = np.bincount(group, weights=cols[j], minlength=n_groups)
    return out
