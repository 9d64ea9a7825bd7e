"""The fast detector (O(1) rolling statistics) against the reference implementation it
replaced (``tests/reference_detect.py``, a frozen copy): the same windows, bit for bit,
on simulated insole and wrist streams, on streams built to sit on the thresholds, and
for every chunking."""

from __future__ import annotations

import numpy as np
import pytest

import reference_detect as ref
from selfcal import detect as fast
from selfcal.sim.config import SimConfig
from selfcal.sim.simulator import simulate_samples
from test_detect import PROP_CFG, STREAM, to_cal_fixed

FIELDS = ("mean_g", "sd_g", "n", "t_start_s", "t_end_s", "temp_c", "pressure_sd_kpa")


def run(module, cfg: dict, data, cuts=None, to_cal=None):
    t, a, tc, p = data
    det = module.StaticDetector(module.DetectorConfig(**cfg))
    edges = [0, *(sorted(set(c for c in (cuts or []) if 0 < c < len(t)))), len(t)]
    out = [det.feed(t[lo:hi], a[lo:hi], tc[lo:hi], p[lo:hi] if p.shape[1] else None, to_cal=to_cal)
           for lo, hi in zip(edges[:-1], edges[1:])]
    out.append(det.flush())
    return module.StillWindows.concat(out)


def assert_identical(a, b):
    assert len(a) == len(b)
    for name in FIELDS:
        np.testing.assert_array_equal(getattr(a, name), getattr(b, name), err_msg=name)


def simulated(seed: int, rate_hz: float, days: float):
    cfg = SimConfig() if rate_hz == 20 else SimConfig(ble={"rate_hz": rate_hz})
    s, _ = simulate_samples(cfg, np.random.default_rng(seed), days=days)
    return s.t_s, s.acc_g, s.temp_c, s.pressure_kpa


def on_threshold_stream(cfg: dict, seed: int, n_windows: int = 400):
    """Still stretches whose every test window has a sample sd within a few ulps of
    ``sd_max_g`` or ``sd_min_g`` (a +-a square wave of period 2 with the matching
    amplitude, on 1 g, with a relative wobble of 1e-15), plus 1-g offsets far from
    zero on the other axes so that rolling sums cancel badly."""
    c = fast.DetectorConfig(**cfg)
    w = c.window_samples
    rng = np.random.default_rng(seed)
    n = w * n_windows
    sign = np.where(np.arange(n) % 2 == 0, 1.0, -1.0)
    parts = []
    for sd in (c.sd_max_g, c.sd_min_g):
        amp = sd * np.sqrt((w - 1) / w) * (1 + 4e-16 * rng.integers(-4, 5, n))
        a = np.empty((n, 3))
        a[:, 0] = 1.0 + amp * sign
        a[:, 1] = 0.02 + amp[::-1] * sign  # sd on both axes near the bound
        a[:, 2] = -0.01 + 0.5 * c.sd_max_g * rng.standard_normal(n)
        parts.append(a)
    acc = np.concatenate(parts)
    t = np.arange(acc.shape[0]) / c.rate_hz
    temp = np.full(acc.shape[0], 24.0)
    pres = 40.0 + np.outer(np.where(np.arange(acc.shape[0]) % 2 == 0, 1.0, -1.0),
                           np.full(4, c.pressure_sd_max_kpa * np.sqrt((w - 1) / w)))
    return t, acc, temp, pres


@pytest.mark.parametrize("seed", [1, 2, 3])
def test_simulated_insole_day_identical_for_every_chunking(seed):
    data = simulated(seed, 20.0, 0.35)
    cfg = {"rate_hz": 20.0}
    want = ref_out = run(ref, cfg, data)
    assert len(ref_out) > 100  # the stream has still windows to compare
    rng = np.random.default_rng(seed)
    n = len(data[0])
    assert_identical(run(fast, cfg, data), want)
    assert_identical(run(fast, cfg, data, cuts=list(range(400, n, 400))), want)
    assert_identical(run(fast, cfg, data, cuts=rng.integers(1, n, 300).tolist()), want)


def test_simulated_wrist_rate_identical():
    data = simulated(5, 100.0, 0.1)
    cfg = {"rate_hz": 100.0}
    want = run(ref, cfg, data)
    assert len(want) > 10
    assert_identical(run(fast, cfg, data, cuts=list(range(50_000, len(data[0]), 50_000))), want)


@pytest.mark.parametrize("seed", [0, 1])
@pytest.mark.parametrize("cfg", [{"rate_hz": 20.0}, {"rate_hz": 100.0, "twait_s": 0.5}])
def test_streams_on_the_thresholds_identical(seed, cfg):
    """Windows whose sd sits on ``sd_max_g``/``sd_min_g``/``pressure_sd_max_kpa`` to a
    few ulps: the rolling sums cannot decide them, the exact recheck must."""
    data = on_threshold_stream(cfg, seed)
    want = run(ref, cfg, data)
    got = run(fast, cfg, data)
    assert_identical(got, want)
    rng = np.random.default_rng(seed)
    assert_identical(run(fast, cfg, data, cuts=rng.integers(1, len(data[0]), 50).tolist()), want)


def test_threshold_stream_is_not_vacuous():
    """On the threshold stream, deciding with the rolling variance alone (no exact
    recheck) disagrees with the reference on some windows, and the reference passes
    some windows and fails others: the test above can fail."""
    cfg = fast.DetectorConfig(rate_hz=20.0)
    t, acc, _, _ = on_threshold_stream(cfg.model_dump(), 0)
    w = cfg.window_samples
    x = np.ascontiguousarray(acc[: 400 * w].T)  # the sd_max part
    idx = np.arange(x.shape[1] - w + 1)
    _, sd_exact = fast._exact_window_stats(x, w, idx)
    exact_pass = (sd_exact[:, :2] <= cfg.sd_max_g).all(axis=1)
    assert 0 < exact_pass.sum() < idx.size
    c1 = np.concatenate((np.zeros((3, 1)), np.cumsum(x, axis=1)), axis=1)
    c2 = np.concatenate((np.zeros((3, 1)), np.cumsum(x * x, axis=1)), axis=1)
    s1, s2 = c1[:, w:] - c1[:, :-w], c2[:, w:] - c2[:, :-w]
    naive_sd = np.sqrt(np.maximum(s2 - s1 * s1 / w, 0) / (w - 1))
    naive_pass = (naive_sd[:2] <= cfg.sd_max_g).all(axis=0)
    assert (naive_pass != exact_pass).any()


@pytest.mark.parametrize("use_model", [False, True])
def test_property_stream_identical(use_model):
    to_cal = to_cal_fixed if use_model else None
    cfg = PROP_CFG.model_dump()
    want = run(ref, cfg, STREAM, to_cal=to_cal)
    assert_identical(run(fast, cfg, STREAM, to_cal=to_cal), want)
    assert_identical(run(fast, cfg, STREAM, cuts=list(range(1, len(STREAM[0]))), to_cal=to_cal), want)


@pytest.mark.filterwarnings("ignore:overflow:RuntimeWarning")  # the reference overflows
def test_huge_values_without_clip_identical():
    """Values that overflow the squared sums (clip test off): decided exactly anyway."""
    rng = np.random.default_rng(4)
    n = 3000
    t = np.arange(n) / 20.0
    acc = np.array([0.0, 0.0, 1.0]) + 0.003 * rng.standard_normal((n, 3))
    acc[1000:1003] = 1e200
    acc[2000:2400, 0] += 1e3  # far from 1 g: cancellation in plain sums
    cfg = {"rate_hz": 20.0, "clip_abs_g": False, "norm_tol_raw_g": 1e300}
    data = (t, acc, np.full(n, 20.0), np.zeros((n, 0)))
    want = run(ref, cfg, data)
    assert len(want) > 5
    assert_identical(run(fast, cfg, data), want)


def test_rolling_sums_that_overflow_are_decided_exactly():
    """Values near 1e153 g with no clip and huge thresholds: the rolling sums of squares
    overflow (a window's sum of squared deviations comes out -inf or NaN) although every
    window's two-pass sd is finite; those windows are reduced in full, as the reference
    does (a review found them ruled out unchecked)."""
    rng = np.random.default_rng(0)
    n, w = 100, 20
    x = np.empty((3, n))
    x[0] = 1e153 * (1 + 1e-3 * rng.standard_normal(n))
    x[0, 0] = 0.0
    x[1:] = 3e-3 * rng.standard_normal((2, n))
    lo_sd, hi_sd = np.full(3, 2e-4), np.full(3, 1e300)
    with np.errstate(over="ignore", invalid="ignore"):
        got = fast._sd_within(x, w, lo_sd, hi_sd)
    _, sd = fast._exact_window_stats(x, w, np.arange(n - w + 1))
    want = ((sd <= hi_sd) & (sd >= lo_sd)).all(axis=1)
    assert want.sum() > 50
    np.testing.assert_array_equal(got, want)
    cfg = {"rate_hz": 20.0, "clip_abs_g": False, "norm_tol_raw_g": 1e300, "sd_max_g": 1e300}
    data = (np.arange(n) / 20.0, x.T.copy(), np.full(n, 25.0), np.zeros((n, 0)))
    with np.errstate(over="ignore", invalid="ignore"):
        ref_out = run(ref, cfg, data)
        assert len(ref_out) == 1
        assert_identical(run(fast, cfg, data), ref_out)
        assert_identical(run(fast, cfg, data, cuts=list(range(7, n, 7))), ref_out)


def stuck_channel_stream(kind: str, n: int = 400):
    """Still axes (1 g, 2 mg of noise) with one channel that does not move at all: a
    pressure channel stuck at a huge sentinel, or the y axis stuck at 0.1 g with an sd
    floor of 1e-17 g. (data, detector settings)."""
    rng = np.random.default_rng(0)
    t = np.arange(n) / 20.0
    acc = np.array([0.0, 0.0, 1.0]) + 0.002 * rng.standard_normal((n, 3))
    pres = np.zeros((n, 0))
    cfg = {"rate_hz": 20.0}
    if kind.startswith("pressure"):
        pres = np.full((n, 1), float(kind.split("=")[1]))
    else:
        acc[:, 1] = float(kind.split("=")[1])
        cfg["sd_min_g"] = 1e-17
    return (t, acc, np.full(n, 25.0), pres), cfg


@pytest.mark.filterwarnings("ignore::RuntimeWarning")  # the reference overflows at 1e300
@pytest.mark.parametrize("kind", ["pressure=1e155", "pressure=1e300", "pressure=5e17", "pressure=1e17",
                                  "y=0.1", "y=0.3"])
@pytest.mark.parametrize("numba", ["0", "1"])
def test_a_stuck_channel_far_from_zero_is_decided_as_the_reference_does(monkeypatch, kind, numba):
    """The rolling sums of a channel that does not move are exactly 0, but the two-pass
    definition's own mean is off by an ulp or so of the value, which adds ``w`` times its
    square to the window's sum of squared deviations (or overflows): that term is in the
    rolling test's margin, so such windows are reduced in full. Before, the rolling test
    called them still and the exact reduction (chunks of <= 64 new windows) did not: the
    windows depended on the chunking (a review found it)."""
    monkeypatch.setenv("SELFCAL_NUMBA", numba)
    data, cfg = stuck_channel_stream(kind)
    with np.errstate(all="ignore"):
        want = run(ref, cfg, data)
        for cuts in (None, list(range(40, 400, 40)), list(range(7, 400, 7))):
            assert_identical(run(fast, cfg, data, cuts=cuts), want)
