"""numba kernels of the running and per-group sums (imported only through
:mod:`selfcal.sums_numba`): the additions of :func:`selfcal.poses._running_sums` and of
:func:`selfcal.groupsum.sum_by_group` in the same order (no fastmath), so the same values
bit for bit (checked at first use)."""

from __future__ import annotations

import numba


@numba.njit(cache=True, nogil=True)
def running_sums(start_rows, rows, first, out):
    """Fill ``out`` (k, m): on a group's first row its start row, then the sum so far plus
    the row before, one addition at a time; every value plus 0.0 at the end (no -0.0).

    ``start_rows``, ``rows`` (k, m) float64 C-contiguous, ``first`` (k,) bool."""
    k, m = rows.shape
    for i in range(k):
        if first[i]:
            for c in range(m):
                out[i, c] = start_rows[i, c]
        else:
            for c in range(m):
                out[i, c] = out[i - 1, c] + rows[i - 1, c]
    for i in range(k):
        for c in range(m):
            out[i, c] = out[i, c] + 0.0


@numba.njit(cache=True, nogil=True)
def sum_by_group(group, values, out):
    """Add each row of ``values`` (k, c) float64 to ``out[group[i]]`` ((n_groups, c), zeros
    on entry), in input order: ``np.add.at(out, group, values)``, as ``np.bincount`` with
    weights does it column by column."""
    k, c = values.shape
    for i in range(k):
        g = group[i]
        for j in range(c):
            out[g, j] += values[i, j]
