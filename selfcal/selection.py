"""Online model selection: the calibrator extends its own error model when held-out poses say so.

On a schedule (``every_hours`` of data time), the online calibrator asks of its own pose
store, for each candidate effect that its model lacks (``temperature_bias``,
``temperature_scale``, ``time_drift_bias``, ``scale_nonlinearity``): would the model
with it predict poses it was not fitted to better? A candidate is **supported** when
both hold:

* **The terms themselves.** The extended model's fit on every cell: its effect terms,
  against their posterior covariance (Wald χ², 3 terms), beyond the ``1 − alpha``
  quantile. The posterior covariance is the one whose honesty the consistency bench
  checks, so this is a calibrated test; ``alpha`` is small because the question is
  asked again every day for every candidate (30 days × 4 candidates is 120 tests, and
  false switches must stay rare per device). This cheap test comes first: most checks
  of an effect-free device end here. Cheaper still, and before it: one Gauss-Newton step
  of the extended model from the current estimate (the effect at 0) gives the effect
  terms' chi2 of a score test (:func:`one_step_chi2`). Its covariance is the linear one,
  never inflated, so it is the larger of the two wherever the step lands where the fit
  does; a candidate whose one-step chi2 is below ``screen_ratio`` of the threshold is not
  fitted at all (``Comparison.screened``).
* **Held-out gain.** A k-fold cross-validation over the store's cells (the guard's
  folds: a hash of the cell key). Every cell is held out once; the base and the extended
  model are fitted without its fold and score it. The paired per-cell differences of
  the squared (clipped) norm residuals give a z-score of the gain, which must reach
  ``min_heldout_z``, and the held-out RMS must drop by ``min_gain_rel``.

The best supported candidate (largest relative held-out gain) is switched in. The calibrator
publishes the extended fit as a new version whose ``model_change`` says from what, to
what, why, and the gain. An effect that selection added is tested the other way round
at every later check, and dropped (a version again) when it no longer pays: its terms
are no longer significant at ``drop_alpha`` and its held-out z is below ``drop_z``.

Candidates need their covariate: temperature terms need cells with a temperature and a
span of ``min_temp_span_c`` across cells, the time drift ``min_time_span_days`` of data.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np
from pydantic import BaseModel, ConfigDict, Field
from scipy.special import chdtri

from selfcal.errors import InputError
from selfcal.fit import FitConfig, FitResult, NoiseModel, PoseData, Prior, fit_poses
from selfcal.models import EFFECT_PARAMS, ErrorModel


class SelectionConfig(BaseModel):
    """The ``[selection]`` section: when and how the online calibrator changes its model."""

    model_config = ConfigDict(extra="forbid")

    enabled: bool = Field(True, description="look for missing effects on a schedule and switch the model")
    every_hours: float = Field(24.0, gt=0, description="data time between two checks, h")
    min_cells: int = Field(48, ge=12, description="pose cells needed before the first check")
    candidates: list[str] = Field(default_factory=lambda: list(EFFECT_PARAMS),
                                  description="effects that may be switched in")
    alpha: float = Field(1e-4, gt=0, lt=0.5, description="false-alarm rate of one test of the effect terms (Wald)")
    min_heldout_z: float = Field(3.0, gt=0, description="z-score of the paired held-out gain needed to switch")
    min_gain_rel: float = Field(0.02, ge=0, description="relative held-out RMS gain needed to switch")
    drop_z: float = Field(1.0, description="a switched-in effect is dropped when its held-out z falls below this")
    drop_alpha: float = Field(0.01, gt=0, lt=1, description="...and its terms are not significant at this level")
    min_temp_span_c: float = Field(3.0, gt=0, description="temperature span across cells for temperature terms, degC")
    min_time_span_days: float = Field(3.0, gt=0, description="data span for the time drift, days")
    clip_mg: float = Field(20.0, gt=0, description="held-out residuals are clipped here (one wild cell cannot decide), mg")
    secondary_margin_chi2: float = Field(
        10.0, gt=0, description="a secondary effect beats a supported primary one when its Wald chi2 is this much larger")
    step: bool = Field(
        True, description="also look for a bias step (a shock, a battery change) when no effect is supported; once one "
                          "is found, the cells from before it are brought to today's offset by its size, refitted "
                          "with them")
    step_downweight: float = Field(
        10.0, ge=1, description="bias step: the sd of a cell with windows from both sides of a step grows by this many "
                                "times the step's size, and of a cell from before an earlier step by this many times "
                                "that step's sd")
    step_times: int = Field(9, ge=1, description="bias step: candidate times scanned (the Wald level is alpha / this)")
    step_min_side: float = Field(
        0.15, gt=0, lt=0.5, description="bias step: the outer candidate times leave this fraction of the cells outside")
    screen_ratio: float = Field(
        0.25, ge=0, lt=1, description="a candidate whose one-step (score) chi2 is below this fraction of its Wald "
                                      "threshold is not fitted: it is not supported (0: fit every candidate)")

    @classmethod
    def from_section(cls, section_: dict | None) -> "SelectionConfig":
        """Validate the ``[selection]`` TOML section; unknown candidates are an error."""
        cfg = cls(**(section_ or {}))
        bad = [c for c in cfg.candidates if c not in EFFECT_PARAMS]
        if bad:
            raise InputError(f"[selection] candidates: unknown {bad}; choose from {list(EFFECT_PARAMS)}")
        return cfg


@dataclass
class Comparison:
    """A smaller model against a larger one (one more effect) on the same cells."""

    effect: str
    small: str
    large: str
    heldout_z: float          # paired z of the held-out gain of the large model (> 0: it predicts better); NaN: not run
    heldout_rms_small_mg: float
    heldout_rms_large_mg: float
    n_heldout: int
    wald_chi2: float          # the effect terms of the large model's full fit against their covariance
    wald_dof: int
    large_fit: FitResult | None = None
    notes: list[str] = field(default_factory=list)
    screened: bool = False    # wald_chi2 is the one-step chi2 (:func:`one_step_chi2`): the large model was not fitted

    @property
    def gain_rel(self) -> float:
        """Relative held-out RMS gain of the large model (NaN when not cross-validated)."""
        if not self.heldout_rms_small_mg > 0:
            return float("nan")
        return 1.0 - self.heldout_rms_large_mg / self.heldout_rms_small_mg

    def to_dict(self) -> dict:
        """JSON-ready summary (mg, z, chi2; None where the cross-validation was skipped)."""
        return {"effect": self.effect, "small": self.small, "large": self.large, "heldout_z": rounded(self.heldout_z, 3),
                "heldout_rms_mg_before": rounded(self.heldout_rms_small_mg, 4),
                "heldout_rms_mg_after": rounded(self.heldout_rms_large_mg, 4),
                "heldout_gain_rel": rounded(self.gain_rel, 4), "n_heldout_cells": self.n_heldout,
                "wald_chi2": round(self.wald_chi2, 3), "wald_dof": self.wald_dof, "screened": self.screened}


def rounded(x: float, nd: int) -> float | None:
    """``x`` rounded to ``nd`` decimals for a JSON record; None when it is not finite (NaN: not measured)."""
    return None if not np.isfinite(x) else round(float(x), nd)


def extend_prior(prior: Prior, model: ErrorModel, target: ErrorModel, datasheet: Prior) -> Prior:
    """The prior of ``target`` (normalised units): ``prior`` (of ``model``) for the shared
    parameters, the datasheet ``datasheet`` (of ``target``) for the others."""
    mean = datasheet.mean.copy()
    cov = datasheet.cov.copy()
    idx = [target.param_names.index(n) for n in model.param_names if n in target.param_names]
    src = [i for i, n in enumerate(model.param_names) if n in target.param_names]
    mean[idx] = prior.mean[src]
    cov[np.ix_(idx, idx)] = prior.cov[np.ix_(src, src)]
    return Prior(mean, cov)


def applicable(effect: str, data: PoseData, cfg: SelectionConfig) -> str | None:
    """Why ``effect`` cannot be tested on these cells (its covariate is missing), or None."""
    if effect.startswith("temperature"):
        if data.temp_c is None or not np.all(np.isfinite(data.temp_c)):
            return "cells without a temperature"
        if float(np.ptp(data.temp_c)) < cfg.min_temp_span_c:
            return f"temperature span {float(np.ptp(data.temp_c)):.1f} degC < {cfg.min_temp_span_c:g}"
    if effect == "time_drift_bias":
        span = float(np.ptp(data.t_s)) / 86400.0
        if span < cfg.min_time_span_days:
            return f"data span {span:.1f} days < {cfg.min_time_span_days:g}"
    return None


def _clipped(model: ErrorModel, theta: np.ndarray, data: PoseData, clip_g: float) -> np.ndarray:
    """Norm residuals (g, shape (n,)) clipped at ``clip_g``: one wild cell cannot decide."""
    r = model.residuals(theta, data.mean, data.temp_c, data.t_s)
    return np.clip(r, -clip_g, clip_g)


def compare(small: ErrorModel, large: ErrorModel, data: PoseData, folds: np.ndarray, *,
            prior_small: Prior, prior_large: Prior, theta_small: np.ndarray, fit_cfg: FitConfig,
            clip_g: float, cv_small: dict[int, np.ndarray] | None = None,
            clusters: np.ndarray | None = None, cv_only_if=None, small_fit: FitResult | None = None,
            screen_if=None) -> Comparison:
    """Test ``large`` (``small`` plus one effect) against ``small`` on the cells ``data``.

    ``folds`` (n,) int: the held-out fold of each cell. ``clusters`` (n,): the direction
    cell of each (covariances and the held-out z are cluster-robust). ``cv_small``: the small model's
    held-out clipped residuals per fold (g), shared by candidates on the same cells
    (filled in when given empty). ``cv_only_if(wald_chi2, dof) -> bool``: run the
    cross-validation only when this says the Wald test leaves the question open.
    ``small_fit`` (the small model's robust fit on ``data``) and ``screen_if(chi2, dof) ->
    bool``: when both are given and ``screen_if`` holds for :func:`one_step_chi2`, the
    large model is not fitted (``screened``, ``large_fit`` None, ``wald_chi2`` the
    one-step chi2).
    Returns a :class:`Comparison` with the large model's full fit; its held-out fields
    are NaN when the cross-validation was skipped.
    """
    effect = next(e for e in large.effects if e not in small.effects)
    theta_large0 = large.extend_theta(theta_small, small)
    sl = large.index(effect)
    if small_fit is not None and screen_if is not None:
        chi2 = one_step_chi2(small_fit, large, data, prior_large=prior_large, theta_large0=theta_large0,
                             fit_cfg=fit_cfg)
        dof = sl.stop - sl.start
        if screen_if(chi2, dof):
            return Comparison(effect, small.name, large.name, np.nan, np.nan, np.nan, 0, chi2, dof, None,
                              ["not fitted: the one-step chi2 is far below the threshold"], screened=True)
    # the large model on every cell first: its effect terms against their covariance
    full = fit_poses(large, data, prior=prior_large, theta0_u=theta_large0, cfg=fit_cfg, robust=True,
                     clusters=clusters)
    coef = full.theta_u[sl]
    try:
        wald = float(coef @ np.linalg.solve(full.cov_u[sl, sl], coef))
    except np.linalg.LinAlgError:
        wald = 0.0
    out = Comparison(effect, small.name, large.name, np.nan, np.nan, np.nan, 0, wald, len(coef), full, [])
    if cv_only_if is not None and not cv_only_if(wald, len(coef)):
        out.notes.append("cross-validation skipped: the Wald test already decides")
        return out
    res_s = np.full(len(folds), np.nan)
    res_l = np.full(len(folds), np.nan)
    fold_cfg = fit_cfg.model_copy(update={"curvature_cov": False})  # their estimates alone are used
    for f in np.unique(folds):
        held = folds == f
        train = data.subset(~held)
        ref = data.subset(held)
        try:
            if cv_small is not None and f in cv_small:
                res_s[held] = cv_small[f]
            else:
                fs = fit_poses(small, train, prior=prior_small, theta0_u=theta_small, cfg=fold_cfg, robust=True)
                res_s[held] = _clipped(small, fs.theta_u, ref, clip_g)
                if cv_small is not None:
                    cv_small[f] = res_s[held]
            fl = fit_poses(large, train, prior=prior_large, theta0_u=full.theta_u, cfg=fold_cfg, robust=True)
            res_l[held] = _clipped(large, fl.theta_u, ref, clip_g)
        except InputError as exc:
            out.notes.append(f"fold {int(f)}: {exc}")
    ok = np.isfinite(res_s) & np.isfinite(res_l)
    n = int(ok.sum())
    out.n_heldout = n
    if n < 8:  # no held-out evidence: neither an add nor a drop may follow (z stays NaN)
        out.notes.append(f"{n} held-out cells: no comparison")
        return out
    d = res_s[ok] ** 2 - res_l[ok] ** 2
    out.heldout_z = paired_z(d, None if clusters is None else np.asarray(clusters)[ok])
    out.heldout_rms_small_mg = float(np.sqrt(np.mean(res_s[ok] ** 2)) * 1e3)
    out.heldout_rms_large_mg = float(np.sqrt(np.mean(res_l[ok] ** 2)) * 1e3)
    return out


def one_step_chi2(small_fit: FitResult, large: ErrorModel, data: PoseData, *, prior_large: Prior,
                  theta_large0: np.ndarray, fit_cfg: FitConfig) -> float:
    """The effect terms' chi2 after one Gauss-Newton step of ``large`` from ``theta_large0``
    (p,) (the small model's value, the effect's terms at 0): a score test on the cells
    ``data`` (g), in ~one Jacobian instead of a robust fit.

    The step solves ``(J^T W J + P) step = -(J^T W r + P (theta - mu))`` on the whitened
    residuals (the noise following the scales, as the fit's); the chi2 is the effect's
    part of the step against the same linear covariance ``(J^T W J + P)^-1``. The weights
    ``W`` are Huber's on ``small_fit``'s residuals (shape (n,), at its robust scale), with
    no cell rejected: a cell the small model cannot explain, but the effect can, still
    speaks. The full fit's chi2 divides by a covariance at least this large (inflated by
    the reduced chi2, the clusters' sandwich and the curvature), so where the step lands
    where the fit does the one-step chi2 is the larger.
    """
    nz = small_fit.normalizer
    if len(small_fit.residuals_g) != len(data.mean) or nz.scale != 1.0 or np.any(np.asarray(nz.center) != 0):
        return float("inf")  # not the fit of these cells in g: no screen, the fit decides
    z = small_fit.residuals_g / small_fit.sigma_g
    scale = float(small_fit.extra.get("robust_scale", 1.0))
    w = np.minimum(1.0, fit_cfg.robust_c / np.maximum(np.abs(z / scale), 1e-300))
    noise = NoiseModel.from_poses(data.mean, data.sd, data.count, fit_cfg, large, data.temp_c, data.t_s).scaled(w)
    _, _, rw, jw = noise.whitened(large, theta_large0, data.mean, data.temp_c, data.t_s)
    lam = prior_large.precision()
    a = jw.T @ jw + lam
    g = jw.T @ rw + lam @ (theta_large0 - prior_large.mean)
    effect = next(e for e in large.effects if e not in small_fit.model.effects)
    sl = large.index(effect)
    try:
        step = -np.linalg.solve(a, g)
        cov = np.linalg.inv(a)[sl, sl]
        chi2 = float(step[sl] @ np.linalg.solve(cov, step[sl]))
    except np.linalg.LinAlgError:
        return float("inf")  # no screen: the fit decides
    return chi2 if np.isfinite(chi2) else float("inf")


def paired_z(d: np.ndarray, clusters: np.ndarray | None = None) -> float:
    """z-score of the mean of paired differences ``d`` (n,). With ``clusters`` (n,) labels
    (the direction cell of each pose cell: its time blocks share their errors), the standard
    error is the cluster-robust one, from the clusters' sums about the mean."""
    n = len(d)
    mean = float(np.mean(d))
    if clusters is None:
        se = float(np.std(d, ddof=1)) / np.sqrt(n)
    else:
        _, inv = np.unique(clusters, return_inverse=True)
        sums = np.bincount(inv, weights=d - mean)
        k = len(sums)
        se = float(np.sqrt(np.sum(sums**2) * k / max(k - 1, 1))) / n
    return mean / se if se > 0 else 0.0


def change_record(c: Comparison, change: str, from_model: str, to_model: str) -> dict:
    """The ``model_change`` of a published switch, oriented along the change: held-out RMS
    (mg) of the model before and of the model after, whichever of the two is larger."""
    before, after = ((c.heldout_rms_small_mg, c.heldout_rms_large_mg) if change == "added"
                     else (c.heldout_rms_large_mg, c.heldout_rms_small_mg))

    return {"change": change, "effect": c.effect, "from_model": from_model, "to_model": to_model,
            "heldout_rms_mg_before": rounded(before, 4), "heldout_rms_mg_after": rounded(after, 4),
            "heldout_z_larger_model": rounded(c.heldout_z, 3), "n_heldout_cells": c.n_heldout,
            "wald_chi2": round(c.wald_chi2, 3), "wald_dof": c.wald_dof}


def wald_significant(cfg: SelectionConfig):
    """``(chi2, dof) -> bool``: the effect terms are significant at ``cfg.alpha``."""
    return lambda chi2, dof: chi2 > float(chdtri(dof, cfg.alpha))


def wald_far_below(cfg: SelectionConfig):
    """``(chi2, dof) -> bool``: a one-step chi2 below ``screen_ratio`` of the threshold at
    ``cfg.alpha``; None (no screen, nothing computed) when ``screen_ratio`` is 0."""
    if cfg.screen_ratio <= 0:
        return None
    return lambda chi2, dof: chi2 < cfg.screen_ratio * float(chdtri(dof, cfg.alpha))


def wald_not_significant_to_keep(cfg: SelectionConfig):
    """``(chi2, dof) -> bool``: the effect terms are no longer significant at ``cfg.drop_alpha``."""
    return lambda chi2, dof: chi2 <= float(chdtri(max(dof, 1), cfg.drop_alpha))


def supports(c: Comparison, cfg: SelectionConfig) -> bool:
    """Does the comparison support switching the effect in?"""
    return (c.large_fit is not None and c.large_fit.success and np.isfinite(c.heldout_z)
            and c.heldout_z >= cfg.min_heldout_z and c.gain_rel >= cfg.min_gain_rel
            and wald_significant(cfg)(c.wald_chi2, c.wald_dof))


def stops_paying(c: Comparison, cfg: SelectionConfig) -> bool:
    """Does the comparison say a switched-in effect no longer pays (drop it)?"""
    return (bool(np.isfinite(c.heldout_z)) and c.heldout_z < cfg.drop_z
            and wald_not_significant_to_keep(cfg)(c.wald_chi2, c.wald_dof))
