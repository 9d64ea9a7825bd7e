"""numba kernel of the simulator's normal draws (imported only through
:mod:`selfcal.sim.draw_numba`): numba's ``Generator.standard_normal`` is numpy's ziggurat
on the same bit generator, so it takes the same numbers from the same state, and leaves
the generator where numpy would (checked at first use)."""

from __future__ import annotations

import numba
import numpy as np


@numba.njit(cache=True, nogil=True)
def fill_standard_normal(rng, out):
    """Fill ``out`` (any shape, C-contiguous float64) with standard normals from ``rng``
    (a ``numpy.random.Generator``), in C order: the values of ``rng.standard_normal(out.shape)``."""
    flat = out.reshape(-1)
    for i in range(flat.size):
        flat[i] = rng.standard_normal()


@numba.njit(cache=True, nogil=True)
def lowpass(rng, n, dim, alpha, gain):
    """:func:`selfcal.sim.motion.lowpass_noise` (n, dim): the normals drawn in C order, each
    column filtered as ``scipy.signal.lfilter([1 - alpha], [1, -alpha])`` does (direct form
    II transposed: ``y = z + b0 x``, then ``z = x b1 - y a1`` with ``b1 = 0``, ``a1 = -alpha``),
    times ``gain``."""
    out = np.empty((n, dim))
    for i in range(n):
        for c in range(dim):
            out[i, c] = rng.standard_normal()
    b0 = 1.0 - alpha
    a1 = -alpha
    for c in range(dim):
        z = 0.0
        for i in range(n):
            x = out[i, c]
            y = z + b0 * x
            z = x * 0.0 - y * a1
            out[i, c] = y * gain
    return out
