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
        c3 = (math.log2(w) + 32) * u
        overflow = False
        for ch in range(c):
            p = q2[ch, length]
            f = x[ch, lo]
            if p >= 0:
                e3 = c3 * (abs(f) + math.sqrt(p))
                margin = 2 * (c1 * p + c2 * abs(f) * math.sqrt(p) + w * e3 * e3) + 1e-300
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
    recursive functions): :func:`_pairwise_sum_on` with a stack of its own."""
    if n <= 128:
        return _block_sum(a, start, n)
    return _pairwise_sum_on(a, start, n, np.empty((3, 64), dtype=np.int64), np.empty(64))


@_jit
def _pairwise_sum_on(a, start, n, frames, values):
    """:func:`pairwise_sum` with the caller's stack: ``frames`` (3, 64) int64 and
    ``values`` (64,) float64, overwritten (a caller that sums many windows allocates
    them once)."""
    if n <= 128:
        return _block_sum(a, start, n)
    frame_start = frames[0]
    frame_n = frames[1]
    frame_stage = frames[2]
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
    frames = np.empty((3, 64), dtype=np.int64)  # pairwise_sum's stack, once for every window
    values = np.empty(64)
    for j in range(k):
        s0 = idx[j]
        for ch in range(c):
            for i in range(w):
                buf[i] = x[ch, s0 + i]
            # numpy's reduction starts from its identity, 0.0 (so an all -0.0 window sums to 0.0)
            mu = (0.0 + _pairwise_sum_on(buf, 0, w, frames, values)) / w
            for i in range(w):
                d = buf[i] - mu
                buf[i] = d * d
            mean[j, ch] = mu
            sd[j, ch] = math.sqrt((0.0 + _pairwise_sum_on(buf, 0, w, frames, values)) / (w - 1))
    return mean, sd


@_jit
def finite_or_zero(x):
    """A copy of ``x`` (c, n) with every channel of a sample that has a non-finite value
    set to 0.0, as the numpy code's ``np.where(np.isfinite(x).all(axis=0), x, 0.0)``."""
    c, n = x.shape
    x0 = np.empty((c, n))
    for i in range(n):
        fin = True
        for ch in range(c):
            if not math.isfinite(x[ch, i]):
                fin = False
        for ch in range(c):
            x0[ch, i] = x[ch, i] if fin else 0.0
    return x0


@_jit
def window_codes(t, x, w, clip, norm_tol, max_gap, thresholds, roll_block, unit_roundoff, exact):
    """Every condition of :func:`selfcal.detect._window_flags` but the calibrated norm, per
    ``w``-sample window of ``x`` (c, n) at times ``t`` (n,): ``(codes, unsure)``, OUT, IN or
    UNSURE per window (int8, n - w + 1) and how many are UNSURE, in one pass over the
    samples before the sd test.

    A window is OUT when one of its samples is not finite on some channel, is at or past
    ``clip`` on an axis (NaN: no clip test), or has ``| ||a|| - 1 | >= norm_tol`` (NaN: no
    raw norm test, a model decides it), or when a time step inside it is ``<= 0``, NaN or
    ``> max_gap``. The others get :func:`sd_codes`' verdict on the samples with every
    channel of a sample holding a non-finite value set to 0.0 (as the numpy code does
    before its sd test). When no window passes those tests the sd test is not run (every
    window OUT), as in the numpy code. With ``exact`` (a few windows: the numpy code
    reduces each one) every window that passes the other tests is UNSURE, left to the
    exact statistics. Sums and comparisons are the numpy code's, in its order (the norm:
    ``sqrt((ax*ax + ay*ay) + az*az)``)."""
    c, n = x.shape
    m = n - w + 1
    codes = np.zeros(max(m, 0), dtype=np.int8)  # OUT
    if m <= 0:
        return codes, 0
    ok = np.zeros(m, dtype=np.bool_)
    last_bad = -1  # the last sample that fails a per-sample test
    last_gap = 0  # the last sample i whose step from i - 1 breaks a window (0: none)
    all_finite = True
    any_ok = False
    use_clip = clip == clip
    use_norm = norm_tol == norm_tol
    for i in range(n):
        bad = False
        for ch in range(c):
            if not math.isfinite(x[ch, i]):
                bad = True
        if bad:
            all_finite = False
        else:
            if use_clip:
                for ch in range(3):
                    if abs(x[ch, i]) >= clip:
                        bad = True
            if use_norm and not bad:
                a0 = x[0, i]
                a1 = x[1, i]
                a2 = x[2, i]
                if abs(math.sqrt(a0 * a0 + a1 * a1 + a2 * a2) - 1.0) >= norm_tol:
                    bad = True
        if bad:
            last_bad = i
        if i >= 1:
            dt = t[i] - t[i - 1]
            if not (dt > 0) or dt > max_gap:
                last_gap = i
        j = i - w + 1
        if j >= 0 and last_bad < j and last_gap <= j:
            ok[j] = True
            any_ok = True
    if not any_ok:
        return codes, 0
    if exact:
        unsure = 0
        for j in range(m):
            if ok[j]:
                codes[j] = UNSURE
                unsure += 1
        return codes, unsure
    x0 = x if all_finite else finite_or_zero(x)
    sd = sd_codes(x0, w, thresholds, roll_block, unit_roundoff)
    unsure = 0
    for j in range(m):
        if ok[j]:
            codes[j] = sd[j]
            unsure += sd[j] == UNSURE
    return codes, unsure


@_jit
def pieces_stats(t, x, lo, hi, min_duration):
    """:func:`selfcal.detect._pieces_table`'s statistics of the pieces ``[lo, hi)`` (q,) of
    the buffered samples ``x`` (4 + k, b): axes (g), ``k`` pressure channels (kPa), then
    temperature (°C), at times ``t`` (b,), in one call.

    Returns ``(keep (q,) bool, mean (p, 3), sd (p, 3), n (p,), t_start (p,), t_end (p,),
    temp (p,), pressure_sd (p,))`` for the ``p`` pieces kept (at least 2 samples and
    ``t_end - t_start >= min_duration``), each piece's statistics by :func:`window_stats`
    (numpy's, bit for bit). ``temp`` is the piece's temperature mean when every reading is
    finite (a sum past the float range stays as numpy leaves it), the mean of its finite
    readings when some are missing (as numpy takes it: their contiguous pairwise sum over
    their count), NaN when none is finite. ``pressure_sd`` is the largest channel sd (NaN
    if one is NaN, as ``np.max``; NaN without pressure)."""
    q0 = lo.shape[0]
    c = x.shape[0]
    keep = np.zeros(q0, dtype=np.bool_)
    p = 0
    for i in range(q0):
        if hi[i] - lo[i] >= 2 and t[hi[i] - 1] - t[lo[i]] >= min_duration:
            keep[i] = True
            p += 1
    mean = np.empty((p, 3))
    sd = np.empty((p, 3))
    n = np.empty(p, dtype=np.int64)
    t_start = np.empty(p)
    t_end = np.empty(p)
    temp = np.full(p, np.nan)
    psd = np.full(p, np.nan)
    one = np.empty(1, dtype=np.int64)
    j = 0
    for i in range(q0):
        if not keep[i]:
            continue
        length = hi[i] - lo[i]
        one[0] = lo[i]
        mu, s = window_stats(x, length, one)
        for ch in range(3):
            mean[j, ch] = mu[0, ch]
            sd[j, ch] = s[0, ch]
        n[j] = length
        t_start[j] = t[lo[i]]
        t_end[j] = t[hi[i] - 1]
        tm = mu[0, c - 1]
        if math.isfinite(tm):
            temp[j] = tm
        else:
            finite = np.empty(length)  # the finite readings, contiguous
            cnt = 0
            for k in range(lo[i], hi[i]):
                v = x[c - 1, k]
                if math.isfinite(v):
                    finite[cnt] = v
                    cnt += 1
            if cnt == length:
                temp[j] = tm  # every reading finite, the sum past the float range: numpy's mean too
            elif cnt > 0:
                temp[j] = (0.0 + pairwise_sum(finite, 0, cnt)) / cnt
        if c > 4:
            top = s[0, 3]
            for ch in range(4, c - 1):
                v = s[0, ch]
                if top != top:
                    break
                if v != v or v > top:
                    top = v
            psd[j] = top
        j += 1
    return keep, mean, sd, n, t_start, t_end, temp, psd


@_jit
def run_edges(flags, run_open):
    """The runs of passing windows in ``flags`` (m,) bool, a run open before the first
    window if ``run_open``: ``(starts, ends)`` int64, the first passing window of each run
    that opens here and the last passing window of each run that closes here (local
    indices), as :func:`selfcal.detect.step` takes them from the flags' differences."""
    m = flags.shape[0]
    starts = np.empty(m, dtype=np.int64)
    ends = np.empty(m, dtype=np.int64)
    a = 0
    b = 0
    prev = run_open
    for j in range(m):
        f = flags[j]
        if f and not prev:
            starts[a] = j
            a += 1
        elif prev and not f:
            ends[b] = j - 1
            b += 1
        prev = f
    return starts[:a].copy(), ends[:b].copy()


@_jit
def _cut(lo, hi, q, start, limit_end, final, size):
    """:func:`selfcal.detect._piece_ranges` into ``lo``/``hi`` from row ``q`` (global
    indices; each piece ends where the next starts, the last at ``limit_end`` with
    ``final``, else at the last full piece's end): ``(rows, next_start)``."""
    if limit_end < start:
        return q, start
    if final:
        nxt = limit_end + 1
        s = start
        while s <= limit_end:
            lo[q] = s
            hi[q] = min(s + size, nxt)
            q += 1
            s += size
        return q, nxt
    n_full = (limit_end - start + 1) // size
    for i in range(n_full):
        lo[q] = start + i * size
        hi[q] = start + (i + 1) * size
        q += 1
    return q, start + size * n_full


@_jit
def step_chunk(tb, xb, tn, acc, temp, pres, g0, n_seen, run_open, piece_start, last_end, w, trim, size,
               clip, norm_tol, max_gap, thresholds, lo_sd, hi_sd, roll_block, unit_roundoff, small_windows,
               min_duration):
    """:func:`selfcal.detect.step` for one chunk without a calibrated norm test, in one call:
    the same windows and the same state, bit for bit.

    ``tb`` (b,) s and ``xb`` (4 + k, b) are the buffered samples by channel (axes in g,
    ``k`` pressure channels in kPa, temperature in °C); ``tn`` (n,) s, ``acc`` (n, 3) g,
    ``temp`` (n,) °C and ``pres`` (n, k) kPa the chunk; ``g0``, ``n_seen``, ``run_open``,
    ``piece_start`` and ``last_end`` the state's (global sample indices); the rest the
    settings as :func:`window_codes`, :func:`pieces_stats` and the detector take them
    (``small_windows``: at most this many new windows are each reduced exactly).

    Returns ``(t_keep (b',), x_keep (4 + k, b'), n_seen, buf_start, run_open, piece_start,
    last_end, mean (p, 3), sd (p, 3), n (p,), t_start (p,), t_end (p,), temp (p,),
    pressure_sd (p,))``: the new state's buffer and fields, and the still windows that
    closed in the chunk (their statistics by :func:`pieces_stats`)."""
    b = tb.shape[0]
    n = tn.shape[0]
    kp = pres.shape[1]
    c = 4 + kp
    nb = b + n
    t = np.empty(nb)
    x = np.empty((c, nb))
    for i in range(b):
        t[i] = tb[i]
    for ch in range(c):
        for i in range(b):
            x[ch, i] = xb[ch, i]
    for i in range(n):
        t[b + i] = tn[i]
        x[0, b + i] = acc[i, 0]
        x[1, b + i] = acc[i, 1]
        x[2, b + i] = acc[i, 2]
        for j in range(kp):
            x[3 + j, b + i] = pres[i, j]
        x[c - 1, b + i] = temp[i]
    n_total = g0 + nb

    # the new test windows, j0 .. n_total - w (global), every one starting in the buffer
    j0 = max(n_seen - w + 1, 0)
    l0 = j0 - g0
    m = nb - l0 - w + 1
    lo = np.empty(nb + 1, dtype=np.int64)
    hi = np.empty(nb + 1, dtype=np.int64)
    q = 0
    if m > 0:
        xs = x[: 3 + kp, l0:]
        codes, n_unsure = window_codes(t[l0:], xs, w, clip, norm_tol, max_gap, thresholds, roll_block,
                                       unit_roundoff, m <= small_windows)
        flags = np.empty(m, dtype=np.bool_)
        for j in range(m):
            flags[j] = codes[j] == IN
        if n_unsure:  # each left to its exact statistics, on the samples with non-finite ones zeroed
            idx = np.empty(n_unsure, dtype=np.int64)
            u = 0
            for j in range(m):
                if codes[j] == UNSURE:
                    idx[u] = j
                    u += 1
            _, sd = window_stats(finite_or_zero(xs), w, idx)
            for r in range(n_unsure):
                good = True
                for ch in range(3 + kp):
                    if not (sd[r, ch] <= hi_sd[ch] and sd[r, ch] >= lo_sd[ch]):
                        good = False
                flags[idx[r]] = good
        # the runs of passing windows, then their pieces (loops over runs, not samples)
        was_open = run_open
        starts, ends = run_edges(flags, was_open)
        n_runs = starts.shape[0] + (1 if was_open else 0)
        last_window = n_total - w
        for r in range(n_runs):
            if was_open and r == 0:  # the run open before the chunk
                has_a = False
                a = 0
            else:
                has_a = True
                a = starts[r - 1 if was_open else r] + j0
            if has_a:
                piece_start = max(a + trim, last_end + 1)
                run_open = True
            if r < ends.shape[0]:
                seg_end = ends[r] + j0 + w - 1 - trim
                q, piece_start = _cut(lo, hi, q, piece_start, seg_end, True, size)
                last_end = max(last_end, seg_end)
                run_open = False
            else:
                q, piece_start = _cut(lo, hi, q, piece_start, last_window + w - 1 - trim, False, size)

    keep = n_total - w + 1
    if run_open:
        keep = min(keep, piece_start)
    keep = min(max(keep, g0), n_total)
    k = keep - g0
    t_keep = t[k:].copy()
    x_keep = x[:, k:].copy()

    for i in range(q):
        lo[i] -= g0
        hi[i] -= g0
    _, mean, sd_p, n_p, t_start, t_end, temp_p, psd = pieces_stats(t, x, lo[:q], hi[:q], min_duration)
    return (t_keep, x_keep, n_total, keep, run_open, piece_start, last_end, mean, sd_p, n_p, t_start, t_end,
            temp_p, psd)
