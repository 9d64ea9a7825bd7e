"""The pose store's numba kernel (imported only through :mod:`selfcal.store_numba`): each
group's running sums, row by row, the additions of :func:`selfcal.poses._running_sums` in
the same order (no fastmath), so the same values bit for bit (checked at first use)."""

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
