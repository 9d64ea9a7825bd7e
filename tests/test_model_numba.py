"""The error models' optional numba kernels (selfcal.model_numba) give the numpy code's
residuals and Jacobian, and their whitened values, bit for bit, for every base and effect
they cover, and so the same fits: a fit, a calibrator's refits and a replay do not depend
on whether numba is there."""

from __future__ import annotations

import importlib.util
import itertools

import numpy as np
import pytest

from selfcal import model_numba
from selfcal.models import EFFECT_PARAMS, ErrorModel
from test_calibrator import _strip_timing as without_timings  # fit_ms: a wall time

needs_numba = pytest.mark.skipif(importlib.util.find_spec("numba") is None,
                                 reason="numba is not installed (pip install 'selfcal[fast]')")


@pytest.fixture(autouse=True)
def numba_on(monkeypatch):
    """The kernel on (a SELFCAL_NUMBA=0 in the environment would make these tests compare
    numpy with numpy); a test that wants it off says so."""
    monkeypatch.setenv("SELFCAL_NUMBA", "1")


def same_bits(a: np.ndarray, b: np.ndarray) -> bool:
    """Equal values, NaN at the same places, the same signs of zeros (not of NaNs)."""
    sign = ~np.isnan(a)
    return (a.shape == b.shape and np.array_equal(a, b, equal_nan=True)
            and np.array_equal(np.signbit(a)[sign], np.signbit(b)[sign]))


def every_model() -> list[str]:
    """scale6 and affine9 with every subset of effects they take (bias_step included)."""
    names = []
    effects = list(EFFECT_PARAMS) + ["bias_step"]
    for base in ("scale6", "affine9"):
        for k in range(len(effects) + 1):
            for combo in itertools.combinations(effects, k):
                if base == "scale6" and "temperature_cross" in combo:
                    continue
                names.append("+".join((base,) + combo))
    return names


def readings(rng: np.random.Generator, n: int) -> np.ndarray:
    """Pose means (n, 3), ~g, with rows a fit meets rarely: exact zeros, -0.0, huge and tiny."""
    raw = rng.normal(0.0, 0.6, (n, 3)) * 10.0 ** rng.integers(-3, 2, (n, 1))
    raw[rng.random((n, 3)) < 0.05] = 0.0
    raw[rng.random((n, 3)) < 0.05] = -0.0
    if n > 4:
        raw[0] = 0.0  # with a zero offset, a zero norm: NaN residual, NaN Jacobian row
        raw[1] = (1e150, -1e-300, 3.0)
        raw[2] = -0.0
    return raw


def random_case(rng: np.random.Generator, name: str) -> tuple:
    """``(model, n, raw (n, 3), theta, temp_c (n,), t_s (n,))``: the model ``name`` with random
    references, 1-299 readings of :func:`readings`, parameters near nominal at scales from
    1e-4 to 1 of 0.05, temperatures and times."""
    model = ErrorModel(name, temp_ref_c=float(rng.uniform(0, 40)), t_ref_s=float(rng.uniform(0, 1e6)),
                       t_step_s=float(rng.uniform(0, 1e6)))
    n = int(rng.integers(1, 300))
    raw = readings(rng, n)
    theta = model.nominal() + rng.normal(0.0, 0.05, model.n_params) * 10.0 ** rng.integers(-4, 1)
    return model, n, raw, theta, rng.uniform(-20.0, 60.0, n), rng.uniform(0.0, 2e6, n)


@needs_numba
@pytest.mark.parametrize("seed", [1, 2, 3])
def test_the_kernel_gives_the_numpy_residuals_and_jacobian_bit_for_bit(seed):
    from selfcal import _model_jit

    rng = np.random.default_rng(seed)
    kern = _model_jit.residual_jac  # the kernel itself, whatever the first-use check said of it
    assert model_numba.RESIDUAL_JAC.get() is kern, "the kernel failed its first-use check on this machine"
    for name in every_model():
        model, n, raw, theta, temp, t_s = random_case(rng, name)
        if rng.random() < 0.3:
            theta[:3] = 0.0
        # layouts the callers pass: contiguous, a column slice, Fortran order
        wide = np.empty((n, 7))
        wide[:, 2:5] = raw
        for rows in (raw, wide[:, 2:5], np.asfortranarray(raw)):
            with np.errstate(all="ignore"):
                want = model.residual_jac(theta, rows, temp, t_s, accelerate=False)
                got = model.residual_jac(theta, rows, temp, t_s, accelerate=kern)
                auto = model.residual_jac(theta, rows, temp, t_s)  # the kernel, loaded above
            for g in (got, auto):
                assert same_bits(g[0], want[0]) and same_bits(g[1], want[1]), name
        with np.errstate(all="ignore"):
            assert same_bits(model.residuals(theta, raw, temp, t_s), want[0]), name


@needs_numba
@pytest.mark.parametrize("seed", [1, 2])
def test_the_whitening_kernel_gives_the_numpy_whitened_residuals_and_jacobian_bit_for_bit(seed):
    """One Levenberg-Marquardt evaluation (residuals, Jacobian, both divided by a sigma
    that follows the scales) by the whitening kernel: the numpy code's four arrays, for
    every model, robust weights down to a rejected pose, zero and nonzero floors."""
    from selfcal import _model_jit
    from selfcal.fit import NoiseModel

    kern = _model_jit.whitened_residual_jac
    assert model_numba.whitening_kernel(model_numba.LOAD_FOR_ROWS) is kern, "it failed its first-use check here"
    rng = np.random.default_rng(seed)
    for name in every_model():
        model, n, raw, theta, temp, t_s = random_case(rng, name)
        var_axis = rng.uniform(0.0, 1e-5, (n, 3)) * (rng.random((n, 1)) < 0.9)  # some rows without noise
        weights = np.where(rng.random(n) < 0.1, 1e-12, rng.uniform(0.05, 1.0, n))
        noise = NoiseModel(var_axis, float(rng.choice([0.0, 2.5e-7])), None).scaled(weights)
        wide = np.empty((n, 6))
        wide[:, 1:4] = raw
        for rows in (raw, wide[:, 1:4]):
            with np.errstate(all="ignore"):
                want = noise.whitened(model, theta, rows, temp, t_s, accelerate=False)
                got = noise.whitened(model, theta, rows, temp, t_s, accelerate=kern)
                auto = noise.whitened(model, theta, rows, temp, t_s)
            for g in (got, auto):
                for a, b, what in zip(g, want, ("r", "jac", "r/sigma", "jac whitened")):
                    assert same_bits(a, b), (name, what)
        # the numpy code's sigma is the one every other part of a fit uses
        with np.errstate(all="ignore"):
            assert same_bits(want[0] / noise.sigma(theta), want[2]), name


def test_a_noise_with_the_scale_nonlinearity_is_whitened_by_the_numpy_code(monkeypatch):
    """The kernel's sigma has no nonlinearity gain: a noise model that has one never calls it."""
    from selfcal.fit import FitConfig, NoiseModel

    def refuse(*args):
        raise AssertionError("the whitening kernel was called for a noise with the nonlinearity gain")

    rng = np.random.default_rng(3)
    model = ErrorModel("affine9+scale_nonlinearity")
    raw = rng.normal(0.0, 0.6, (50, 3))
    noise = NoiseModel.from_poses(raw, np.full((50, 3), 2e-3), np.full(50, 100.0), FitConfig(), model)
    assert noise.nonlin is not None
    theta = model.nominal() + rng.normal(0.0, 0.01, model.n_params)
    r, jac, rw, jw = noise.whitened(model, theta, raw, accelerate=refuse)
    sig, dsig = noise(theta)
    assert np.array_equal(rw, r / sig) and np.allclose(jw, jac / sig[:, None] - (rw / sig)[:, None] * dsig)


@needs_numba
def test_a_kernel_that_differs_is_not_used(monkeypatch):
    """The first-use check compares on every model of CHECK_MODELS: one wrong column of one
    effect is found, and the numpy code runs, with a warning."""
    real = model_numba.RESIDUAL_JAC.get()

    def wrong_nonlinearity(theta, raw, dtemp, dtime, after, has_n, i_sb, i_tb, i_db, i_ts, i_q, i_tn, r, jac):
        real(theta, raw, dtemp, dtime, after, has_n, i_sb, i_tb, i_db, i_ts, i_q, i_tn, r, jac)
        if i_q >= 0:
            jac[:, i_q] *= 1.0 + 2.0**-52

    assert model_numba._same_as_numpy(real)
    assert not model_numba._same_as_numpy(wrong_nonlinearity)
    from selfcal import _model_jit

    monkeypatch.setattr(_model_jit, "residual_jac", wrong_nonlinearity)
    with pytest.warns(RuntimeWarning, match="numba kernel gave other results than the numpy code"):
        assert model_numba.RESIDUAL_JAC.load_and_check() is None


@needs_numba
def test_a_whitening_kernel_that_differs_is_not_used(monkeypatch):
    """The whitening kernel's own check: a sigma summed in another order (one rounding) is
    found, and the numpy code runs, with a warning; the plain kernel stays in use."""
    import math

    import numba

    from selfcal import _model_jit

    real = model_numba.whitening_kernel(model_numba.LOAD_FOR_ROWS)
    assert model_numba._same_whitening_as_numpy(real)

    @numba.njit
    def reassociated(theta, raw, dtemp, dtime, after, has_n, i_sb, i_tb, i_db, i_ts, i_q, i_tn, var_axis, floor2,
                     r, jac, rw, jw):
        _model_jit.residual_jac(theta, raw, dtemp, dtime, after, has_n, i_sb, i_tb, i_db, i_ts, i_q, i_tn, r, jac)
        s0, s1, s2 = theta[3], theta[4], theta[5]
        for i in range(raw.shape[0]):
            v0, v1, v2 = var_axis[i, 0], var_axis[i, 1], var_axis[i, 2]
            sig = math.sqrt((v0 * s0 * s0 + (v1 * s1 * s1 + v2 * s2 * s2)) + floor2)  # another order
            rw[i] = r[i] / sig
            t = rw[i] / sig
            for k in range(jac.shape[1]):
                jw[i, k] = jac[i, k] / sig - t * 0.0
            jw[i, 3] = jac[i, 3] / sig - t * ((v0 * s0) / sig)
            jw[i, 4] = jac[i, 4] / sig - t * ((v1 * s1) / sig)
            jw[i, 5] = jac[i, 5] / sig - t * ((v2 * s2) / sig)

    assert not model_numba._same_whitening_as_numpy(reassociated)
    monkeypatch.setattr(_model_jit, "whitened_residual_jac", reassociated)
    monkeypatch.setattr(model_numba.WHITENING, "_found", [])
    with pytest.warns(RuntimeWarning, match="whitening kernel gave other results"):
        assert model_numba.whitening_kernel(model_numba.LOAD_FOR_ROWS) is None
    assert model_numba.kernel(model_numba.LOAD_FOR_ROWS) is not None


def test_small_calls_wait_for_a_load_and_the_switch_turns_it_off(monkeypatch):
    """Below LOAD_FOR_ROWS a call does not load the kernel (its load costs more than such a
    call saves); at it, or after load(), the kernel is used; SELFCAL_NUMBA=0 turns it off."""
    monkeypatch.setattr(model_numba.RESIDUAL_JAC, "_found", [])
    monkeypatch.setattr(model_numba.WHITENING, "_found", [])
    assert model_numba.kernel(10) is None and not model_numba.loaded()
    assert model_numba.whitening_kernel(10) is None
    usable = model_numba.kernel(model_numba.LOAD_FOR_ROWS) is not None
    assert model_numba.loaded()
    assert (model_numba.kernel(10) is not None) == usable
    assert (model_numba.whitening_kernel(10) is not None) <= usable
    monkeypatch.setenv("SELFCAL_NUMBA", "0")
    assert model_numba.kernel(10) is None and model_numba.kernel(10**6) is None
    assert model_numba.whitening_kernel(10**6) is None
    assert not model_numba.load()


@needs_numba
@pytest.mark.parametrize("seed", [4, 5])
def test_fits_and_a_calibrators_refits_are_the_same_with_and_without_the_kernel(seed, monkeypatch):
    """A robust fit with the curvature term, and an online calibrator's published versions
    over simulated wear, with the kernel loaded and with numba switched off."""
    from selfcal.calibrator import OnlineCalibrator
    from selfcal.config import load_config
    from selfcal.fit import fit_poses
    from selfcal.poses import PoseData
    from selfcal.sim import SimConfig, Simulation

    sim = Simulation(SimConfig(), np.random.default_rng(seed), days=3, seed=seed)
    poses = sim.poses()
    keep = np.all(poses.sd_g <= 0.01, axis=1)
    args = (poses.mean_g[keep], poses.sd_g[keep], poses.n[keep], poses.t_s[keep] + poses.duration_s[keep] / 2,
            poses.temp_c[keep])
    runs = []
    for switch in ("1", "0"):
        monkeypatch.setenv("SELFCAL_NUMBA", switch)
        if switch == "1":
            assert model_numba.load()
        model = ErrorModel("affine9+temperature_bias", temp_ref_c=25.0)
        data = PoseData(args[0], args[1], args[2], args[3], args[4])
        fit = fit_poses(model, data, robust=True, theta0_u=model.nominal())
        cal = OnlineCalibrator(load_config(), "affine9")
        events = cal.feed_poses(*args)
        runs.append((fit, [without_timings(e) for e in events]))
    (fast, ev_fast), (slow, ev_slow) = runs
    for name in ("theta_u", "cov_u", "residuals_g", "sigma_g", "crlb_std"):
        assert same_bits(getattr(fast, name), getattr(slow, name)), name
    assert len(ev_fast) > 3 and ev_fast == ev_slow
