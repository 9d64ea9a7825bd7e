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
  order, so means and sds are numpy's bit for bit (a NaN's sign aside: which of two NaNs
  a sum keeps is the compiler's choice). That order is numpy's implementation,
  not its promise: at first use the kernel is compared with numpy on windows of many
  lengths, and not used if any result differs.

With both, a chunk without a calibrated norm test (``to_cal`` None: the calibrator's and
the service's) goes through :func:`selfcal.detect.step` in one kernel call
(``step_chunk``: the buffer and the chunk by channel, the per-window tests, the runs, the
pieces and their table), the same windows and state bit for bit; a chunk of 400 samples
then costs one call instead of a dozen numpy and kernel calls.

numba is optional (``pip install 'selfcal[fast]'``; ``dev`` installs it for the tests).
Without it, or with the environment variable ``SELFCAL_NUMBA=0``, the functions here
return None and the detector runs its numpy code; ``tests/test_detect_numba.py`` checks
that both give the same windows.
"""

from __future__ import annotations

import functools
import os
import threading
import warnings

import numpy as np

#: Verdicts of the sliding sd test's kernel, per window.
OUT, IN, UNSURE = 0, 1, 2


def enabled() -> bool:
    """False when the environment variable ``SELFCAL_NUMBA`` is 0 / false / no / off
    (read at every call: a process may switch it; the parsing is kept per value)."""
    return _switched_on(os.environ.get("SELFCAL_NUMBA", "1"))


@functools.lru_cache(maxsize=8)
def _switched_on(value: str) -> bool:
    return value.strip().lower() not in ("0", "false", "no", "off")


def sd_codes_kernel():
    """``(x (c, n) float64, w, thresholds (c, 4), roll_block, unit_roundoff) -> codes
    (n - w + 1,) int8`` (OUT, IN, UNSURE), or None (numba missing or switched off)."""
    return _kernel(0)


def window_stats_kernel():
    """``(x (c, n) float64, w, idx (k,) int64) -> (mean (k, c), sd (k, c))``, numpy's
    two-pass statistics bit for bit, or None (numba missing or switched off, or this
    numpy sums in another order)."""
    return _kernel(1)


def kernels_now():
    """The kernels as the environment has them now (one read of ``SELFCAL_NUMBA``), for a
    caller that makes several detector calls in a row: ``(sd test, window statistics or
    None, per-window tests, pieces' table or None, run edges, whole chunk or None)``, or
    None (numba missing or switched off). The pieces' table and the whole chunk are None
    when the statistics kernel is (they use it). Their signatures are those of
    :mod:`selfcal._detect_jit` (``sd_codes``, ``window_stats``, ``window_codes``,
    ``pieces_stats``, ``run_edges``, ``step_chunk``)."""
    kernels = _kernels() if enabled() else None
    if kernels is None or kernels[1] is not None:
        return kernels
    return kernels[:3] + (None,) + kernels[4:5] + (None,)


def _kernel(i: int):
    """Kernel ``i`` of :func:`kernels_now`, or None."""
    kernels = kernels_now()
    return None if kernels is None else kernels[i]


_compile_lock = threading.Lock()  # one first-use compilation and check, not one per thread


@functools.lru_cache(maxsize=1)
def _kernels():
    """(sd test, window statistics or None, per-window tests, pieces' table, run edges,
    whole chunk),
    compiled at first use; None without numba, with numba's JIT disabled, or when numba
    fails here (no cache location, a compiler error): the detector then runs its numpy
    code, with one warning."""
    with _compile_lock:
        try:
            jit = _load()
        except ImportError:
            return None
        except Exception as exc:  # noqa: BLE001 - an accelerator must never stop the detector
            warnings.warn(f"selfcal: the detector's numba kernels are not used ({exc!r}); "
                          "running its numpy code", RuntimeWarning, stacklevel=2)
            return None
        if jit is None:
            return None
        if (jit.OUT, jit.IN, jit.UNSURE) != (OUT, IN, UNSURE):
            # the kernels' verdict values are literals there (numba bakes a module's constants
            # into its cached code and does not see edits made in another file)
            warnings.warn("selfcal: the detector's numba kernels disagree on their verdict codes; "
                          "running its numpy code", RuntimeWarning, stacklevel=2)
            return None
        try:
            stats = jit.window_stats if _same_stats_as_numpy(jit.window_stats) else None
        except Exception as exc:  # noqa: BLE001
            warnings.warn(f"selfcal: the detector's numba statistics kernel failed its check ({exc!r}); "
                          "using numpy's", RuntimeWarning, stacklevel=2)
            stats = None
        try:
            _compile_as_used(jit, stats is not None)
        except Exception as exc:  # noqa: BLE001 - an accelerator must never stop the detector
            warnings.warn(f"selfcal: the detector's numba kernels are not used ({exc!r}); "
                          "running its numpy code", RuntimeWarning, stacklevel=2)
            return None
        return jit.sd_codes, stats, jit.window_codes, jit.pieces_stats, jit.run_edges, jit.step_chunk


def _compile_as_used(jit, with_stats: bool) -> None:
    """Call every kernel once on a few samples, with the array layouts the detector passes
    (a chunk's samples as a contiguous block and as a column slice of one, the cached
    read-only thresholds), so that numba compiles (or loads from its cache) here, where a
    failure leaves the numpy code, and not at a detector call."""
    x = np.zeros((4, 12))
    x[2] = 1.0
    t = np.arange(12) / 20.0
    thresholds = np.array([[1e-3, 1e-3, -np.inf, -np.inf]] * 3)
    thresholds.setflags(write=False)
    for tt, xx in ((t, x[:3]), (t[2:], x[:3, 2:])):  # contiguous, and a column slice
        for exact in (False, True):
            jit.window_codes(tt, xx, 4, 1.5, 0.15, 0.2, thresholds, 8192, 2.0**-53, exact)
        jit.sd_codes(xx, 4, thresholds, 8192, 2.0**-53)
    jit.run_edges(np.array([True, False, True]), False)
    if with_stats:
        lo, hi = np.array([0, 6], dtype=np.int64), np.array([6, 12], dtype=np.int64)
        jit.pieces_stats(t, x, lo, hi, 0.1)
        for xx in (x, x[:, 2:]):
            jit.window_stats(xx, 4, np.array([0, 1], dtype=np.int64))
        # a chunk as the detector passes it: every array C-contiguous and writable, the
        # settings' bounds cached and read-only (its one signature, with or without pressure)
        lo_sd, hi_sd, th = np.zeros(3), np.ones(3), np.zeros((3, 4))
        for ro in (lo_sd, hi_sd, th):
            ro.setflags(write=False)
        acc = np.zeros((6, 3))
        acc[:, 2] = 1.0
        jit.step_chunk(t[:6].copy(), x[:, :6].copy(), t[6:] + 0.3, acc, np.full(6, np.nan), np.zeros((6, 0)),
                       0, 6, False, 0, -1, 4, 1, 6, 1.5, 0.15, 0.2, th, lo_sd, hi_sd, 8192, 2.0**-53, 64, 0.1)


def _load():
    """The kernels' module (numba compiles its functions at their first call), or None
    when numba's JIT is switched off (``NUMBA_DISABLE_JIT``: the kernels would run as
    plain Python, far slower than the numpy code); ImportError without numba."""
    import numba

    if numba.config.DISABLE_JIT:
        return None
    from selfcal import _detect_jit

    return _detect_jit


def _same_stats_as_numpy(kernel) -> bool:
    """Whether ``kernel`` gives numpy's means and sds, bit for bit (the sign of a zero
    included), on windows of lengths around every boundary of numpy's pairwise summation
    (8, 128 and their halvings) up to 10 s at 1.6 kHz."""
    from selfcal.detect import _exact_window_stats  # (selfcal.detect imports this module)

    rng = np.random.default_rng(12345)
    for w in (2, 3, 7, 8, 9, 15, 16, 17, 127, 128, 129, 136, 255, 256, 257, 1000, 1031, 4097, 8193, 16385):
        x = rng.normal(1.0, 1e-3, (3, w + 40)) * rng.uniform(0.5, 2.0, (3, 1))
        x[1, 17 : 17 + w] = -0.0  # a window of negative zeros: numpy's sum starts from 0.0
        idx = np.array([0, 1, 17, 40], dtype=np.int64)
        want_mu, want_sd = _exact_window_stats(x, w, idx, accelerate=False)  # the numpy code
        got_mu, got_sd = kernel(x, w, idx)
        for got, want in ((got_mu, want_mu), (got_sd, want_sd)):
            if not (np.array_equal(got, want) and np.array_equal(np.signbit(got), np.signbit(want))):
                return False
    return True
