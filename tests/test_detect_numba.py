"""The still detector's optional numba kernels (selfcal.detect_numba) give the numpy
code's results bit for bit: the sliding sd test's flags, the windows' two-pass means and
sds (the sign of a zero included), and so every window of a stream, for every chunking.
The numpy code itself is checked against the frozen reference in test_detect_reference."""

from __future__ import annotations

import numpy as np
import pytest

from selfcal import detect, detect_numba
from test_detect_reference import FIELDS, on_threshold_stream, run, simulated

needs_numba = pytest.mark.skipif(detect_numba._kernels() is None,
                                 reason="numba is not installed (pip install 'selfcal[fast]')")


def same_bits(a: np.ndarray, b: np.ndarray) -> bool:
    """Equal values, NaN at the same places, the same signs of zeros (a NaN's sign is the
    compiler's choice when two NaNs meet, so not compared)."""
    sign = ~np.isnan(a)
    return (a.shape == b.shape and np.array_equal(a, b, equal_nan=True)
            and np.array_equal(np.signbit(a)[sign], np.signbit(b)[sign]))


@pytest.fixture(autouse=True)
def numba_on(monkeypatch):
    """The kernels on (a SELFCAL_NUMBA=0 in the environment would make these tests compare
    numpy with numpy); a test that wants them off says so."""
    monkeypatch.setenv("SELFCAL_NUMBA", "1")


def stream_like(rng: np.random.Generator) -> tuple[np.ndarray, int, np.ndarray, np.ndarray]:
    """Samples by channel (c, n) with still stretches, offsets far from zero, a few huge
    values (rolling sums that overflow), and sd bounds near the data's: (x, w, lo, hi)."""
    c = int(rng.integers(1, 9))
    n = int(rng.integers(2, 20_000))
    w = int(rng.integers(2, min(n, 300) + 1))
    scale = 10.0 ** rng.integers(-6, 3)
    x = rng.normal(0, scale, (c, n)) + rng.normal(0, 1, (c, 1)) * 10.0 ** rng.integers(0, 4)
    a = int(rng.integers(0, n))
    x[:, a:a + int(rng.integers(1, 5000))] *= 1e-4  # a still stretch
    if rng.random() < 0.2:
        x[rng.integers(0, c), rng.integers(0, n)] = rng.choice([1e200, 1e300, -1e160])
    sd = np.abs(rng.normal(0, scale, c))
    lo = np.where(rng.random(c) < 0.5, sd * 0.1, 0.0)
    return x, w, lo, sd * rng.uniform(0.5, 2.0, c)


@needs_numba
@pytest.mark.parametrize("seed", [1, 2, 3])
def test_the_sliding_sd_test_flags_are_the_numpy_codes(seed):
    rng = np.random.default_rng(seed)
    for _ in range(120):
        x, w, lo, hi = stream_like(rng)
        with np.errstate(all="ignore"):
            fast = detect._sd_within(x, w, lo, hi, accelerate=True)
            slow = detect._sd_within(x, w, lo, hi, accelerate=False)
        np.testing.assert_array_equal(fast, slow)


def flags_stream(rng: np.random.Generator) -> tuple[np.ndarray, np.ndarray, dict]:
    """(t (n,), x (3 + k, n), detector settings) of a stretch that trips every per-window
    test: near-1 g still stretches with motion, non-finite values on any channel,
    saturated axes, raw norms off by more than the tolerance, huge values, and time steps
    that are zero, negative, NaN or past the gap."""
    k = int(rng.integers(0, 5))
    n = int(rng.integers(2, 3000))
    t = np.arange(n) / 20.0 + 1e5 * rng.integers(0, 2)
    x = np.empty((3 + k, n))
    x[:3] = (np.array([0.1, -0.2, 0.97]) + rng.normal(0, 10.0 ** rng.uniform(-4, -1.5), (n, 3))).T
    x[3:] = rng.uniform(0, 200, (k, 1)) + rng.normal(0, 10.0 ** rng.uniform(-1, 2), (k, n))
    a = int(rng.integers(0, n))
    x[:, a:a + int(rng.integers(1, 400))] = x[:, a:a + 1]  # flat: below sd_min_g
    for _ in range(int(rng.integers(0, 6))):
        i, ch = int(rng.integers(0, n)), int(rng.integers(0, 3 + k))
        x[ch, i] = rng.choice([np.nan, np.inf, -np.inf, 1e200, -1e300, 1.6, -2.0, 0.0])
    for _ in range(int(rng.integers(0, 4))):
        i = int(rng.integers(0, n))
        t[i:] += rng.choice([0.0, -0.5, 0.3, np.nan, 1e-9])
    cfg = {"rate_hz": 20.0, "twait_s": float(rng.choice([0.1, 0.5, 1.0, 3.0, 9.0])),
           "sd_max_g": float(10.0 ** rng.uniform(-3, -1.5)), "sd_min_g": float(rng.choice([0.0, 1e-4])),
           "norm_tol_raw_g": float(rng.choice([0.01, 0.05, 0.15])),
           "pressure_sd_max_kpa": float(10.0 ** rng.uniform(-1, 2))}
    if rng.random() < 0.3:
        cfg["clip_abs_g"] = False
    return t, x, cfg


@needs_numba
@pytest.mark.parametrize("seed", [11, 12, 13])
def test_every_windows_flags_are_the_numpy_codes(seed):
    """The one-call kernel of the per-window tests (non-finite values, saturation, the raw
    norm, time steps, the sliding sd test) gives the numpy code's flags, without and with
    a calibration (which turns the raw norm test off)."""
    rng = np.random.default_rng(seed)
    tripped = 0
    for _ in range(150):
        t, x, settings = flags_stream(rng)
        cfg = detect.DetectorConfig(**settings)
        to_cal = None if rng.random() < 0.5 else (lambda m: m * 1.01)
        with np.errstate(all="ignore"):
            fast = detect._window_flags(t, x, cfg, to_cal, accelerate=True)
            slow = detect._window_flags(t, x, cfg, to_cal, accelerate=False)
        np.testing.assert_array_equal(fast, slow)
        tripped += bool(slow.any()) and not slow.all()
    assert tripped > 20  # streams with windows both in and out, not all of one kind


@needs_numba
@pytest.mark.parametrize("seed", [21, 22])
def test_the_pieces_table_is_the_numpy_codes_bit_for_bit(seed):
    """The one-call table of still pieces: pieces of many lengths (some too short or too
    brief to keep), with and without pressure channels (one of them NaN at times),
    temperature missing in part of a piece, in all of it, or past the float range."""
    rng = np.random.default_rng(seed)
    for _ in range(200):
        k = int(rng.integers(0, 5))
        b = int(rng.integers(1, 3000))
        t = np.cumsum(rng.uniform(0.0, 0.2, b)) + 1e5 * rng.integers(0, 2)
        x = np.empty((4 + k, b))
        x[:3] = rng.normal(0, 1e-3, (3, b)) + rng.normal(0, 1, (3, 1))
        x[3 : 3 + k] = rng.uniform(0, 200, (k, 1)) + rng.normal(0, 10.0 ** rng.uniform(-2, 2), (k, b))
        x[-1] = 25.0 + rng.normal(0, 0.1, b)
        if k and rng.random() < 0.3:  # a pressure channel's sd NaN: np.max's NaN
            x[3 + int(rng.integers(0, k)), int(rng.integers(0, b))] = rng.choice([np.nan, np.inf])
        for _ in range(int(rng.integers(0, 4))):  # temperature missing: one reading, a stretch, all
            a = int(rng.integers(0, b))
            x[-1, a : a + int(rng.choice([1, 50, b]))] = rng.choice([np.nan, np.inf, 1e308])
        cuts = np.unique(rng.integers(0, b + 1, int(rng.integers(1, 12))))
        lo, hi = cuts[:-1].astype(np.int64), cuts[1:].astype(np.int64)
        cfg = detect.DetectorConfig(min_duration_s=float(rng.choice([0.05, 1.0, 9.9])))
        with np.errstate(all="ignore"):
            fast = detect._pieces_table(t, x, lo, hi, cfg, accelerate=True)
            slow = detect._pieces_table(t, x, lo, hi, cfg, accelerate=False)
        for name in FIELDS:
            got, want = getattr(fast, name), getattr(slow, name)
            assert got.dtype == want.dtype and same_bits(got, want), name


@needs_numba
def test_any_true_accelerate_and_other_dtypes_keep_the_numpy_flags():
    """``accelerate`` may be any true value (np.True_, 1), and samples that are not float64
    are flagged in their own dtype, as the numpy code flags them (a review found float32
    times cast before their steps were taken)."""
    rng = np.random.default_rng(41)
    t, x, settings = flags_stream(rng)
    cfg = detect.DetectorConfig(**settings)
    with np.errstate(all="ignore"):
        want = detect._window_flags(t, x, cfg, None, accelerate=False)
        for flag in (True, np.True_, 1):
            np.testing.assert_array_equal(detect._window_flags(t, x, cfg, None, accelerate=flag), want)
    t32 = np.array([-1e-8, 1.0, 1.05, 1.1, 1.15, 1.2], dtype=np.float32)
    x32 = np.tile(np.array([[0.0], [0.0], [1.0]], dtype=np.float32), (1, 6))
    x32 += rng.normal(0, 3e-3, x32.shape).astype(np.float32)
    cfg = detect.DetectorConfig(rate_hz=20.0, twait_s=0.1, max_gap_s=1.0)
    np.testing.assert_array_equal(detect._window_flags(t32, x32, cfg, None, accelerate=True),
                                  detect._window_flags(t32, x32, cfg, None, accelerate=False))


@needs_numba
def test_run_edges_are_the_flags_differences():
    """Where runs of passing windows open and close, with a run open before or not."""
    edges = detect_numba.kernels_now()[4]
    rng = np.random.default_rng(31)
    for _ in range(300):
        flags = rng.random(int(rng.integers(0, 60))) < rng.uniform(0, 1)
        run_open = bool(rng.random() < 0.5)
        d = np.diff(np.concatenate(([run_open], flags)).astype(np.int8))
        starts, ends = edges(flags, run_open)
        np.testing.assert_array_equal(starts, np.flatnonzero(d == 1))
        np.testing.assert_array_equal(ends, np.flatnonzero(d == -1) - 1)


@needs_numba
@pytest.mark.parametrize("seed", [4, 5])
def test_window_statistics_are_numpys_bit_for_bit(seed):
    """Lengths around numpy's pairwise-summation boundaries (8, 128, halvings), NaN and
    inf in a channel, windows of negative zeros (numpy's sum starts from +0.0)."""
    rng = np.random.default_rng(seed)
    lengths = [2, 3, 7, 8, 9, 15, 16, 17, 127, 128, 129, 130, 255, 256, 257, 1000, 1031, 4097, 20_000, 65_537]
    for _ in range(150):
        c = int(rng.integers(1, 9))
        w = int(rng.choice(lengths))
        n = w + int(rng.integers(0, 2000))
        x = rng.normal(0, 1, (c, n)) * 10.0 ** rng.integers(-6, 4, (c, 1)) + 10.0 ** rng.integers(0, 3, (c, 1))
        if rng.random() < 0.3:
            x[-1, rng.integers(0, n)] = rng.choice([np.nan, np.inf, -np.inf, 1e308])
        if rng.random() < 0.15:
            x[0] = -0.0
        idx = rng.integers(0, n - w + 1, int(rng.integers(1, 12)))
        with np.errstate(all="ignore"):
            m1, s1 = detect._exact_window_stats(x, w, idx, accelerate=True)
            m2, s2 = detect._exact_window_stats(x, w, idx, accelerate=False)
        assert same_bits(m1, m2) and same_bits(s1, s2), (w, c)


@needs_numba
@pytest.mark.parametrize("rate_hz, days", [(20, 0.3), (100, 0.05)])
def test_every_window_of_a_stream_is_the_same_with_and_without_numba(monkeypatch, rate_hz, days):
    """Simulated wear (20-Hz insole with pressure, 100-Hz wrist-like) and a stream built to
    sit on the sd thresholds, whole and in chunks of 1-400 samples."""
    data = simulated(7, rate_hz, days)
    rng = np.random.default_rng(8)
    cuts = np.cumsum(rng.integers(1, 400, len(data[0]) // 150))
    cfg = {"rate_hz": rate_hz}
    for cut in (None, list(cuts)):
        monkeypatch.setenv("SELFCAL_NUMBA", "1")
        fast = run(detect, cfg, data, cut)
        monkeypatch.setenv("SELFCAL_NUMBA", "0")
        slow = run(detect, cfg, data, cut)
        assert len(fast) == len(slow) > 10
        for name in FIELDS:
            assert same_bits(getattr(fast, name), getattr(slow, name)), name
    edge = on_threshold_stream({}, seed=9)
    monkeypatch.setenv("SELFCAL_NUMBA", "1")
    fast = run(detect, {}, edge)
    monkeypatch.setenv("SELFCAL_NUMBA", "0")
    slow = run(detect, {}, edge)
    for name in FIELDS:
        assert same_bits(getattr(fast, name), getattr(slow, name)), name


def test_switched_off_or_disagreeing_kernels_are_not_used(monkeypatch):
    """``SELFCAL_NUMBA=0`` gives the numpy code; a statistics kernel that differs from
    numpy in one bit (a numpy that sums in another order) fails the first-use check."""
    monkeypatch.setenv("SELFCAL_NUMBA", "0")
    assert detect_numba.sd_codes_kernel() is None and detect_numba.window_stats_kernel() is None
    assert detect_numba.kernels_now() is None

    def numpy_stats(x, w, idx):
        return detect._exact_window_stats(x, w, idx, accelerate=False)

    def one_ulp_off(x, w, idx):
        mu, sd = numpy_stats(x, w, idx)
        return np.nextafter(mu, np.inf), sd

    def sequential(x, w, idx):  # the naive order: differs from numpy's pairwise sums
        win = np.take(x, idx[:, None] + np.arange(w), axis=1)
        mu = np.zeros(win.shape[:2])
        for i in range(w):
            mu = mu + win[..., i]
        mu = mu / w
        dev = win - mu[..., None]
        return mu.T, np.sqrt((dev * dev).sum(axis=-1) / (w - 1)).T

    assert detect_numba._same_stats_as_numpy(numpy_stats)
    assert not detect_numba._same_stats_as_numpy(one_ulp_off)
    assert not detect_numba._same_stats_as_numpy(sequential)


def test_a_numba_that_fails_leaves_the_numpy_code_with_one_warning(monkeypatch):
    """No cache location (a read-only install), a compiler error, kernels whose verdict
    codes disagree with the front's, a kernel that fails at its first call (compiled at
    first use, before any detector call): the detector runs its numpy code, same windows."""
    import types

    data = simulated(7, 20, 0.05)
    monkeypatch.setenv("SELFCAL_NUMBA", "0")
    want = run(detect, {}, data)
    monkeypatch.setenv("SELFCAL_NUMBA", "1")

    def no_cache():
        raise RuntimeError("cannot cache function 'sd_codes': no locator available")

    other_codes = types.SimpleNamespace(OUT=1, IN=0, UNSURE=2, sd_codes=None, window_stats=None)

    def fails_to_compile(*args):  # numba's TypingError for a layout it had not seen
        raise RuntimeError("Failed in nopython mode pipeline (step: nopython frontend)")

    from selfcal import _detect_jit
    broken_codes = types.SimpleNamespace(**{k: getattr(_detect_jit, k) for k in (
        "OUT", "IN", "UNSURE", "sd_codes", "window_stats", "pieces_stats", "run_edges", "step_chunk")},
        window_codes=fails_to_compile)
    try:
        for load in (no_cache, lambda: other_codes, lambda: broken_codes):
            monkeypatch.setattr(detect_numba, "_load", load)
            detect_numba._kernels.cache_clear()
            with pytest.warns(RuntimeWarning, match="numpy code"):
                assert detect_numba.sd_codes_kernel() is None
            assert detect_numba.window_stats_kernel() is None
            got = run(detect, {}, data)
            for name in FIELDS:
                assert same_bits(getattr(got, name), getattr(want, name)), name
    finally:
        monkeypatch.undo()
        detect_numba._kernels.cache_clear()


def messy_stream(rng: np.random.Generator, rate_hz: float, n: int, k: int):
    """Still and moving stretches with everything a chunk can hold: NaN and inf samples,
    clipped values, gaps and repeated times, temperature missing in part of a piece, in
    all of it or past the float range, pressure channels (``k``) that move."""
    t = np.cumsum(np.where(rng.random(n) < 0.003, rng.choice([0.0, 0.5, 3.0], n), 1.0 / rate_hz))
    block = int(8 * rate_hz)  # 8-s poses, 6-s stretches of motion
    level = rng.normal(0, 1, (n // block + 1, 3))
    level /= np.linalg.norm(level, axis=1, keepdims=True)
    acc = np.repeat(level, block, axis=0)[:n] + 0.003 * rng.standard_normal((n, 3))
    moving = np.repeat(rng.random(n // (6 * rate_hz) + 1) < 0.3, 6 * rate_hz)[:n]
    acc[moving] += 0.3 * rng.standard_normal((int(moving.sum()), 3))
    for bad in (np.nan, np.inf, 9.0):
        acc[rng.integers(0, n, 3), rng.integers(0, 3, 3)] = bad
    temp = 25.0 + 0.01 * rng.standard_normal(n)
    for _ in range(6):
        a = int(rng.integers(0, n))
        temp[a : a + int(rng.choice([1, 30, 400]))] = rng.choice([np.nan, np.inf, 1e308])
    pres = 40.0 + 0.05 * rng.standard_normal((n, k))
    if k:
        pres[moving] += 5.0 * rng.standard_normal((int(moving.sum()), k))
        pres[rng.integers(0, n), rng.integers(0, k)] = np.nan
    return t, acc, temp, pres


@needs_numba
@pytest.mark.parametrize("seed", [31, 32, 33])
def test_a_chunk_in_one_call_gives_the_numpy_windows_and_state(monkeypatch, seed):
    """The whole chunk in one kernel call (``step_chunk``): after every chunk of 1-700
    samples, the same windows and the same carried state (buffer, indices, open run) as
    the numpy code, bit for bit; also when the state was saved and restored in between
    (a restored state has no buffer by channel)."""
    rng = np.random.default_rng(seed)
    for rate_hz, k in ((20, 4), (100, 0), (20, 1)):
        t, acc, temp, pres = messy_stream(rng, rate_hz, 30 * 60 * rate_hz // 5, k)
        cfg = detect.DetectorConfig(rate_hz=rate_hz, min_duration_s=float(rng.choice([0.5, 2.0])))
        cuts = np.unique(np.concatenate(([0, len(t)], np.cumsum(rng.integers(1, 700, len(t) // 150)))))
        cuts = cuts[cuts <= len(t)]
        dets = {on: detect.StaticDetector(cfg) for on in ("1", "0")}
        n_windows = 0
        for i, (lo, hi) in enumerate(zip(cuts[:-1], cuts[1:])):
            out = {}
            for on, det in dets.items():
                monkeypatch.setenv("SELFCAL_NUMBA", on)
                with np.errstate(all="ignore"):
                    out[on] = det.feed(t[lo:hi], acc[lo:hi], temp[lo:hi], pres[lo:hi] if k else None)
            for name in FIELDS:
                assert same_bits(getattr(out["1"], name), getattr(out["0"], name)), (name, lo)
            n_windows += len(out["0"])
            fast, slow = dets["1"].state_, dets["0"].state_
            for name in ("n_seen", "buf_start", "n_pressure", "run_open", "piece_start", "last_end"):
                assert getattr(fast, name) == getattr(slow, name), (name, lo)
            for name in ("t_s", "acc_g", "temp_c", "pressure_kpa"):
                assert same_bits(getattr(fast, name), getattr(slow, name)), (name, lo)
            if i % 7 == 3:  # saved and restored: the next chunk builds its buffer from the fields
                dets["1"] = detect.StaticDetector.from_state(cfg, dets["1"].state_dict())
        assert n_windows > 5
