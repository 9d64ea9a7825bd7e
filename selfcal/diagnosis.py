"""Measured vs simulated: what the base model misses, its cause, and the gain of fixing it.

Given still poses (a poses table, or the still windows of a samples recording):

1. **Base fit.** ``affine9`` (MAP; directions the poses do not determine stay at the
   datasheet prior and are listed).
2. **What the simulation gets wrong.** The base model is the project's simulation of
   this sensor. We simulate the *same* recording under it: the same poses (their
   fitted gravity directions), times and temperatures, and each pose's noise as
   measured (its sd and sample count). We refit and compute the residual statistics
   many times. The measured statistics are then compared with that distribution
   (z-scores):
   * level (RMS);
   * structure against temperature and against time (OLS slope and R²);
   * structure against orientation (R² on the per-axis gravity components);
   * whiteness (lag-1 autocorrelation in time order), and the share of the residual
     variance shared within still bouts.

   The simulated noise is each pose's measured noise plus the correlated part of the
   **noise model** (:mod:`selfcal.boutnoise`) estimated from the base fit's residuals: an
   error shared by the windows of one still bout and an AR(1) term within the bout. The
   model's independent excess (the floor) is not drawn, so that it still shows as a level
   discrepancy. When the windows are not correlated within bouts (a chi-square test), the
   model has no correlated part and everything below is as with independent noise.
3. **Candidate effects.** ``temperature_bias``, ``temperature_scale``, ``time_drift_bias``
   and ``scale_nonlinearity`` (primary), ``temperature_cross`` (secondary: the
   cross-axis terms' tempcos, affine9 only), and the event ``bias_step`` (the offset
   jumps at one time, after a shock or a battery change). Each extends the fitted model
   (``affine9+effect``) and the simulator. The step's time is chosen first, by a scan:
   at ``step_times`` candidate times evenly spaced in pose order, the linearised χ² drop
   of a step there (score statistic at the base fit); the best time is fitted like any
   other candidate and its p-value multiplied by the number of times scanned
   (Bonferroni). A candidate is supported when all three hold:
   * an F-test on the fit gives ``p < alpha / n_candidates`` (3 extra parameters
     against the residual variance: the complexity penalty). Under correlated noise the
     F statistic is divided by the effect's *design effect*: the ratio of the Wald
     statistic of its estimate under independent noise to the same under the fitted
     correlated noise (sandwich covariance, linearised at the base fit). It is 1 when
     the noise model has no correlated part;
   * the held-out RMS improves by at least ``min_gain_rel``, averaged over a blocked
     cross-validation in time (contiguous blocks held out in turn: the standard for data
     ordered in time, and far less variable than one chronological split) and a k-fold
     split by pose. Both hold out whole still bouts, so that a window is never predicted
     from its own bout.

   With no supported candidate the answer is ``cause: null``.
4. **Separability.** The poses may not be able to tell two candidates apart (one
   orientation: a temperature bias and a temperature scale both move the norm by
   ``c · dT`` along gravity). A rival that is itself significant and whose fit is worse
   than the best by less than ``separable_dchi2`` (χ² in residual-variance units: a
   non-nested comparison; each candidate's χ² reduction divided by its design effect)
   cannot be told apart by these poses. The evidence says so,
   reports the share of the best pattern the rival reproduces, and no cause is named.
   A *secondary* candidate is named only when it beats every supported primary by
   ``separable_dchi2``; otherwise it neither wins nor makes a primary ambiguous. (On
   mostly flat insole poses a cross-axis tempco into z moves the norm as an x or y
   temperature bias does; as a full rival it cost the bias its name in 6 of 50 sets.)
5. **Gain.** The extended model is refitted on all poses (its estimate has an sd). The
   held-out RMS before → after is reported on the chronological split: fit on the first
   part, evaluate on the rest.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any, Literal

import numpy as np
from pydantic import BaseModel, ConfigDict, Field
from scipy import stats

from selfcal.boutnoise import BoutNoise, Bouts, estimate_bout_noise, find_bouts
from selfcal.errors import InputError
from selfcal.fit import FitConfig, GuardConfig, PoseData, datasheet_prior, fit_poses, implausible, pose_sigma
from selfcal.models import EFFECT_PARAMS, EVENT_PARAMS, SECONDARY_EFFECTS, ErrorModel, Normalizer
from selfcal.steps import refine_time, scan_step, step_times, whitened_basis

EFFECTS = tuple(EFFECT_PARAMS)
#: Every candidate diagnose tests: the model effects, then the events (a bias step at a
#: time found by a scan). The F-test level is divided over all of them.
CANDIDATES = EFFECTS + tuple(EVENT_PARAMS)

#: Physical unit and factor (from normalised parameters, g-based) for reporting estimates.
EFFECT_UNITS = {
    "temperature_bias": ("mg/degC", 1e3),
    "temperature_scale": ("ppm/degC", 1e6),
    "time_drift_bias": ("mg/day", 1e3),
    "scale_nonlinearity": ("mg/g^2", 1e3),
    "temperature_cross": ("ppm/degC", 1e6),
    "bias_step": ("mg", 1e3),
}


class DiagnoseConfig(BaseModel):
    """The ``[diagnose]`` section."""

    model_config = ConfigDict(extra="forbid")

    alpha: float = Field(0.012, gt=0, lt=1, description="F-test level, Bonferroni-divided over the 6 candidates "
                                                       "(2e-3 each; docs/diagnose.md, Power against BIC)")
    min_gain_rel: float = Field(0.01, ge=0, description="held-out RMS must drop by at least this fraction")
    time_split: float = Field(0.5, gt=0.1, lt=0.9, description="chronological split: fraction of time used to fit")
    pose_folds: int = Field(5, ge=2, description="folds of the split by pose")
    time_blocks: int = Field(4, ge=2, description="contiguous time blocks of the blocked cross-validation")
    separable_dchi2: float = Field(
        4.0, gt=0,
        description="a significant rival whose fit is worse by less than this (chi2, in residual-variance units): not separable",
    )
    n_sim: int = Field(10, ge=2, description="simulated replicates of the recording under the base model")
    min_temp_range_c: float = Field(3.0, ge=0, description="temperature candidates need this range, degC")
    min_time_span_h: float = Field(12.0, ge=0, description="drift and step candidates need this time span, h")
    step_times: int = Field(
        9, ge=1, description="bias step: candidate times scanned, evenly spaced in pose order (the step's p-value "
                             "is multiplied by this: Bonferroni over the scan)")
    step_min_side: float = Field(
        0.15, gt=0, lt=0.5, description="bias step: the first and last candidate times leave this fraction of the "
                                        "poses on their outer side")
    seed: int = Field(0, description="seed of the simulated replicates")
    estimate_floor: bool = Field(
        True, description="estimate the residual floor (beyond measured noise) from the base fit, instead of [fit] sigma_floor_g"
    )
    noise_model: Literal["bouts", "independent"] = Field(
        "bouts",
        description="bouts: correlated noise within still bouts, estimated from the base fit (simulation, F-tests, CV folds); "
                    "independent: every window independent (the former behaviour)",
    )
    correlated_test: Literal["design_effect", "gls"] = Field(
        "design_effect",
        description="under correlated noise, each candidate's F test: design_effect (the weighted fit's F divided by "
                    "the design effect) or gls (generalised least squares: the residuals, the base model's and the "
                    "candidate's columns whitened bout by bout; more power when the noise model is right, false "
                    "significance on the 84-h record where it is not: docs/diagnose.md)",
    )
    bout_gap_s: float = Field(60.0, ge=0, description="a still bout continues across gaps of at most this, s")
    bout_angle_deg: float = Field(
        5.0, ge=0, description="... and direction changes of at most this between consecutive windows, deg"
    )
    noise_max_lag_s: float = Field(900.0, gt=0, description="longest lag of the within-bout covariance fit, s")
    noise_boot: int = Field(200, ge=0, description="bootstrap replicates (over bouts) for the noise-model sds")

    @classmethod
    def from_section(cls, section: dict[str, Any] | None) -> "DiagnoseConfig":
        """Validate the ``[diagnose]`` TOML section."""
        return cls(**(section or {}))


# ----------------------------------------------------------------------------- statistics


def _ols_slope_r2(x: np.ndarray, y: np.ndarray) -> tuple[float, float]:
    if x is None or np.ptp(x) == 0 or len(x) < 3:
        return float("nan"), float("nan")
    xc = x - x.mean()
    yc = y - y.mean()
    slope = float(xc @ yc / (xc @ xc))
    ss = yc @ yc
    r2 = float(1 - np.sum((yc - slope * xc) ** 2) / ss) if ss > 0 else 0.0
    return slope, r2


def residual_stats(res_g: np.ndarray, gdir: np.ndarray, t_s: np.ndarray, temp_c: np.ndarray | None,
                   bout: np.ndarray | None = None) -> dict[str, float]:
    """Residual statistics of one fit, shape-free numbers.

    Parameters
    ----------
    res_g : (n,) norm residuals, g
    gdir : (n, 3) unit gravity directions (calibrated)
    t_s : (n,) s
    temp_c : (n,) degC or None
    bout : (n,) int still-bout labels, or None. With labels, ``bout_share`` is the share of
        the residual variance (windows of bouts of two or more) that lies between bout
        means (one-way ANOVA R²).
    """
    order = np.argsort(t_s, kind="stable")
    r = res_g[order] * 1e3
    out = {"rms_mg": float(np.sqrt(np.mean(r**2)))}
    slope, r2 = _ols_slope_r2(None if temp_c is None else temp_c[order], r)
    out["temp_slope_mg_per_c"], out["temp_r2"] = slope, r2
    slope, r2 = _ols_slope_r2(t_s[order] / 86400.0, r)
    out["time_slope_mg_per_day"], out["time_r2"] = slope, r2
    # orientation structure: residual regressed on cubic direction terms (what affine9 cannot absorb)
    g = gdir[order]
    design = np.column_stack([g**3, np.ones(len(g))])
    coef, *_ = np.linalg.lstsq(design, r, rcond=None)
    ss = np.sum((r - r.mean()) ** 2)
    out["orientation_r2"] = float(1 - np.sum((r - design @ coef) ** 2) / ss) if ss > 0 else 0.0
    out["lag1_autocorr"] = float(np.corrcoef(r[:-1], r[1:])[0, 1]) if len(r) > 3 and np.std(r) > 0 else float("nan")
    if bout is not None:
        out["bout_share"] = _bout_share(res_g * 1e3, np.asarray(bout))
    return out


def _bout_share(r: np.ndarray, bout: np.ndarray) -> float:
    """One-way ANOVA R² of residuals on bout labels, over bouts of two windows or more."""
    size = np.bincount(bout)
    multi = size[bout] >= 2
    if multi.sum() < 3:
        return float("nan")
    r, b = r[multi], bout[multi]
    mean_b = np.bincount(b, r) / np.maximum(np.bincount(b), 1)
    ss = np.sum((r - r.mean()) ** 2)
    return float(1 - np.sum((r - mean_b[b]) ** 2) / ss) if ss > 0 else float("nan")


# ----------------------------------------------------------------------------- helpers


@dataclass
class _Data:
    u: np.ndarray  # (n,3) normalised means
    sd_u: np.ndarray | None
    count: np.ndarray
    t_s: np.ndarray
    temp_c: np.ndarray | None

    def poses(self, idx=None) -> PoseData:
        idx = slice(None) if idx is None else idx
        return PoseData(self.u[idx], None if self.sd_u is None else self.sd_u[idx], self.count[idx], self.t_s[idx],
                        None if self.temp_c is None else self.temp_c[idx])


def _fit(model: ErrorModel, data: _Data, idx=None, cfg: FitConfig | None = None, theta0=None):
    return fit_poses(model, data.poses(idx), cfg=cfg, prior=datasheet_prior(model, cfg), theta0_u=theta0)


#: Restarts of the base fit from its own optimum, at most, until its chi-square stops falling.
BASE_FIT_RESTARTS = 20


def _fit_converged(model: ErrorModel, data: _Data, cfg: FitConfig | None = None, theta0=None):
    """:func:`_fit` on every pose, restarted from its own optimum until its chi-square falls by
    less than a millionth: the candidates' F-tests compare their chi-square with this one, and
    a base fit that had stopped short (poses in few orientations: undetermined directions)
    made every candidate look significant (p ~ 1e-5 with one orientation, 1e-55 with two)."""
    fit = _fit(model, data, None, cfg, theta0)
    chi2 = float(np.sum((fit.residuals_g / fit.sigma_g) ** 2))
    for _ in range(BASE_FIT_RESTARTS):
        again = _fit(model, data, None, cfg, fit.theta_u)
        chi2_again = float(np.sum((again.residuals_g / again.sigma_g) ** 2))
        if not chi2_again < chi2 * (1 - 1e-6):
            break
        fit, chi2 = again, chi2_again
    return fit


def _heldout_rms(model: ErrorModel, theta_u, data: _Data, idx) -> float:
    if not np.any(idx):  # nothing held out (every pose at one time): no RMS, and no numpy warning
        return float("nan")
    r = model.residuals(theta_u, data.u[idx], None if data.temp_c is None else data.temp_c[idx], data.t_s[idx])
    return float(np.sqrt(np.mean(r**2)) * 1e3)


def _time_split(data: _Data, frac: float) -> tuple[np.ndarray, np.ndarray]:
    t_cut = data.t_s.min() + frac * np.ptp(data.t_s)
    train = data.t_s <= t_cut
    return train, ~train


def _cv_rms(model, data: _Data, folds: np.ndarray, fit_cfg: FitConfig, theta0) -> float:
    """Cross-validated RMS (mg): each fold label held out in turn, fit on the rest."""
    sq = []
    for k in np.unique(folds):
        test = folds == k
        try:
            f = _fit(model, data, ~test, fit_cfg, theta0)
        except InputError:
            continue
        r = model.residuals(f.theta_u, data.u[test], None if data.temp_c is None else data.temp_c[test], data.t_s[test])
        sq.append(r**2)
    return float(np.sqrt(np.mean(np.concatenate(sq))) * 1e3) if sq else float("nan")


def _cv_folds(data: _Data, cfg: DiagnoseConfig, bouts: Bouts) -> tuple[np.ndarray, np.ndarray]:
    """Fold labels (n,) of the blocked time CV and of the k-fold CV, holding out whole bouts.

    A bout goes to the time block of its first window; the k folds deal bouts in turn, in
    the input order of their first windows. With one window per bout these are the
    per-window blocks and ``arange(n) % k``.
    """
    span = max(np.ptp(data.t_s), 1e-9)
    blocks = np.minimum(((data.t_s - data.t_s.min()) / span * cfg.time_blocks).astype(int), cfg.time_blocks - 1)
    first = bouts.first_index()
    rank = np.empty(len(first), dtype=np.int64)
    rank[np.argsort(first, kind="stable")] = np.arange(len(first))
    return blocks[first][bouts.label], rank[bouts.label] % cfg.pose_folds


def _split_scores(model: ErrorModel, data: _Data, cfg: DiagnoseConfig, fit_cfg: FitConfig, theta0=None,
                  bouts: Bouts | None = None) -> dict[str, float]:
    """Held-out RMS (mg) by blocked time CV (contiguous blocks), by pose CV (k folds of
    bouts) and on the plain chronological split (first part fits, the rest is held out)."""
    train, test = _time_split(data, cfg.time_split)
    out = {}
    try:
        f = _fit(model, data, train, fit_cfg, theta0)
        out["chrono"] = _heldout_rms(model, f.theta_u, data, test)
    except InputError:
        out["chrono"] = float("nan")
    blocks, folds = _cv_folds(data, cfg, bouts if bouts is not None else Bouts.singletons(data.t_s))
    out["time"] = _cv_rms(model, data, blocks, fit_cfg, theta0)
    out["pose"] = _cv_rms(model, data, folds, fit_cfg, theta0)
    return out


def _not_testable(effect: str, temp_c: np.ndarray | None, t_s: np.ndarray, cfg: DiagnoseConfig,
                  base: str = "affine9") -> str | None:
    """Why a candidate effect cannot be tested on these poses (temperature, time span) with
    the ``base`` model, or None."""
    if not ErrorModel(base).takes(effect):
        return f"not testable: {base} takes no {effect}"
    if effect.startswith("temperature") and temp_c is None:
        return "not testable: the recording has no temperature"
    if effect.startswith("temperature") and np.ptp(temp_c) < cfg.min_temp_range_c:
        return f"not testable: temperature range {np.ptp(temp_c):.1f} degC < {cfg.min_temp_range_c} degC"
    if effect in ("time_drift_bias", "bias_step") and np.ptp(t_s) < cfg.min_time_span_h * 3600:
        return f"not testable: time span {np.ptp(t_s) / 3600:.1f} h < {cfg.min_time_span_h} h"
    return None


def _refine_step(entry: dict, base_fit, data: _Data, sigma, q, times: np.ndarray, fit_cfg: FitConfig,
                 unit: str, factor: float, max_times: int = 200) -> None:
    """A supported step's time, refined between the scanned times around it (every gap
    between two poses there, at most ``max_times``); the fit and the estimate are redone
    at the refined time when it fits better. Estimation only: the test keeps the scanned
    time and its Bonferroni count (a finer scan would be more looks)."""
    tau = entry["step_time_s"]
    tau_f = refine_time(base_fit, data.u, data.temp_c, data.t_s, sigma, q, times, tau, max_times)
    if tau_f == tau:
        return
    old = entry["_fit"]
    ext = ErrorModel(old.model.name, old.model.temp_ref_c, old.model.t_ref_s, tau_f)
    fit = fit_poses(ext, data.poses(), prior=datasheet_prior(ext, fit_cfg), theta0_u=old.theta_u, cfg=fit_cfg)
    if np.sum((fit.residuals_g / fit.sigma_g) ** 2) >= np.sum((old.residuals_g / old.sigma_g) ** 2):
        return
    sl = ext.index("bias_step")
    est = fit.theta_u[sl] * factor
    est_sd_ind = np.sqrt(np.diag(fit.cov_u)[sl]) * factor
    est_sd = est_sd_ind * entry["_std_factor"][sl]
    entry.update(step_time_s=tau_f, step_time_h=_f((tau_f - ext.t_ref_s) / 3600.0), step_time_scanned_s=tau,
                 _fit=fit,
                 estimate={"unit": unit, "value": dict(zip("xyz", np.round(est, 6).tolist())),
                           "std": dict(zip("xyz", np.round(est_sd, 6).tolist())),
                           "std_independent": dict(zip("xyz", np.round(est_sd_ind, 6).tolist()))})


def _noise_residuals(base_fit, data: _Data, effects: list[str]) -> tuple[np.ndarray, tuple[np.ndarray, np.ndarray]]:
    """Base-fit residuals (g, (n,)) with every testable candidate effect's pattern removed,
    and the projection used, ``(q (n, k) orthonormal whitened columns, sigma_g (n,))``.

    The candidates' Jacobian columns at the base fit (zero effect), with the base model's,
    are projected out in the fit's weighted metric. The noise model is estimated from
    these: an effect the base model misses is smooth in time, so left in it would be taken
    for noise correlated within bouts, and its own evidence discounted by it.
    """
    sigma = base_fit.sigma_g
    cols = [base_fit.model.residual_jac(base_fit.theta_u, data.u, data.temp_c, data.t_s)[1]]
    for eff in effects:
        ext = base_fit.model.with_effects((eff,))
        theta = ext.extend_theta(base_fit.theta_u, base_fit.model)
        cols.append(ext.residual_jac(theta, data.u, data.temp_c, data.t_s)[1][:, ext.index(eff)])
    q = _orth(np.column_stack(cols) / sigma[:, None])
    rw = base_fit.residuals_g / sigma
    return (rw - q @ (q.T @ rw)) * sigma, (q, sigma)


def _correlated_covariances(model: ErrorModel, base_fit, data: _Data, noise: BoutNoise | None, bouts: Bouts,
                            noise_g: np.ndarray, fit_cfg: FitConfig) -> tuple[np.ndarray, np.ndarray] | None:
    """Linearised covariances (normalised units, (p, p)) of ``model``'s parameters at the
    base fit: ``(A^-1, A^-1 M A^-1)``, under independent noise and under the fitted
    correlated noise (sandwich), with ``A = J' W J + prior`` and ``M = J' W Sigma W J + prior``.

    ``J`` is the Jacobian at the base fit (zero effect) and ``W`` the inverse of each
    window's variance in the fit, ``sigma_g^2``. ``Sigma`` has the noise model's
    correlations on the fit's variances: ``Sigma_ij = rho_ij sigma_g,i sigma_g,j`` (the
    level is the F test's business, the correlation the design effect's). ``noise_g`` (n,)
    is each window's measured noise (g). None when the noise model has no correlated part
    (the two covariances are then equal).
    """
    if noise is None or noise.correlated_var_g2 <= 0:
        return None
    theta0 = model.extend_theta(base_fit.theta_u, base_fit.model)
    j = model.residual_jac(theta0, data.u, data.temp_c, data.t_s)[1]
    var = base_fit.sigma_g**2
    y = j / var[:, None]
    lam = datasheet_prior(model, fit_cfg).precision()
    binv = np.linalg.inv(j.T @ y + lam)
    indep = noise_g**2 + noise.sigma_white_g**2
    scale = np.sqrt(var / (indep + noise.correlated_var_g2))[:, None]  # model marginal -> fit marginal
    meat = y.T @ (scale * noise.cov_matvec(bouts, indep, scale * y)) + lam
    return binv, binv @ meat @ binv


def _std_factor(covs: tuple[np.ndarray, np.ndarray] | None, p: int) -> np.ndarray:
    """Per-parameter sd inflation (p,) from independent to correlated noise (1 without correlation)."""
    if covs is None:
        return np.ones(p)
    return np.sqrt(np.diag(covs[1]) / np.diag(covs[0]))


def _inflate(cov_u: np.ndarray, factor: np.ndarray) -> np.ndarray:
    """``cov_u`` with each sd multiplied by ``factor`` (correlations kept), (p, p)."""
    return cov_u * np.outer(factor, factor)


def _design_effect(covs: tuple[np.ndarray, np.ndarray] | None, sl: slice, estimate: np.ndarray) -> float:
    """How many times the independent-noise F statistic over-counts an effect's evidence.

    The Wald statistic of the effect's estimate (``estimate``, its parameters at ``sl``)
    under the independent-noise covariance over the same under the correlated-noise
    sandwich (:func:`_correlated_covariances`). Exactly 1 when the noise model has no
    correlated part.
    """
    if covs is None:
        return 1.0
    v_ind, v_cor = covs[0][sl, sl], covs[1][sl, sl]
    c = np.asarray(estimate, float)
    w_ind = float(c @ np.linalg.solve(v_ind, c))
    w_cor = float(c @ np.linalg.solve(v_cor, c))
    if w_ind > 0 and w_cor > 0:
        return w_ind / w_cor
    return float(np.trace(np.linalg.solve(v_ind, v_cor)) / len(c))


def _orth(a: np.ndarray) -> np.ndarray:
    """Orthonormal basis of the column span of ``a`` (n, k), rank-revealing."""
    u, sv, _ = np.linalg.svd(a, full_matrices=False)
    return u[:, sv > (sv[0] if len(sv) else 0.0) * 1e-10]


class _GlsBase:
    """The residuals ``r`` (n,) and the base model's columns ``x`` (n, p), in g, whitened
    once by ``whiten`` (:meth:`selfcal.boutnoise.BoutNoise.whitener`) with the base
    columns projected out, for the F test of every candidate (:meth:`f`)."""

    def __init__(self, whiten, r: np.ndarray, x: np.ndarray):
        self.whiten = whiten
        w = whiten(np.column_stack([r, x]))
        self.qx = _orth(w[:, 1:])
        self.e = w[:, 0] - self.qx @ (self.qx.T @ w[:, 0])

    def f(self, c: np.ndarray) -> tuple[float, int]:
        """Score F statistic of adding the columns ``c`` (n, k), g: the generalised-least-
        squares test, linearised at the fit that gave ``r``. Returns ``(F, residual dof)``;
        F is free of the noise level (the residual variance after both is its denominator)."""
        ct = self.whiten(c)
        qc = _orth(ct - self.qx @ (self.qx.T @ ct))
        t = float(np.sum((qc.T @ self.e) ** 2))
        dof = max(len(self.e) - self.qx.shape[1] - qc.shape[1], 1)
        k = max(qc.shape[1], 1)
        rss = max(float(self.e @ self.e) - t, 1e-300)
        return (t / k) / (rss / dof), dof


def _whitened_projection(fit, data: _Data):
    """Base-model Jacobian columns (whitened) and the projector onto their complement."""
    return whitened_basis(fit, data.u, data.temp_c, data.t_s)


def _effect_columns(ext: ErrorModel, effect: str, base_fit, data: _Data, sigma, q) -> np.ndarray:
    """Whitened Jacobian columns of ``effect`` in ``ext`` (the base model plus it) at zero
    effect, with the base part projected out."""
    theta = ext.extend_theta(base_fit.theta_u, base_fit.model)
    j = ext.residual_jac(theta, data.u, data.temp_c, data.t_s)[1][:, ext.index(effect)] / sigma[:, None]
    return j - q @ (q.T @ j)


# ----------------------------------------------------------------------------- main


def diagnose_poses(
    mean: np.ndarray,
    sd: np.ndarray | None,
    count: np.ndarray,
    t_s: np.ndarray,
    temp_c: np.ndarray | None,
    normalizer: Normalizer | None = None,
    config: dict | None = None,
    base_model: str = "affine9",
    keep_arrays: bool = False,
) -> dict:
    """Diagnose a table of still poses; returns the design-contract JSON (dict).

    With ``keep_arrays`` the dict also holds ``_arrays`` (residuals, covariates and one
    simulated replicate) for plotting; it is not JSON.

    Parameters
    ----------
    mean, sd : ndarray, shape (n, 3), raw unit
    count : ndarray, shape (n,) — samples per pose
    t_s : ndarray, shape (n,), s
    temp_c : ndarray, shape (n,), degC, or None
    normalizer : Normalizer — raw -> ~g (identity for data in g)
    config : loaded configuration (sections ``diagnose`` and ``fit``)
    """
    from selfcal.config import section

    cfg = DiagnoseConfig.from_section(section(config, "diagnose"))
    fit_cfg = FitConfig.from_section(section(config, "fit"))
    normalizer = normalizer or Normalizer()
    mean = np.asarray(mean, dtype=float)
    if len(mean) == 0:
        raise InputError("diagnose: no still window in the recording")
    if len(mean) < 12:  # too few orientations for the base model: what soaks can say, never a refusal
        return soak_only_report(mean, sd, count, t_s, temp_c, normalizer, config)
    t_s = np.asarray(t_s, dtype=float)
    temp = None if temp_c is None else np.asarray(temp_c, dtype=float)
    if temp is not None and not np.all(np.isfinite(temp)):
        temp = None if np.mean(np.isfinite(temp)) < 0.5 else np.where(np.isfinite(temp), temp, np.nanmedian(temp))
    data = _Data(normalizer.to_u(mean), None if sd is None else np.asarray(sd, float) / normalizer.scale,
                 np.asarray(count, dtype=float), t_s, temp)
    temp_ref = float(np.median(temp)) if temp is not None else 25.0
    t_ref = float(t_s.min())
    base = ErrorModel(base_model, temp_ref, t_ref)
    if base.effects:  # the candidates are effects added to a bare base: tests nested in it
        raise InputError(f"base model {base.name}: give a base without effects (affine9, scale6, ...); the "
                         f"effects ({', '.join(base.effects)}) are the candidates diagnose tests against it")
    base_fit = _fit_converged(base, data, fit_cfg)
    # each window's measured noise on the norm (g), without any floor
    noise = pose_sigma(data.u, data.sd_u, data.count, fit_cfg.model_copy(update={"sigma_floor_g": 0.0}))
    if cfg.estimate_floor:
        # the floor is what the base model leaves beyond the measured noise (moment match)
        floor = float(np.sqrt(max(np.mean(base_fit.residuals_g**2 - noise**2), 0.0)))
        fit_cfg = fit_cfg.model_copy(update={"sigma_floor_g": max(floor, 1e-5)})
        base_fit = _fit_converged(base, data, fit_cfg, base_fit.theta_u)
    a = base.apply(base_fit.theta_u, data.u)
    gdir = a / np.linalg.norm(a, axis=1, keepdims=True)

    # ---------------------------------------------------------------- noise model
    noise_model: BoutNoise | None = None
    bouts = Bouts.singletons(t_s)
    bout_labels = None
    if cfg.noise_model == "bouts":
        found = find_bouts(t_s, gdir, cfg.bout_gap_s, cfg.bout_angle_deg)
        testable = [e for e in EFFECTS if _not_testable(e, temp, t_s, cfg, base.base) is None]
        res_noise, projection = _noise_residuals(base_fit, data, testable)
        noise_model = estimate_bout_noise(res_noise, noise, found, cfg.noise_max_lag_s, cfg.noise_boot, cfg.seed,
                                          projection)
        bout_labels = found.label
        if noise_model.correlated_var_g2 > 0:
            # correlated windows: bouts are the units of the simulation, the tests and the CV folds;
            # without a correlated part every window is its own unit, as with independent noise
            bouts = found

    # ---------------------------------------------------------------- discrepancy vs simulation
    measured = residual_stats(base_fit.residuals_g, gdir, t_s, temp, bout_labels)
    rng = np.random.default_rng(cfg.seed)
    matrix, offset = base.linear(base_fit.theta_u)
    inv = np.linalg.inv(matrix)
    raw_clean = gdir @ inv.T + offset
    sd_u = data.sd_u if data.sd_u is not None else np.full_like(data.u, fit_cfg.default_sample_sd_g)
    noise_sd = sd_u / np.sqrt(data.count)[:, None]
    sims = []
    sim_residuals = None
    for _ in range(cfg.n_sim):
        raw_sim = raw_clean + rng.normal(0.0, 1.0, raw_clean.shape) * noise_sd
        if noise_model is not None:
            # the correlated excess (bout, AR(1)) moves each window along its gravity direction; the
            # independent excess (the floor) stays out, as before, and shows as a level discrepancy
            eps = noise_model.draw(rng, bouts, white=False)
            if np.any(eps):
                raw_sim = raw_sim + (gdir * eps[:, None]) @ inv.T
        sim = _Data(raw_sim, data.sd_u, data.count, t_s, temp)
        f = fit_poses(base, sim.poses(), prior=datasheet_prior(base, fit_cfg), theta0_u=base_fit.theta_u, cfg=fit_cfg)
        sims.append(residual_stats(f.residuals_g, gdir, t_s, temp, bout_labels))
        if sim_residuals is None:
            sim_residuals = f.residuals_g
    discrepancy = {}
    for key, value in measured.items():
        vals = np.array([s[key] for s in sims], dtype=float)
        ok = np.isfinite(vals)
        mu = float(np.mean(vals[ok])) if ok.any() else float("nan")
        sdv = float(np.std(vals[ok], ddof=1)) if ok.sum() > 1 else float("nan")
        z = (value - mu) / sdv if np.isfinite(value) and sdv and np.isfinite(sdv) and sdv > 0 else float("nan")
        discrepancy[key] = {"measured": _f(value), "simulated_mean": _f(mu), "simulated_sd": _f(sdv), "z": _f(z)}
    discrepancy["rms_ratio_measured_over_simulated"] = _f(measured["rms_mg"] / discrepancy["rms_mg"]["simulated_mean"])
    discrepancy["noise_level_mg"] = _f(float(np.sqrt(np.mean(np.sum((noise_sd * gdir) ** 2, axis=1)))) * 1e3)

    # ---------------------------------------------------------------- candidates
    base_scores = _split_scores(base, data, cfg, fit_cfg, base_fit.theta_u, bouts)
    guard_cfg = GuardConfig.from_section(section(config, "guard"))
    n = len(data.u)
    chi2_base = float(np.sum((base_fit.residuals_g / base_fit.sigma_g) ** 2))
    sigma, q = _whitened_projection(base_fit, data)
    level = cfg.alpha / len(CANDIDATES)
    gls = None  # the residuals and the base model's columns, whitened once for every candidate
    if cfg.correlated_test == "gls" and noise_model is not None and noise_model.correlated_var_g2 > 0:
        gls = _GlsBase(noise_model.whitener(bouts, noise**2 + noise_model.sigma_white_g**2), base_fit.residuals_g,
                       base.residual_jac(base_fit.theta_u, data.u, data.temp_c, data.t_s)[1])
    candidates = []
    for eff in CANDIDATES:
        entry: dict[str, Any] = {"name": eff, "selected": False, "evidence": "", "estimate": None}
        why_not = _not_testable(eff, temp, t_s, cfg, base.base)
        looks = 1  # the step's time is chosen by a scan over this many candidate times
        if eff == "bias_step" and why_not is None:
            times = step_times(t_s, cfg)
            if len(times) == 0:
                why_not = "not testable: no time between two poses to place a step"
            else:
                tau, _ = scan_step(base_fit, data.u, data.temp_c, data.t_s, sigma, q, times)
                looks = len(times)
                entry["step_time_s"] = tau
                entry["step_time_h"] = _f((tau - t_ref) / 3600.0)
                entry["step_times_scanned"] = looks
        if why_not:
            entry["evidence"] = why_not
            candidates.append(entry)
            continue
        ext = ErrorModel(f"{base.base}+{eff}", temp_ref, t_ref, entry.get("step_time_s", float("nan")))
        ext_fit = fit_poses(ext, data.poses(), prior=datasheet_prior(ext, fit_cfg),
                            theta0_u=ext.extend_theta(base_fit.theta_u, base), cfg=fit_cfg)
        chi2_ext = float(np.sum((ext_fit.residuals_g / ext_fit.sigma_g) ** 2))
        dof = max(n - base.n_params - 3, 1)
        f_indep = max(chi2_base - chi2_ext, 0.0) / 3.0 / (chi2_ext / dof)
        # correlated noise: the evidence the windows carry is divided by the design effect
        covs = _correlated_covariances(ext, base_fit, data, noise_model, bouts, noise, fit_cfg)
        deff = _design_effect(covs, ext.index(eff), ext_fit.theta_u[ext.index(eff)])
        std_factor = _std_factor(covs, ext.n_params)
        fstat = f_indep / deff
        if gls is not None:
            # generalised least squares: the effect's columns against the base model's, each
            # bout whitened by its covariance (the changes within a bout carry the evidence
            # that its shared error hides); the design effect is then what it over-counted
            jac_eff = ext.residual_jac(ext.extend_theta(base_fit.theta_u, base), data.u, data.temp_c,
                                       data.t_s)[1][:, ext.index(eff)]
            fstat, dof = gls.f(jac_eff)
            deff = f_indep / fstat if fstat > 0 else float("inf")
        pval = min(1.0, looks * float(stats.f.sf(fstat, 3, dof)))
        scores = _split_scores(ext, data, cfg, fit_cfg, ext_fit.theta_u, bouts)
        # a fit that leaves the plausible range, or folds the poses onto a few directions
        # (a degenerate minimum of the norm objective), explains nothing physical
        why_implausible = implausible(ext, ext_fit.theta_u, guard_cfg)
        a_ext = ext.apply(ext_fit.theta_u, data.u, data.temp_c, data.t_s)
        cosang = np.sum(a_ext * gdir, axis=1) / np.linalg.norm(a_ext, axis=1)
        moved_deg = float(np.degrees(np.arccos(np.clip(np.median(cosang), -1, 1))))
        if why_implausible is None and moved_deg > 5.0:
            why_implausible = f"the fit turns the median pose direction by {moved_deg:.0f} deg (a degenerate fold)"
        gain_time = 1 - scores["time"] / base_scores["time"] if base_scores["time"] > 0 else float("nan")
        gain_pose = 1 - scores["pose"] / base_scores["pose"] if base_scores["pose"] > 0 else float("nan")
        # a step is judged on the split by pose alone: a held-out time block on one side of
        # the step leaves the fit nothing to tell the offset before it from the one after
        gain_cv = gain_pose if eff == "bias_step" else np.nanmean([gain_time, gain_pose])
        sl = ext.index(eff)
        unit, factor = EFFECT_UNITS[eff]
        est = ext_fit.theta_u[sl] * factor
        est_sd_ind = np.sqrt(np.diag(ext_fit.cov_u)[sl]) * factor
        est_sd = est_sd_ind * std_factor[sl]
        cols = _effect_columns(ext, eff, base_fit, data, sigma, q)
        pattern = cols @ (ext_fit.theta_u[sl])  # whitened residual pattern the effect explains
        entry.update(
            chi2=chi2_ext, dchi2_eff=(chi2_base - chi2_ext) / deff, f_stat=_f(fstat), p_value=pval,
            f_stat_independent=_f(f_indep), design_effect=_f(deff), heldout_rms_mg_time=_f(scores["time"]),
            heldout_rms_mg_pose=_f(scores["pose"]), heldout_rms_mg_chrono=_f(scores["chrono"]),
            gain_time=_f(gain_time), gain_pose=_f(gain_pose), gain_cv=_f(gain_cv),
            estimate={"unit": unit, "value": dict(zip("xyz", np.round(est, 6).tolist())),
                      "std": dict(zip("xyz", np.round(est_sd, 6).tolist())),
                      "std_independent": dict(zip("xyz", np.round(est_sd_ind, 6).tolist()))},
            _fit=ext_fit, _cols=cols, _pattern=pattern, _std_factor=std_factor,
        )
        passes = (pval < level) and gain_cv >= cfg.min_gain_rel and why_implausible is None
        entry["supported"] = bool(passes)
        if eff == "bias_step" and passes:
            _refine_step(entry, base_fit, data, sigma, q, times, fit_cfg, unit, factor)
        deff_note = "" if deff == 1.0 else f"; design effect {deff:.1f} under the bout noise, F={f_indep:.1f} if independent"
        if gls is not None:
            deff_note = f"; generalised least squares under the bout noise, F={f_indep:.1f} if independent"
        entry["evidence"] = (
            f"F={fstat:.1f} (p={pval:.2g}, 3 extra parameters{deff_note}); held-out RMS {base_scores['time']:.3f} -> "
            f"{scores['time']:.3f} mg by time blocks, {base_scores['pose']:.3f} -> {scores['pose']:.3f} mg by pose"
        )
        if eff == "bias_step":
            refined = (f", refined to {entry['step_time_h']:.1f} h" if "step_time_scanned_s" in entry else "")
            entry["evidence"] += (f"; the step at {(entry.get('step_time_scanned_s', entry['step_time_s']) - t_ref) / 3600:.1f} h "
                                  f"scores best of {looks} times scanned (p multiplied by {looks}){refined}")
        if not passes:
            why = []
            if pval >= level:
                why.append("not significant")
            if not gain_cv >= cfg.min_gain_rel:
                split = "the split by pose" if eff == "bias_step" else "mean of the time and pose splits"
                why.append(f"held-out gain {gain_cv:.1%} ({split}) below {cfg.min_gain_rel:.0%}")
            if why_implausible:
                why.append("implausible: " + why_implausible)
            entry["evidence"] += "; not supported: " + ", ".join(why)
        candidates.append(entry)

    supported = [c for c in candidates if c.get("supported")]
    cause = None
    ambiguous: list[str] = []
    if supported:
        # the largest chi2 reduction, each divided by its design effect (with independent
        # noise: the lowest chi2)
        # a secondary candidate (rare, and on mostly flat poses nearly a copy of a primary)
        # is named only when it beats every supported primary by the separability margin;
        # otherwise it neither wins nor makes a primary ambiguous
        primary = [c for c in supported if c["name"] not in SECONDARY_EFFECTS]
        best = max(primary or supported, key=lambda c: c["dchi2_eff"])
        for c in supported:
            if c["name"] in SECONDARY_EFFECTS and c is not best and primary:
                margin = (c["dchi2_eff"] - best["dchi2_eff"]) / (c["chi2"] / max(n - base.n_params - 3, 1))
                if margin >= cfg.separable_dchi2:
                    best = c
                else:
                    c["evidence"] += (f"; secondary: named only when it beats {best['name']} by "
                                      f"{cfg.separable_dchi2:g} chi2 units (by {margin:.1f})")
        # separability: a rival that also explains the data significantly and fits almost as
        # well (non-nested comparison, chi2 difference in residual-variance units) cannot be
        # told apart from the best by these poses
        s2 = best["chi2"] / max(n - base.n_params - 3, 1)
        pat = best["_pattern"]
        for c in candidates:
            if c is best or "_cols" not in c:
                continue
            coef, *_ = np.linalg.lstsq(c["_cols"], pat, rcond=None)
            overlap = float(1 - np.sum((pat - c["_cols"] @ coef) ** 2) / max(pat @ pat, 1e-300))
            dchi2 = (best["dchi2_eff"] - c["dchi2_eff"]) / s2
            c["reproduces_best_r2"] = _f(overlap)
            c["dchi2_vs_best"] = _f(dchi2)
            if best["name"] not in SECONDARY_EFFECTS and c["name"] in SECONDARY_EFFECTS:
                continue  # a secondary that did not win does not make a primary ambiguous
            if c["p_value"] < level and dchi2 < cfg.separable_dchi2:
                ambiguous.append(c["name"])
        if ambiguous:
            best["evidence"] += (
                "; the poses cannot separate it from " + ", ".join(ambiguous) +
                f" (a rival fits within {cfg.separable_dchi2:g} chi2 units and reproduces the same residual pattern):"
                " no cause named"
            )
        else:
            cause = best["name"]
            best["selected"] = True
            best["evidence"] += "; selected"

    # ---------------------------------------------------------------- gain on the chronological split
    train, test = _time_split(data, cfg.time_split)
    extended_model = None
    gain = {"split": f"chronological: fit on the first {cfg.time_split:.0%} of the time span, evaluate on the rest",
            "n_fit": int(train.sum()), "n_heldout": int(test.sum()),
            "heldout_rms_mg_before": _f(base_scores["chrono"]), "heldout_rms_mg_after": None}
    if cause is not None:
        best = next(c for c in candidates if c["name"] == cause)
        ext = best["_fit"].model
        gain["heldout_rms_mg_after"] = best["heldout_rms_mg_chrono"]
        if "bias_step" in ext.effects:
            # the chronological split's first part holds few poses after a step (none when it is
            # after the cut): its size stays near the prior's 0, and the split said a step named
            # right gained nothing (2.62 -> 2.62 mg for 3 mg, 5 of 8 seeds); the cross-validation
            # over poses, the rule that selects a step, measures it
            gain.update(split="pose cross-validation (a step: the chronological split's first part holds too few "
                              "poses after it to measure it)",
                        n_fit=None, n_heldout=int(len(data.t_s)),
                        heldout_rms_mg_before=_f(base_scores["pose"]), heldout_rms_mg_after=best["heldout_rms_mg_pose"])
        full = best["_fit"]
        extended_model = {
            "model": ext.name, "temp_ref_c": ext.temp_ref_c, "t_ref_s": ext.t_ref_s,
            **({"t_step_s": ext.t_step_s} if "bias_step" in ext.effects else {}),
            "params": ext.to_dict(normalizer.theta_to_raw(ext, full.theta_u)),
            "std": dict(zip(ext.param_names, np.sqrt(np.diag(
                normalizer.cov_to_raw(ext, _inflate(full.cov_u, best["_std_factor"])))).tolist())),
            "residual_rms_mg": full.residual_rms_mg,
        }
    arrays = None
    if keep_arrays:
        arrays = {"t_s": t_s, "temp_c": temp, "gdir": gdir, "res_base_mg": base_fit.residuals_g * 1e3,
                  "res_sim_mg": None if sim_residuals is None else sim_residuals * 1e3, "res_ext_mg": None}
        if cause is not None:
            arrays["res_ext_mg"] = next(c for c in candidates if c["name"] == cause)["_fit"].residuals_g * 1e3
    for c in candidates:
        for k in ("_fit", "_cols", "_pattern", "_std_factor", "chi2", "dchi2_eff"):
            c.pop(k, None)
    out = {
        "n_poses": n,
        "base_model": {
            "model": base.name,
            "params": base.to_dict(normalizer.theta_to_raw(base, base_fit.theta_u)),
            "std": dict(zip(base.param_names, np.sqrt(np.diag(normalizer.cov_to_raw(base, _inflate(
                base_fit.cov_u, _std_factor(_correlated_covariances(base, base_fit, data, noise_model, bouts, noise, fit_cfg),
                                            base.n_params))))).tolist())),
            "residual_rms_mg": base_fit.residual_rms_mg,
            "undetermined": [nm for nm, d in zip(base.param_names, base_fit.determined) if not d],
            "temp_ref_c": temp_ref,
        },
        "discrepancy": discrepancy,
        "noise_model": _noise_report(noise_model, cfg),
        "effects": candidates,
        "cause": cause,
        "ambiguous": ambiguous or None,
        "extended_model": extended_model,
        "gain": gain,
    }
    # soaks (one orientation, changing temperature): what they say about the temperature
    # terms, beside the multi-pose analysis. On the raw (normalised) means: their drift is
    # the model's own raw-unit tb, and it does not depend on a base fit that a recording
    # with few orientations cannot pin down.
    from selfcal.soak import soak_report

    out["soaks"] = soak_report(data.t_s, data.u, window_mean_variance(data.u, sd, count, normalizer), data.temp_c,
                               _soak_config(config))  # ([soak] was read on the soaks-only path only)
    if arrays is not None:
        out["_arrays"] = arrays
    return out


def _noise_report(noise_model: BoutNoise | None, cfg: DiagnoseConfig) -> dict:
    """The report's ``noise_model`` section (mg, s), with the bout rule used."""
    if noise_model is None:
        return {"model": "independent: each window's measured noise and the floor", "estimated": False}
    out = noise_model.to_report()
    out["bout_rule"] = {"gap_s": cfg.bout_gap_s, "angle_deg": cfg.bout_angle_deg}
    return out


def _f(x) -> float | None:
    x = float(x)
    return x if np.isfinite(x) else None


def window_mean_variance(mean_u: np.ndarray, sd, count, normalizer) -> np.ndarray:
    """Variance (g²) of each window mean per axis, with the fit's 0.3 mg floor."""
    count = np.maximum(np.asarray(count, float), 1.0)
    sd_u = np.full_like(mean_u, 2e-3) if sd is None else np.asarray(sd, float) / normalizer.scale
    return sd_u**2 / count[:, None] + (0.3e-3) ** 2


def _soak_config(config: dict | None):
    """The ``[soak]`` section as a SoakConfig (None: the defaults); InputError naming a key it
    does not have or a value of the wrong type."""
    from dataclasses import fields

    from selfcal.config import section
    from selfcal.soak import SoakConfig

    sec = section(config, "soak")
    if not sec:
        return None
    known = {f.name: f.type for f in fields(SoakConfig)}
    unknown = sorted(set(sec) - set(known))
    if unknown:
        raise InputError(f"config [soak]: unknown keys {unknown} (known: {sorted(known)})")
    for k, v in sec.items():
        if isinstance(v, bool) or not isinstance(v, (int, float)) or not np.isfinite(v) or v < 0:
            raise InputError(f"config [soak] {k} = {v!r}: expected a number >= 0")
    return SoakConfig(**sec)


def soak_only_report(mean, sd, count, t_s, temp_c, normalizer, config) -> dict:
    """The report for a recording with too few orientations for the base model (< 12 poses):
    the soaks it holds and what they determine, on the raw (normalised) means."""
    from selfcal.soak import soak_report

    normalizer = normalizer or Normalizer()
    u = normalizer.to_u(np.asarray(mean, float))
    soaks = soak_report(np.asarray(t_s, float), u, window_mean_variance(u, sd, count, normalizer), temp_c,
                        _soak_config(config))
    return {"kind": "soaks_only", "n_poses": int(len(u)),
            "why": f"{len(u)} poses: the base model needs 12 or more orientations; soaks need only one",
            # cause: an effect's name or None, as in every report (the answer's text is in "soaks")
            "soaks": soaks, "cause": ((soaks.get("combined") or {}).get("effect")
                                      if str(soaks.get("answer", "")).startswith("temperature") else None)}


def diagnose_recording(rec, config: dict | None = None, base_model: str = "affine9",
                       keep_arrays: bool = False, progress: bool = False) -> tuple[dict, dict]:
    """Diagnose a Recording or a file path (samples: still windows first; a file is streamed,
    with a progress bar on stderr if ``progress``).

    Returns (report, poses used).
    """
    import os

    from selfcal.pipeline import path_poses, recording_poses

    if isinstance(rec, (str, os.PathLike)):
        poses, normalizer, _, unit = path_poses(rec, config, progress=progress)
        mean, sd, count, t_s, temp = poses["mean"], poses["sd"], poses["count"], poses["t_s"], poses["temp_c"]
        report = diagnose_poses(mean, sd, count, t_s, temp, normalizer, config, base_model, keep_arrays)
        report["recording"] = os.fspath(rec)
        report["unit"] = unit
        return report, dict(poses, normalizer=normalizer)
    poses, normalizer, _ = recording_poses(rec, config)
    mean, sd, count, t_s, temp = poses["mean"], poses["sd"], poses["count"], poses["t_s"], poses["temp_c"]
    report = diagnose_poses(mean, sd, count, t_s, temp, normalizer, config, base_model, keep_arrays)
    report["recording"] = rec.path
    report["unit"] = rec.unit
    return report, dict(poses, normalizer=normalizer)

