"""The error models' optional numba kernel (selfcal.model_numba) gives the numpy code's
residuals and Jacobian bit for bit, for every base and effect it covers, and so the same
fits: a fit, a calibrator's refits and a replay do not depend on whether numba is there."""

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


@needs_numba
@pytest.mark.parametrize("seed", [1, 2, 3])
def test_the_kernel_gives_the_numpy_residuals_and_jacobian_bit_for_bit(seed):
    from selfcal import _model_jit

    rng = np.random.default_rng(seed)
    kern = _model_jit.residual_jac  # the kernel itself, whatever the first-use check said of it
    assert model_numba._checked() is kern, "the kernel failed its first-use check on this machine"
    for name in every_model():
        model = ErrorModel(name, temp_ref_c=float(rng.uniform(0, 40)), t_ref_s=float(rng.uniform(0, 1e6)),
                           t_step_s=float(rng.uniform(0, 1e6)))
        n = int(rng.integers(1, 300))
        raw = readings(rng, n)
        theta = model.nominal() + rng.normal(0.0, 0.05, model.n_params) * 10.0 ** rng.integers(-4, 1)
        if rng.random() < 0.3:
            theta[:3] = 0.0
        temp = rng.uniform(-20.0, 60.0, n)
        t_s = rng.uniform(0.0, 2e6, n)
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
def test_a_kernel_that_differs_is_not_used(monkeypatch):
    """The first-use check compares on every model of CHECK_MODELS: one wrong column of one
    effect is found, and the numpy code runs, with a warning."""
    real = model_numba._checked()

    def wrong_nonlinearity(theta, raw, dtemp, dtime, after, has_n, i_sb, i_tb, i_db, i_ts, i_q, i_tn, r, jac):
        real(theta, raw, dtemp, dtime, after, has_n, i_sb, i_tb, i_db, i_ts, i_q, i_tn, r, jac)
        if i_q >= 0:
            jac[:, i_q] *= 1.0 + 2.0**-52

    assert model_numba._same_as_numpy(real)
    assert not model_numba._same_as_numpy(wrong_nonlinearity)
    from selfcal import _model_jit

    monkeypatch.setattr(_model_jit, "residual_jac", wrong_nonlinearity)
    with pytest.warns(RuntimeWarning, match="differs from their numpy code"):
        assert model_numba._load_and_check() is None


def test_small_calls_wait_for_a_load_and_the_switch_turns_it_off(monkeypatch):
    """Below LOAD_FOR_ROWS a call does not load the kernel (its load costs more than such a
    call saves); at it, or after load(), the kernel is used; SELFCAL_NUMBA=0 turns it off."""
    monkeypatch.setattr(model_numba, "_found", [])
    assert model_numba.kernel(10) is None and not model_numba.loaded()
    usable = model_numba.kernel(model_numba.LOAD_FOR_ROWS) is not None
    assert model_numba.loaded()
    assert (model_numba.kernel(10) is not None) == usable
    monkeypatch.setenv("SELFCAL_NUMBA", "0")
    assert model_numba.kernel(10) is None and model_numba.kernel(10**6) is None
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
