"""The correlated-noise model of still windows (selfcal.boutnoise): its algebra, and that
its estimator recovers an injected per-bout error."""

import numpy as np
import pytest

from boutgen import bout_case
from selfcal.boutnoise import BoutNoise, find_bouts, linear_scan
from selfcal.diagnosis import diagnose_poses


def _dense_cov(model: BoutNoise, bouts, t_s, marginal):
    """The model's covariance as a dense matrix (test reference), g²."""
    same = bouts.label[:, None] == bouts.label[None, :]
    dt = np.abs(t_s[:, None] - t_s[None, :])
    cov = np.where(same, model.sigma_bout_g**2 + model.sigma_ar_g**2 * np.exp(-dt / model.tau_s), 0.0)
    cov[np.diag_indices(len(t_s))] = marginal
    return cov


def _small_case(rng, n=40):
    t = np.cumsum(rng.choice([10.0, 10.0, 20.0, 100.0], n))
    perm = rng.permutation(n)  # input order need not be time order
    g = np.tile([0.0, 0.0, 1.0], (n, 1))
    g[n // 2:] = [1.0, 0.0, 0.0]  # a turn in the middle splits a bout
    return t[perm], g[perm]


def test_linear_scan_is_the_recursion():
    rng = np.random.default_rng(1)
    a = rng.uniform(0, 1, 50)
    a[[0, 7, 20]] = 0.0
    b = rng.normal(size=(50, 3))
    u, prev = np.zeros_like(b), np.zeros(3)
    for i in range(50):
        prev = a[i] * prev + b[i]
        u[i] = prev
    assert np.allclose(linear_scan(a, b), u, rtol=0, atol=1e-12)
    assert np.allclose(linear_scan(a, b[:, 0]), u[:, 0], rtol=0, atol=1e-12)


def test_bouts_split_at_gaps_and_turns():
    rng = np.random.default_rng(2)
    t, g = _small_case(rng)
    bouts = find_bouts(t, g, gap_s=30.0, angle_deg=5.0)
    order = np.argsort(t)
    lab = bouts.label[order]
    gaps = np.diff(t[order])
    turns = np.sum(g[order][1:] * g[order][:-1], axis=1) < np.cos(np.deg2rad(5.0))
    assert np.array_equal(lab[1:] != lab[:-1], (gaps > 30.0) | turns)
    assert bouts.n_bouts == 1 + int(np.sum((gaps > 30.0) | turns))


def _dense_case(seed: int, permute: bool = False):
    """A small bout layout, the test's noise model, its dense covariance and the generator:
    ``(t, g, bouts, model, indep, dense, rng)`` (``permute``: windows not in time order)."""
    rng = np.random.default_rng(seed)
    t, g = _small_case(rng)
    if permute:
        perm = rng.permutation(len(t))
        t, g = t[perm], g[perm]
    bouts = find_bouts(t, g, gap_s=30.0)
    model = BoutNoise(sigma_bout_g=2e-3, sigma_ar_g=1e-3, tau_s=50.0)
    indep = rng.uniform(1e-6, 9e-6, len(t))
    return t, g, bouts, model, indep, _dense_cov(model, bouts, t, indep + model.correlated_var_g2), rng


def test_covariance_product_and_draws_match_the_dense_covariance():
    t, g, bouts, model, indep, dense, rng = _dense_case(3)
    y = rng.normal(size=(len(t), 2))
    assert np.allclose(model.cov_matvec(bouts, indep, y), dense @ y, rtol=1e-12, atol=0)
    assert np.allclose(model.cov_matvec(bouts, indep, y[:, 0]), dense @ y[:, 0], rtol=1e-12, atol=0)
    # draws (no white part): covariance of 20 000 draws against the model's, 3 % of the largest entry
    draws = np.array([model.draw(rng, bouts) for _ in range(20_000)])
    expected = dense.copy()
    expected[np.diag_indices(len(t))] = model.correlated_var_g2
    assert np.max(np.abs(np.cov(draws.T) - expected)) < 0.03 * expected.max()


@pytest.mark.parametrize("max_block", [400, 3])
def test_the_whitener_inverts_the_dense_covariance(max_block):
    t, g, bouts, model, indep, dense, _ = _dense_case(4, permute=True)  # input order need not be time order
    w = model.whitener(bouts, indep, max_block=max_block)
    wm = w(np.eye(len(t)))
    assert np.allclose(w(np.arange(len(t), dtype=float)), wm @ np.arange(len(t)), rtol=1e-12, atol=1e-9)
    white = wm @ dense @ wm.T
    if max_block >= bouts.sizes.max():
        assert np.allclose(white, np.eye(len(t)), atol=1e-9)
    else:  # bouts cut into pieces: each piece is whitened alone, the pieces' shared error is not
        assert bouts.sizes.max() > max_block and not np.allclose(white, np.eye(len(t)), atol=1e-3)
        piece = model.whitener(bouts, indep, max_block=len(t))(np.eye(len(t)))
        assert np.allclose(piece @ dense @ piece.T, np.eye(len(t)), atol=1e-9)


def _noise_model(poses):
    rep = diagnose_poses(poses["mean"], poses["sd"], poses["count"], poses["t_s"], poses["temp_c"],
                         config={"diagnose": {"n_sim": 2}})
    return rep["noise_model"]


@pytest.mark.parametrize("seed", range(5))
def test_an_injected_per_bout_error_is_recovered(seed):
    """200 bouts of 2-40 windows, 2 mg per bout and 0.5 mg per window on top of 0.27 mg
    measured noise: the bout and white sds within 3 bootstrap sds, no AR term invented."""
    poses, truth = bout_case(np.random.default_rng(seed), sigma_bout_mg=2.0, sigma_white_mg=0.5)
    nm = _noise_model(poses)
    sd = nm["std"]
    assert nm["independence_test"]["p"] < 1e-3
    assert abs(nm["sigma_bout_mg"] - 2.0) <= 3 * sd["sigma_bout_mg"]
    assert abs(nm["sigma_white_mg"] - 0.5) <= 3 * sd["sigma_white_mg"]
    assert nm["sigma_ar_mg"] ** 2 <= 0.1 * nm["sigma_bout_mg"] ** 2  # spurious AR share <= 10 %
    assert abs(nm["measured_noise_mg"] - truth["noise_mg"]) < 0.02


@pytest.mark.parametrize("seed", range(3))
def test_bout_and_ar_terms_are_told_apart(seed):
    """300 bouts of 10-60 windows, 1.5 mg per bout plus a 1.5 mg AR(1) with tau 200 s: the
    correlated variance within 3 bootstrap sds, each sd within 0.4 mg, tau within 2x.
    (A 0.3 mg white part next to a short-tau AR term is not resolved and not checked.)"""
    poses, _ = bout_case(np.random.default_rng(seed), n_bouts=300, windows=(10, 60), sigma_bout_mg=1.5,
                         sigma_ar_mg=1.5, tau_s=200.0, sigma_white_mg=0.3)
    nm = _noise_model(poses)
    assert abs(nm["correlated_var_mg2"] - 4.5) <= 3 * nm["std"]["correlated_var_mg2"]
    assert abs(nm["sigma_bout_mg"] - 1.5) <= 0.4 and abs(nm["sigma_ar_mg"] - 1.5) <= 0.4
    assert 100.0 <= nm["tau_s"] <= 400.0


def test_projection_deltas_match_the_dense_traces():
    """delta_M = 2 tr(PM) - tr(PMP') of the weighted projector, for each covariance term."""
    from selfcal.boutnoise import _projection_deltas

    rng = np.random.default_rng(4)
    n = 60
    t = np.cumsum(rng.choice([10.0, 10.0, 100.0], n))
    bouts = find_bouts(t, np.tile([0.0, 0.0, 1.0], (n, 1)), gap_s=30.0)
    sigma, s2 = rng.uniform(1, 2, n), rng.uniform(0.1, 0.5, n)
    jac = rng.normal(size=(n, 4))
    q = np.linalg.svd(jac / sigma[:, None], full_matrices=False)[0]
    proj = np.diag(sigma) @ q @ q.T @ np.diag(1 / sigma)
    deltas = _projection_deltas(q, sigma, s2, bouts, BoutNoise(sigma_ar_g=1.0, tau_s=40.0))
    same = (bouts.label[:, None] == bouts.label[None, :]).astype(float)
    ar = same * np.exp(-np.abs(t[:, None] - t[None, :]) / 40.0)
    for key, mat in (("S", np.diag(s2)), ("Z", same), ("R", ar), ("I", np.eye(n))):
        assert deltas[key] == pytest.approx(2 * np.trace(proj @ mat) - np.trace(proj @ mat @ proj.T), rel=1e-10)


def test_gls_f_is_the_dense_generalised_least_squares_f():
    from selfcal.diagnosis import _GlsBase

    t, g, bouts, model, indep, dense, rng = _dense_case(5)
    n = len(t)
    x = np.column_stack([np.ones(n), g[:, 2], t / t.max()])
    c = np.column_stack([np.sin(t / 40.0), g[:, 0] * t / t.max()])
    r = np.linalg.cholesky(dense) @ rng.standard_normal(n) + 1e-3 * c[:, 0]
    f, dof = _GlsBase(model.whitener(bouts, indep), r, x).f(c)
    # the textbook form: whiten with the dense Cholesky factor, compare the two least-squares fits
    w = np.linalg.inv(np.linalg.cholesky(dense))

    def rss(a):
        beta, *_ = np.linalg.lstsq(w @ a, w @ r, rcond=None)
        return float(np.sum((w @ r - w @ a @ beta) ** 2))

    rss0, rss1 = rss(x), rss(np.column_stack([x, c]))
    assert dof == n - 5
    assert f == pytest.approx(((rss0 - rss1) / 2) / (rss1 / dof), rel=1e-9)
