"""The still detector's numba kernels (imported only through :mod:`selfcal.detect_numba`,
which needs numba for nothing else). Each does numpy's arithmetic in numpy's order, so its
results are the numpy code's bit for bit: no fastmath (no reassociation, no fused
multiply-add)."""

from __future__ import annotations

import math

import numba
import numpy as np

# the verdicts of sd_codes, as literals: numba bakes them into its cached code, and would
# not see an edit of selfcal.detect_numba's (which checks that they agree)
OUT, IN, UNSURE = 0, 1, 2

_jit = numba.njit(cache=True, nogil=True)


@_jit
def sd_codes(x, w, thresholds, roll_block, unit_roundoff):
    """Per ``w``-sample window of ``x`` (c, n): OUT, IN or UNSURE (int8, n - w + 1).

    ``thresholds`` (c, 4): per channel the upper bound as a sum of squares over ``1 + r``
    and ``1 - r``, the lower over ``1 - r`` and ``1 + r`` (``-inf``: none), as
    :func:`selfcal.detect._sd_within` makes them; ``roll_block`` windows per block of
    prefix sums (re-anchored at the block's first sample); ``unit_roundoff`` 2**-53.
    The margins are :func:`selfcal.detect._sd_limits`' expressions, evaluated in the same
    order in float64.
    """
    c, n = x.shape
    m = n - w + 1
    codes = np.empty(max(m, 0), dtype=np.int8)
    if m <= 0:
        return codes
    inv_w = 1.0 / w
    u = unit_roundoff
    width = min(roll_block, m) + w
    q1 = np.empty((c, width))
    q2 = np.empty((c, width))
    limits = np.empty((c, 4))
    for lo in range(0, m, roll_block):
        hi = min(m, lo + roll_block)
        length = hi - lo + w - 1
        # prefix sums of y = x - x[lo] and of y^2, sequential as np.cumsum adds them
        for ch in range(c):
            first = x[ch, lo]
            a1 = 0.0
            a2 = 0.0
            q1[ch, 0] = 0.0
            q2[ch, 0] = 0.0
            for i in range(length):
                y = x[ch, lo + i] - first
                a1 = a1 + y
                a2 = a2 + y * y
                q1[ch, i + 1] = a1
                q2[ch, i + 1] = a2
        # the block's rounding bound (selfcal.detect._sd_limits)
        k1 = 2 * (length + 1) * u * math.sqrt(length) + u * math.sqrt(w)
        c1 = (2 * (length + 2) + 1) * u + (2 * math.sqrt(w) * k1 + k1 * k1) / w + 6 * u
        c2 = 4 * u * u * w
        overflow = False
        for ch in range(c):
            p = q2[ch, length]
            f = x[ch, lo]
            if p >= 0:
                margin = 2 * (c1 * p + c2 * abs(f) * math.sqrt(p)) + 1e-300
            else:
                margin = math.nan
            if not math.isfinite(margin):
                overflow = True
                break
            limits[ch, 0] = thresholds[ch, 0] - margin  # in_hi
            limits[ch, 1] = thresholds[ch, 1] + margin  # out_hi
            limits[ch, 2] = thresholds[ch, 2] + margin  # in_lo
            limits[ch, 3] = thresholds[ch, 3] - margin  # out_lo
        if overflow:  # every window of the block the slow way
            for j in range(lo, hi):
                codes[j] = UNSURE
            continue
        for j in range(hi - lo):
            sure = True
            possible = True
            for ch in range(c):
                d1 = q1[ch, j + w] - q1[ch, j]
                d2 = q2[ch, j + w] - q2[ch, j]
                s1 = d1 * d1
                s1 = s1 * inv_w
                ss = d2 - s1
                if not (ss < limits[ch, 0] and ss > limits[ch, 2]):
                    sure = False
                    # a sum that overflowed (inf, NaN) cannot rule a window out
                    if math.isfinite(ss) and not (ss <= limits[ch, 1] and ss >= limits[ch, 3]):
                        possible = False
                        break
            codes[lo + j] = IN if sure else (UNSURE if possible else OUT)
    return codes


@_jit
def _block_sum(a, start, n):
    """numpy's sum of at most 128 contiguous values: sequential below 8, else 8 running
    sums combined pairwise, then the rest."""
    if n < 8:
        res = 0.0
        for i in range(n):
            res += a[start + i]
        return res
    r0 = a[start]
    r1 = a[start + 1]
    r2 = a[start + 2]
    r3 = a[start + 3]
    r4 = a[start + 4]
    r5 = a[start + 5]
    r6 = a[start + 6]
    r7 = a[start + 7]
    i = 8
    stop = n - (n % 8)
    while i < stop:
        r0 += a[start + i]
        r1 += a[start + i + 1]
        r2 += a[start + i + 2]
        r3 += a[start + i + 3]
        r4 += a[start + i + 4]
        r5 += a[start + i + 5]
        r6 += a[start + i + 6]
        r7 += a[start + i + 7]
        i += 8
    res = ((r0 + r1) + (r2 + r3)) + ((r4 + r5) + (r6 + r7))
    while i < n:
        res += a[start + i]
        i += 1
    return res


@_jit
def pairwise_sum(a, start, n):
    """numpy's pairwise summation of ``a[start:start + n]`` (contiguous float64), the
    order ``np.add.reduce`` adds a contiguous axis in: blocks of up to 128 values
    (:func:`_block_sum`); above that the two halves (split at a multiple of 8) summed
    apart and added. The halving is walked with an explicit stack (numba does not cache
    recursive functions)."""
    if n <= 128:
        return _block_sum(a, start, n)
    frame_start = np.empty(64, dtype=np.int64)
    frame_n = np.empty(64, dtype=np.int64)
    frame_stage = np.empty(64, dtype=np.int64)
    values = np.empty(64)
    top = 0
    frame_start[0], frame_n[0], frame_stage[0] = start, n, 0
    nv = 0
    while top >= 0:
        s = frame_start[top]
        m = frame_n[top]
        if m <= 128:
            values[nv] = _block_sum(a, s, m)
            nv += 1
            top -= 1
            continue
        half = m // 2
        half -= half % 8
        stage = frame_stage[top]
        if stage == 0:  # the first half next
            frame_stage[top] = 1
            top += 1
            frame_start[top], frame_n[top], frame_stage[top] = s, half, 0
        elif stage == 1:  # then the second
            frame_stage[top] = 2
            top += 1
            frame_start[top], frame_n[top], frame_stage[top] = s + half, m - half, 0
        else:  # both done: their sum
            values[nv - 2] = values[nv - 2] + values[nv - 1]
            nv -= 1
            top -= 1
    return values[0]


@_jit
def window_stats(x, w, idx):
    """Two-pass mean and sd (ddof 1) of the ``w``-sample windows of ``x`` (c, n) that
    start at ``idx`` (k,): ``(mean (k, c), sd (k, c))``, computed as
    :func:`selfcal.detect._exact_window_stats` computes them with numpy (a window's sum
    by :func:`pairwise_sum` added to 0.0, divided by ``w``; the squared deviations summed
    the same way, divided by ``w - 1``, square root)."""
    c = x.shape[0]
    k = idx.shape[0]
    mean = np.empty((k, c))
    sd = np.empty((k, c))
    buf = np.empty(w)
    for j in range(k):
        s0 = idx[j]
        for ch in range(c):
            for i in range(w):
                buf[i] = x[ch, s0 + i]
            # numpy's reduction starts from its identity, 0.0 (so an all -0.0 window sums to 0.0)
            mu = (0.0 + pairwise_sum(buf, 0, w)) / w
            for i in range(w):
                d = buf[i] - mu
                buf[i] = d * d
            mean[j, ch] = mu
            sd[j, ch] = math.sqrt((0.0 + pairwise_sum(buf, 0, w)) / (w - 1))
    return mean, sd
