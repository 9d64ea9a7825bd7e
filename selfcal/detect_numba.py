"""Optional numba kernels of the still detector (:mod:`selfcal.detect`): the same windows, faster.

Two of the detector's numpy stages become one pass each:

* the sliding sd test (:func:`selfcal.detect._sd_within`): the numpy code materialises
  the prefix sums of every channel, their window differences and four comparisons per
  channel and window (about a dozen passes over a block); the kernel does the same
  arithmetic, operation for operation and in the same order, so every window gets the
  same verdict: clearly in, clearly out, or too close to a bound to tell from the
  rolling sums (then reduced exactly);
* the exact two-pass statistics of windows and pieces
  (:func:`selfcal.detect._exact_window_stats`): the kernel sums in numpy's pairwise
  order, so means and sds are numpy's bit for bit. That order is numpy's implementation,
  not its promise: at first use the kernel is compared with numpy on windows of many
  lengths, and not used if any result differs.

numba is optional (``pip install 'selfcal[fast]'``; ``dev`` installs it for the tests).
Without it, or with the environment variable ``SELFCAL_NUMBA=0``, the functions here
return None and the detector runs its numpy code; ``tests/test_detect_numba.py`` checks
that both give the same windows.
"""

from __future__ import annotations

import functools
import os

import numpy as np

#: Verdicts of the sliding sd test's kernel, per window.
OUT, IN, UNSURE = 0, 1, 2


def enabled() -> bool:
    """False when the environment variable ``SELFCAL_NUMBA`` is 0 / false / no / off."""
    return os.environ.get("SELFCAL_NUMBA", "1").strip().lower() not in ("0", "false", "no", "off")


def sd_codes_kernel():
    """``(x (c, n) float64, w, thresholds (c, 4), roll_block, unit_roundoff) -> codes
    (n - w + 1,) int8`` (OUT, IN, UNSURE), or None (numba missing or switched off)."""
    kernels = _kernels() if enabled() else None
    return None if kernels is None else kernels[0]


def window_stats_kernel():
    """``(x (c, n) float64, w, idx (k,) int64) -> (mean (k, c), sd (k, c))``, numpy's
    two-pass statistics bit for bit, or None (numba missing or switched off, or this
    numpy sums in another order)."""
    kernels = _kernels() if enabled() else None
    return None if kernels is None else kernels[1]


@functools.lru_cache(maxsize=1)
def _kernels():
    """(sd test, window statistics or None), compiled at first use; None without numba."""
    try:
        from selfcal import _detect_jit
    except ImportError:
        return None
    stats = _detect_jit.window_stats if _same_stats_as_numpy(_detect_jit.window_stats) else None
    return _detect_jit.sd_codes, stats


def _same_stats_as_numpy(kernel) -> bool:
    """Whether ``kernel`` gives numpy's means and sds, bit for bit (the sign of a zero
    included), on windows of lengths around every boundary of numpy's pairwise summation
    (8, 128 and their halvings)."""
    rng = np.random.default_rng(12345)
    for w in (2, 3, 7, 8, 9, 15, 16, 17, 127, 128, 129, 136, 255, 256, 257, 1000, 1031, 4097):
        x = rng.normal(1.0, 1e-3, (3, w + 40)) * rng.uniform(0.5, 2.0, (3, 1))
        x[1, 17 : 17 + w] = -0.0  # a window of negative zeros: numpy's sum starts from 0.0
        idx = np.array([0, 1, 17, 40], dtype=np.int64)
        windows = np.take(x, idx[:, None] + np.arange(w), axis=1)  # (3, 4, w), as the numpy code takes them
        mu = windows.mean(axis=-1)
        dev = windows - mu[..., None]
        sd = np.sqrt((dev * dev).sum(axis=-1) / (w - 1))
        got_mu, got_sd = kernel(x, w, idx)
        for got, want in ((got_mu, mu.T), (got_sd, sd.T)):
            if not (np.array_equal(got, want) and np.array_equal(np.signbit(got), np.signbit(want))):
                return False
    return True
