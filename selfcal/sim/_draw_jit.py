"""numba kernel of the simulator's normal draws (imported only through
:mod:`selfcal.sim.draw_numba`): numba's ``Generator.standard_normal`` is numpy's ziggurat
on the same bit generator, so it takes the same numbers from the same state, and leaves
the generator where numpy would (checked at first use)."""

from __future__ import annotations

import numba


@numba.njit(cache=True, nogil=True)
def fill_standard_normal(rng, out):
    """Fill ``out`` (any shape, C-contiguous float64) with standard normals from ``rng``
    (a ``numpy.random.Generator``), in C order: the values of ``rng.standard_normal(out.shape)``."""
    flat = out.reshape(-1)
    for i in range(flat.size):
        flat[i] = rng.standard_normal()
