"""Fitting: initial values, observability-aware Levenberg-Marquardt, uncertainty, guard.

The problem (method.md §1): find the parameters ``theta`` of an error model so that
calibrated still poses have unit norm. selfcal solves the *maximum a posteriori*
version of it:

    cost(theta) = 1/2 sum_k (r_k(theta) / sigma_k)^2 + 1/2 (theta - mu)^T Lambda (theta - mu)

with ``r_k = ||a_k|| - 1`` (g), ``sigma_k`` the standard deviation of that residual for
pose ``k`` (from the pose's own noise and sample count, plus a floor for what the
model does not explain), and a Gaussian prior ``N(mu, Lambda^-1)``: the previous model
and its covariance in the online calibrator, the datasheet tolerances before the first
fit. Directions of parameter space that the poses do not determine (most of them for
an insole that is flat most of the time) are held by the prior instead of wandering
with the noise, and are reported as undetermined.

All fitting happens on normalised data ``u = (raw - center)/scale`` (see
:class:`selfcal.models.Normalizer`), so the parameters are O(1) in every unit; results
are converted back to the recording's unit at the end.

Levenberg-Marquardt (``lm_solve``)
----------------------------------
Marquardt-scaled damping ``(A + lambda diag(A)) delta = -g``, step acceptance by the
gain ratio ``rho = actual / predicted`` reduction (Nielsen's lambda update; a step that
raises the cost is rejected and lambda multiplied by a growing factor). Lambda starts
at ``lambda0`` (1e-7: nearly Gauss-Newton) when the start already fits (reduced chi²
below ``chi2_restart``: a warm refit), else at ``lambda0_far`` (1e-3). It stops when
(1) the predicted decrease falls below ``max(ftol * cost, ftol_chi2)``, checked before
the step is tried (whether so small a step lowers the cost is decided by rounding) (a decrease of
1e-6 in chi² moves the parameters by ~1e-3 of their sd: nothing the data can tell), (2) the step is below
``xtol * (||theta|| + xtol)``, (3) the scaled gradient ``max |g_j| / sqrt(A_jj)`` is
below ``gtol``, or (4) after ``max_iter`` iterations (``status = 0``, not converged).
"""

from __future__ import annotations

import functools
import time
from dataclasses import dataclass, field
from typing import Any

import numpy as np
from pydantic import BaseModel, ConfigDict, Field

from selfcal.errors import InputError
from selfcal.groupsum import sum_by_group
from selfcal.models import ErrorModel, Normalizer

# --------------------------------------------------------------------------- config


class FitConfig(BaseModel):
    """The ``[fit]`` section: LM tolerances, noise model and the datasheet prior."""

    model_config = ConfigDict(extra="forbid")

    max_iter: int = Field(100, ge=1, description="LM iteration limit")
    ftol: float = Field(1e-12, gt=0, description="stop: relative predicted cost decrease")
    xtol: float = Field(1e-10, gt=0, description="stop: relative step size")
    gtol: float = Field(1e-10, gt=0, description="stop: scaled gradient")
    lambda0: float = Field(
        1e-7, gt=0,
        description="LM: initial damping relative to diag(A) when the start already fits (reduced chi2 below "
                    "chi2_restart, a warm start): nearly a Gauss-Newton step first",
    )
    lambda0_far: float = Field(
        1e-3, gt=0,
        description="LM: initial damping from a start that does not fit yet (a random or nominal value): "
                    "short steps, so that the fit stays in the basin it starts in",
    )
    ftol_chi2: float = Field(
        1e-6, ge=0,
        description="stop: predicted cost decrease below this, in chi2 units (a change the data cannot tell)",
    )
    sigma_floor_g: float = Field(
        3e-4, ge=0, description="floor added (in quadrature) to every pose's residual sd, g"
    )
    default_sample_sd_g: float = Field(
        3e-3, gt=0, description="per-axis sample sd assumed when a pose has no sd, g"
    )
    # datasheet prior (1 sigma), in g-normalised units
    prior_bias_g: float = Field(0.1, gt=0, description="prior sd of the offsets, g")
    prior_scale_rel: float = Field(0.05, gt=0, description="prior sd of the scales, relative")
    prior_nonorth_rad: float = Field(0.02, gt=0, description="prior sd of nxy, nxz, nyz, rad")
    prior_seed_angle_rad: float = Field(0.02, gt=0, description="prior sd of seed9 angles, rad")
    # effect priors: consumer-MEMS datasheets (ADXL345, LIS3DH, BMA4xx) list offset tempco
    # ~0.5-1 mg/degC, sensitivity tempco 0.01-0.02 %/degC, nonlinearity <= 0.5 % FS
    prior_temp_bias_g_per_c: float = Field(1e-3, gt=0, description="prior sd of the offset tempco, g/degC")
    prior_temp_scale_per_c: float = Field(3e-4, gt=0, description="prior sd of the sensitivity tempco, 1/degC")
    prior_drift_g_per_day: float = Field(2e-3, gt=0, description="prior sd of the offset drift, g/day")
    prior_nonlin_per_g: float = Field(0.003, gt=0, description="prior sd of the quadratic nonlinearity q, 1/g")
    prior_bias_step_g: float = Field(0.02, gt=0, description="prior sd of a bias step (bias_step event), g")
    prior_temp_cross_per_c: float = Field(
        1e-4, gt=0, description="prior sd of the cross-axis tempco tn, 1/degC (100 ppm/degC: 2 mrad over 20 degC)")
    determined_ratio: float = Field(
        0.3, gt=0, lt=1,
        description="a parameter is determined when the data shrink its prior sd to this fraction (>= 91 % of its information from data)",
    )
    axis_tol_g: float = Field(
        0.12, gt=0, description="axis-aligned pose: one axis within this of +-1 g, others within it of 0"
    )
    chi2_restart: float = Field(
        9.0, gt=0, description="reduced chi2 above which LM is restarted from the other initial values"
    )
    robust_c: float = Field(
        3.0, gt=0,
        description="Huber threshold on whitened residuals (|r/sigma| beyond it weighs linearly), for robust fits",
    )
    reject_z: float = Field(
        12.0, gt=0,
        description="robust fits: |r/sigma| beyond this carries no information (covariance and chi2 exclude it)",
    )
    irls_max: int = Field(6, ge=1, description="robust fits: reweighting passes at most")
    curvature_cov: bool = Field(
        True,
        description="add to the linearised covariance the spread that the model's curvature gives along the "
                    "directions the poses leave loose (a few poses from one hemisphere: the fit's valley bends)",
    )

    @classmethod
    def from_section(cls, section: dict[str, Any] | None) -> "FitConfig":
        """Validate the ``[fit]`` TOML section."""
        return cls(**(section or {}))


class GuardConfig(BaseModel):
    """The ``[guard]`` section: when a new model may replace the current one."""

    model_config = ConfigDict(extra="forbid")

    min_heldout: int = Field(3, ge=1, description="fewer unseen held-out cells: no held-out comparison")
    tolerance_rel: float = Field(0.05, ge=0, description="allowed relative held-out RMS increase")
    tolerance_mg: float = Field(0.05, ge=0, description="allowed absolute held-out RMS increase, mg")
    min_poses: int = Field(6, ge=1, description="fewer poses: insufficient_coverage")
    min_determined: int = Field(
        1, ge=1, description="fewer determined parameter directions: insufficient_coverage"
    )
    max_bias_g: float = Field(0.5, gt=0, description="plausible |offset|, g")
    max_scale_dev: float = Field(0.25, gt=0, description="plausible |scale - 1| (normalised)")
    max_nonorth_rad: float = Field(0.1, gt=0, description="plausible |nxy|, |nxz|, |nyz|, rad")
    max_temp_bias_g_per_c: float = Field(0.01, gt=0, description="plausible |temperature bias|, g/degC")
    max_temp_scale_per_c: float = Field(0.005, gt=0, description="plausible |temperature scale|, 1/degC")
    max_drift_g_per_day: float = Field(0.05, gt=0, description="plausible |bias drift|, g/day")
    max_nonlin_per_g: float = Field(0.1, gt=0, description="plausible |scale nonlinearity q|, 1/g")
    max_temp_cross_per_c: float = Field(0.002, gt=0, description="plausible |cross-axis tempco tn|, 1/degC")
    max_bias_step_g: float = Field(0.2, gt=0, description="plausible |bias step| (bias_step event), g")
    max_residual_rms_mg: float = Field(30.0, gt=0, description="fit residual RMS above this: implausible")

    @classmethod
    def from_section(cls, section: dict[str, Any] | None) -> "GuardConfig":
        """Validate the ``[guard]`` TOML section."""
        return cls(**(section or {}))


# --------------------------------------------------------------------------- data


@dataclass
class PoseData:
    """Still poses to fit.

    Attributes
    ----------
    mean : ndarray, shape (n, 3), raw unit — mean specific force of each window
    sd : ndarray, shape (n, 3), raw unit, or None — per-axis sample sd in the window
    count : ndarray, shape (n,) — samples in each window (1 if unknown)
    t_s : ndarray, shape (n,), s — time of each window (centre)
    temp_c : ndarray, shape (n,), degC, or None
    """

    mean: np.ndarray
    sd: np.ndarray | None = None
    count: np.ndarray | None = None
    t_s: np.ndarray | None = None
    temp_c: np.ndarray | None = None

    def __post_init__(self) -> None:
        self.mean = np.asarray(self.mean, dtype=float)
        if self.mean.ndim != 2 or self.mean.shape[1] != 3:
            raise InputError(f"poses: mean must have shape (n, 3), got {self.mean.shape}")
        n = self.mean.shape[0]
        if n == 0:
            raise InputError("poses: no still pose")
        bad = ~np.all(np.isfinite(self.mean), axis=1)
        if bad.any():
            raise InputError(f"poses: mean has NaN/inf in rows {np.flatnonzero(bad)[:10].tolist()}")
        if self.sd is not None:
            self.sd = np.asarray(self.sd, dtype=float).reshape(n, 3)
            if not np.all(np.isfinite(self.sd)) or np.any(self.sd < 0):
                raise InputError("poses: sd must be finite and >= 0")
        self.count = np.ones(n) if self.count is None else np.asarray(self.count, dtype=float).reshape(n)
        if np.any(~np.isfinite(self.count)) or np.any(self.count < 1):
            raise InputError("poses: count must be >= 1")
        self.t_s = np.zeros(n) if self.t_s is None else np.asarray(self.t_s, dtype=float).reshape(n)
        if self.temp_c is not None:
            self.temp_c = np.asarray(self.temp_c, dtype=float).reshape(n)
            if not np.all(np.isfinite(self.temp_c)):
                self.temp_c = None if np.all(~np.isfinite(self.temp_c)) else self.temp_c

    def __len__(self) -> int:
        return self.mean.shape[0]

    def subset(self, idx: np.ndarray) -> "PoseData":
        """The poses at ``idx`` (bool mask or integer indices)."""
        return PoseData(
            self.mean[idx],
            None if self.sd is None else self.sd[idx],
            self.count[idx],
            self.t_s[idx],
            None if self.temp_c is None else self.temp_c[idx],
        )


@dataclass
class Prior:
    """Gaussian prior on normalised parameters: ``N(mean, cov)``, shapes (p,), (p, p)."""

    mean: np.ndarray
    cov: np.ndarray
    _precision: np.ndarray | None = field(default=None, repr=False, compare=False)

    def precision(self) -> np.ndarray:
        """Inverse covariance (p, p), computed once."""
        if self._precision is None:
            self._precision = np.linalg.inv(self.cov)
        return self._precision

    def to_json(self) -> dict:
        return {"mean": self.mean.tolist(), "cov": self.cov.tolist()}

    @classmethod
    def from_json(cls, d: dict) -> "Prior":
        return cls(np.asarray(d["mean"], dtype=float), np.asarray(d["cov"], dtype=float))


def datasheet_prior(model: ErrorModel, cfg: FitConfig | None = None, inflate: float = 1.0) -> Prior:
    """Prior from consumer-MEMS datasheet tolerances around the nominal model.

    ``inflate`` multiplies every sd (use a large value for an essentially flat prior).
    """
    cfg = cfg or FitConfig()
    sd = np.empty(model.n_params)
    sd[0:3] = cfg.prior_bias_g
    sd[3:6] = cfg.prior_scale_rel
    if model.base == "affine9":
        sd[6:9] = cfg.prior_nonorth_rad
    elif model.base == "seed9":
        sd[6:9] = cfg.prior_seed_angle_rad
    per_effect = {
        "temperature_bias": cfg.prior_temp_bias_g_per_c,
        "temperature_scale": cfg.prior_temp_scale_per_c,
        "time_drift_bias": cfg.prior_drift_g_per_day,
        "scale_nonlinearity": cfg.prior_nonlin_per_g,
        "temperature_cross": cfg.prior_temp_cross_per_c,
        "bias_step": cfg.prior_bias_step_g,
    }
    for eff in model.effects:
        sd[model.index(eff)] = per_effect[eff]
    sd = sd * inflate
    return Prior(model.nominal(), np.diag(sd**2))


# --------------------------------------------------------------------------- noise


def pose_sigma(mean_u: np.ndarray, sd_u: np.ndarray | None, count: np.ndarray, cfg: FitConfig) -> np.ndarray:
    """Standard deviation (g) of each pose's norm residual at unit scales, shape (n,).

    The noise of the pose mean projected on the gravity direction,
    ``sqrt(sum_i g_i^2 (sd_i^2 / count + floor^2))``: :class:`NoiseModel` at ``s = 1``.
    """
    return NoiseModel.from_poses(mean_u, sd_u, count, cfg)(np.ones(6))[0]


@dataclass
class NoiseModel:
    """Residual sd of each pose as a function of the model's scales.

    The noise of a pose mean (per-axis variance ``sd^2 / count + floor^2``, raw units)
    reaches the calibrated norm through the model: ``sigma_k(s)^2 = sum_j (s_j g_j)^2
    var_kj`` (``g`` the pose's gravity direction). Holding sigma fixed instead would let
    a fit lower its cost by shrinking the scales (the errors-in-variables bias): on an
    insole's cap of orientations that bias reached 100 mg over the sphere with 26 000
    simulated poses. With sigma following the scales, shrinking buys nothing and the
    estimate is the maximum-likelihood one.

    Attributes
    ----------
    var_axis : ndarray, shape (n, 3) — ``g_j^2 sd_j^2 / count``, normalised units squared
    floor2 : float — ``sigma_floor_g^2``
    """

    var_axis: np.ndarray
    floor2: float
    nonlin: tuple | None = None  # (model, raw_u, temp_c, t_s) when the model has scale_nonlinearity

    @classmethod
    def from_poses(cls, mean_u, sd_u, count, cfg: "FitConfig", model: "ErrorModel | None" = None,
                   temp_c=None, t_s=None) -> "NoiseModel":
        norm = np.linalg.norm(mean_u, axis=1, keepdims=True)
        ghat = mean_u / np.where(norm > 0, norm, 1.0)
        if sd_u is None:
            sd_u = np.full_like(mean_u, cfg.default_sample_sd_g)
        # the floor is unexplained error of the measurement: in the raw domain, like noise,
        # so that it too follows the scales (a fixed floor leaves a shrink incentive)
        var = sd_u**2 / np.asarray(count, dtype=float)[:, None] + cfg.sigma_floor_g**2
        nonlin = None
        if model is not None and "scale_nonlinearity" in model.effects:
            nonlin = (model, np.asarray(mean_u, dtype=float), temp_c, t_s)
        return cls(ghat**2 * var, 0.0, nonlin)

    def scaled(self, weights: np.ndarray) -> "NoiseModel":
        """The same model with each pose's variance divided by ``weights`` (n,)."""
        return NoiseModel(self.var_axis / weights[:, None], self.floor2, self.nonlin)

    def __call__(self, theta: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """``(sigma (n,), d sigma / d theta (n, p))`` at parameters ``theta`` (scales at 3:6).

        The gain from raw noise to the calibrated norm along gravity is ``s_j`` per axis;
        with ``scale_nonlinearity`` it is ``s_j (1 - 2 q_j l_j)`` (``l`` the linear
        calibrated value): without that factor, the ``bz``-``sz``-``qz`` direction that
        norms cannot see on an insole would buy a lower cost by inflating every sigma.
        """
        theta = np.asarray(theta, dtype=float)
        s = theta[3:6]
        sigma, gain, lin = self._sigma_gain(theta)
        dsig = np.zeros((self.var_axis.shape[0], theta.shape[0]))
        if gain is None:
            dsig[:, 3:6] = self.var_axis * s / sigma[:, None]
            return sigma, dsig
        model = self.nonlin[0]
        sl = model.index("scale_nonlinearity")
        q = theta[sl]
        dsig[:, 3:6] = self.var_axis * gain * (1.0 - 4.0 * q * lin) / sigma[:, None]
        dsig[:, sl] = self.var_axis * gain * (-2.0 * s * lin) / sigma[:, None]
        return sigma, dsig

    def whitened(self, model: "ErrorModel", theta: np.ndarray, raw_u: np.ndarray, temp_c=None, t_s=None,
                 accelerate=None) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
        """``(r (n,), jac (n, p), r / sigma (n,), d(r / sigma) / d theta (n, p))`` of ``model``
        at ``theta`` on the poses ``raw_u`` (n, 3) (normalised units), sigma following the
        scales: ``d(r/sigma) = dr/sigma - r dsigma/sigma^2``.

        ``accelerate``: None uses the whitening kernel of :mod:`selfcal.model_numba` where
        it applies (scale6, affine9; a noise without ``scale_nonlinearity``) and is
        loaded: the same values bit for bit, in one call instead of ~15 array operations;
        False the numpy code; or a kernel to use.
        """
        theta = np.asarray(theta, dtype=float)
        if accelerate is not False and self.nonlin is None and model.base != "seed9":
            if accelerate is None:
                from selfcal.model_numba import whitening_kernel

                accelerate = whitening_kernel(len(self.var_axis))
            if accelerate is not None:
                return model._whitened_kernel(accelerate, theta, raw_u, temp_c, t_s, self.var_axis, self.floor2)
        r, j = model.residual_jac(theta, raw_u, temp_c, t_s, accelerate=None if accelerate is None else False)
        sig, dsig = self(theta)
        rw = r / sig
        jw = j / sig[:, None]
        jw -= (rw / sig)[:, None] * dsig
        return r, j, rw, jw

    def sigma(self, theta: np.ndarray) -> np.ndarray:
        """``sigma (n,)`` (g) alone at ``theta``: the first of :meth:`__call__`'s results,
        the same values, without building the (n, p) derivative (the fit's cost, its
        reweighting and its covariance need only sigma)."""
        return self._sigma_gain(np.asarray(theta, dtype=float))[0]

    def _sigma_gain(self, theta: np.ndarray) -> tuple[np.ndarray, np.ndarray | None, np.ndarray | None]:
        """``(sigma (n,), gain (n, 3), lin (n, 3))``; gain and lin are None without
        ``scale_nonlinearity`` (the gain is then the scales)."""
        s = theta[3:6]
        if self.nonlin is None:
            # ((v0 s0² + v1 s1²) + v2 s2²) + floor2, written out in the whitening kernel's
            # order (a matrix-vector product rounds its own way)
            va, ss = self.var_axis, s * s
            return np.sqrt(va[:, 0] * ss[0] + va[:, 1] * ss[1] + va[:, 2] * ss[2] + self.floor2), None, None
        model, raw_u, temp, t_s = self.nonlin
        q = theta[model.index("scale_nonlinearity")]
        lin = model._forward(theta, raw_u, temp, t_s)[1][2]
        gain = s * (1.0 - 2.0 * q * lin)
        return np.sqrt(np.sum(self.var_axis * gain * gain, axis=1) + self.floor2), gain, lin


# --------------------------------------------------------------------------- LM


@dataclass
class LMResult:
    """Outcome of :func:`lm_solve` (normalised units)."""

    x: np.ndarray
    cost: float
    fun: np.ndarray  # residuals, g
    jac: np.ndarray  # (n, p)
    n_iter: int
    nfev: int
    status: int
    message: str

    @property
    def success(self) -> bool:
        return self.status > 0


TERMINATION_MESSAGES = {
    0: "the maximum number of iterations was reached",
    1: "the predicted cost decrease is below ftol (relative) or ftol_chi2 (absolute)",
    2: "the relative step is below xtol",
    3: "the scaled gradient is below gtol",
    -1: "the cost is not finite at the initial value",
}


def lm_solve(
    model: ErrorModel,
    theta0: np.ndarray,
    raw_u: np.ndarray,
    sigma: np.ndarray,
    prior: Prior | None,
    temp_c: np.ndarray | None = None,
    t_s: np.ndarray | None = None,
    cfg: FitConfig | None = None,
) -> LMResult:
    """Levenberg-Marquardt on the weighted norm residuals plus a Gaussian prior.

    Parameters
    ----------
    model : ErrorModel
    theta0 : ndarray, shape (p,) — initial value (normalised units)
    raw_u : ndarray, shape (n, 3) — normalised pose means (~g)
    sigma : ndarray, shape (n,), g, or NoiseModel — residual sd of each pose (a
        NoiseModel makes it follow the model's scales: maximum likelihood)
    prior : Prior or None — None means no prior (maximum likelihood)
    temp_c, t_s : ndarray, shape (n,) — covariates of the effects, if any
    cfg : FitConfig
    """
    cfg = cfg or FitConfig()
    noise = sigma if isinstance(sigma, NoiseModel) else None
    winv = None if noise is not None else 1.0 / sigma
    p = model.n_params
    if prior is not None:
        lam_p = prior.precision()
        mu = prior.mean
    else:
        lam_p = np.zeros((p, p))
        mu = np.zeros(p)

    def evaluate(theta):
        if noise is None:
            r, j = model.residual_jac(theta, raw_u, temp_c, t_s)
            rw = r * winv
            jw = j * winv[:, None]
        else:  # sigma follows the scales: d(r/sigma) = dr/sigma - r dsigma/sigma^2
            r, j, rw, jw = noise.whitened(model, theta, raw_u, temp_c, t_s)
        d = theta - mu
        cost = 0.5 * (rw @ rw + d @ lam_p @ d)
        return r, j, rw, jw, d, cost

    theta = np.asarray(theta0, dtype=float).copy()
    r, j, rw, jw, d, cost = evaluate(theta)
    nfev = 1
    if not np.isfinite(cost):
        return LMResult(theta, float(cost), r, j, 0, nfev, -1, TERMINATION_MESSAGES[-1])
    a = jw.T @ jw + lam_p
    g = jw.T @ rw + lam_p @ d
    diag = np.maximum(np.diag(a), 1e-12 * max(np.max(np.diag(a)), 1e-300))
    # near a solution the Gauss-Newton step is right and damping only slows it (a warm
    # refit took ~9 evaluations at 1e-3, ~3 now); far from one, damped steps keep the fit
    # out of degenerate minima (the insole paper's random initial values)
    near = 2.0 * cost / max(len(rw), 1) < cfg.chi2_restart
    lam = cfg.lambda0 if near else cfg.lambda0_far
    nu = 2.0
    status = 0
    it = 0
    for it in range(1, cfg.max_iter + 1):
        if np.max(np.abs(g) / np.sqrt(diag)) < cfg.gtol:
            status = 3
            break
        try:
            step = -np.linalg.solve(a + lam * np.diag(diag), g)
        except np.linalg.LinAlgError:
            lam *= nu
            nu *= 2.0
            continue
        pred = -(g @ step + 0.5 * step @ a @ step)
        if 0 < pred <= max(cfg.ftol * cost, cfg.ftol_chi2):
            # converged: the best step predicts a decrease the data cannot tell. Stop here,
            # not after trying it: whether a step that small lowers the cost is decided by
            # rounding, and two runs that differ only there would stop a step apart
            status = 1
            break
        theta_new = theta + step
        r_n, j_n, rw_n, jw_n, d_n, cost_n = evaluate(theta_new)
        nfev += 1
        actual = cost - cost_n
        rho = actual / pred if pred > 0 else -1.0
        if np.isfinite(cost_n) and rho > 0:
            # |x| as np.linalg.norm makes it for a vector (sqrt(x . x)), without its dispatch
            small_step = np.sqrt(step @ step) <= cfg.xtol * (np.sqrt(theta @ theta) + cfg.xtol)
            small_dec = pred <= max(cfg.ftol * cost, cfg.ftol_chi2)
            theta, r, j, rw, jw, d, cost = theta_new, r_n, j_n, rw_n, jw_n, d_n, cost_n
            a = jw.T @ jw + lam_p
            g = jw.T @ rw + lam_p @ d
            diag = np.maximum(diag, np.diag(a))  # More's scaling: non-decreasing
            lam *= max(1.0 / 3.0, 1.0 - (2.0 * rho - 1.0) ** 3)
            nu = 2.0
            if small_dec:
                status = 1
                break
            if small_step:
                status = 2
                break
        else:
            if pred <= max(cfg.ftol * cost, cfg.ftol_chi2):
                status = 1
                break
            lam *= nu
            nu *= 2.0
    return LMResult(theta, float(cost), r, j, it, nfev, status, TERMINATION_MESSAGES[status])


# --------------------------------------------------------------------------- initial values


def axis_aligned_mask(mean_u: np.ndarray, tol_g: float) -> np.ndarray:
    """Poses with one axis near +-1 g and the other two near 0 (the paper's O_cor), (n,) bool."""
    absu = np.abs(mean_u)
    k = np.argmax(absu, axis=1)
    rows = np.arange(len(mean_u))
    big = absu[rows, k]
    off = absu.copy()
    off[rows, k] = 0.0
    return (np.abs(big - 1.0) < tol_g) & (off.max(axis=1) < tol_g)


def ls_axis_aligned(model: ErrorModel, mean_u: np.ndarray, mask: np.ndarray, ridge: float = 1e-3) -> np.ndarray | None:
    """The insole paper's linear least-squares initial value from axis-aligned poses.

    With the gravity direction of each axis-aligned pose known (the sign of its big
    axis), ``g_k = M u_k - c`` is linear in ``(M, c)``; rows of ``M`` are solved one
    axis at a time with a small ridge toward the nominal model, so that rows the poses
    do not determine stay nominal. Returns normalised parameters (p,) or None.
    """
    if mask.sum() < 1:
        return None
    u = mean_u[mask]
    k = np.argmax(np.abs(u), axis=1)
    gdir = np.zeros_like(u)
    gdir[np.arange(len(u)), k] = np.sign(u[np.arange(len(u)), k])
    design = np.hstack([u, -np.ones((len(u), 1))])  # unknowns: M_i0, M_i1, M_i2, c_i
    lhs = design.T @ design + ridge * np.eye(4)
    nominal = np.vstack([np.eye(3), np.zeros((1, 3))])  # columns: row i of M = e_i, c_i = 0
    sol = np.linalg.solve(lhs, design.T @ gdir + ridge * nominal)  # (4, 3): one column per axis
    m = sol[:3].T
    c = sol[3]
    try:
        offset = np.linalg.solve(m, c)
    except np.linalg.LinAlgError:
        return None
    if not np.all(np.isfinite(offset)) or np.linalg.det(m) <= 0:
        return None
    return model.from_linear(m, offset)


def quadric_fit(model: ErrorModel, mean_u: np.ndarray, min_rel_sv: float = 1e-4) -> np.ndarray | None:
    """General quadric (ellipsoid) fit: a linear initial value needing no start point.

    Solves ``[x², y², z², 2xy, 2xz, 2yz, 2x, 2y, 2z] v = 1`` by least squares; the
    centre is the offset and a Cholesky factor of the normalised quadric form the
    matrix. Returns None when the poses do not determine the quadric (flat-heavy sets:
    relative singular value below ``min_rel_sv``) or the fit is not an ellipsoid.
    """
    if len(mean_u) < 9:
        return None
    x, y, z = mean_u.T
    design = np.column_stack([x * x, y * y, z * z, 2 * x * y, 2 * x * z, 2 * y * z, 2 * x, 2 * y, 2 * z])
    try:
        v, _, rank, sv = np.linalg.lstsq(design, np.ones(len(x)), rcond=None)
    except np.linalg.LinAlgError:
        return None
    if rank < 9 or sv[-1] < min_rel_sv * sv[0]:
        return None
    a = np.array([[v[0], v[3], v[4]], [v[3], v[1], v[5]], [v[4], v[5], v[2]]])
    b = v[6:9]
    try:
        center = -np.linalg.solve(a, b)
    except np.linalg.LinAlgError:
        return None
    k = 1.0 + center @ a @ center
    if k <= 0:
        return None
    try:
        low = np.linalg.cholesky(a / k)
    except np.linalg.LinAlgError:
        return None
    return model.from_linear(low.T, center)


# --------------------------------------------------------------------------- result


@dataclass
class FitResult:
    """Everything a fit knows, in the recording's unit and in normalised units.

    ``params``/``cov``/``std`` are in the recording's unit (offsets in raw units,
    scales in g per raw unit); ``*_u`` are the normalised values the fit worked with.
    """

    model: ErrorModel
    normalizer: Normalizer
    params: np.ndarray
    cov: np.ndarray
    std: np.ndarray
    theta_u: np.ndarray
    cov_u: np.ndarray
    crlb_std: np.ndarray  # raw unit; inf where the poses carry no information
    determined: np.ndarray  # (p,) bool
    shrink_ratio: np.ndarray  # posterior sd / prior sd, (p,)
    n_determined_directions: int
    undetermined_directions: list[dict[str, float]]
    residuals_g: np.ndarray
    sigma_g: np.ndarray
    residual_rms_mg: float
    chi2_red: float
    n_poses: int
    n_iter: int
    nfev: int
    status: int
    message: str
    initial_value: str
    fit_ms: float
    extra: dict = field(default_factory=dict)
    #: the poses fitted, normalised units: ``(raw_u (n, 3), temp_c (n,) or None, t_s (n,) or None)``
    cells_u: tuple | None = None
    #: the poses fitted as given (recording unit), so that another model can be fitted to them
    poses: PoseData | None = None

    @property
    def success(self) -> bool:
        return self.status > 0

    def linear(self) -> tuple[np.ndarray, np.ndarray]:
        """``(matrix (3,3), offset (3,) raw unit)`` with ``a_g = matrix @ (raw - offset)``."""
        return self.model.linear(self.params)

    def apply(self, raw: np.ndarray, temp_c=None, t_s=None) -> np.ndarray:
        """Calibrate raw readings (n,3) raw unit -> (n,3) g."""
        return self.model.apply(self.theta_u, self.normalizer.to_u(raw), temp_c, t_s)

    def to_calibration(self, unit: str = "g") -> dict:
        """The calibration JSON of the design contract."""
        matrix, offset = self.linear()
        names = self.model.param_names
        return {
            "format": "selfcal-calibration",
            "format_version": 1,
            "model": self.model.name,
            "unit": unit,
            "params": self.model.to_dict(self.params),
            "std": {n: float(s) for n, s in zip(names, self.std)},
            "crlb_std": {n: (float(s) if np.isfinite(s) else None) for n, s in zip(names, self.crlb_std)},
            "determined": [n for n, d in zip(names, self.determined) if d],
            "undetermined": [n for n, d in zip(names, self.determined) if not d],
            "undetermined_directions": self.undetermined_directions,
            "n_poses": int(self.n_poses),
            "residual_rms_mg": float(self.residual_rms_mg),
            "chi2_red": float(self.chi2_red),
            "matrix": matrix.tolist(),
            "offset": offset.tolist(),
            "temp_ref_c": self.model.temp_ref_c,
            "t_ref_s": self.model.t_ref_s,
            "converged": bool(self.success),
            "fit": {
                "n_iter": self.n_iter,
                "nfev": self.nfev,
                "message": self.message,
                "initial_value": self.initial_value,
                "fit_ms": self.fit_ms,
            },
        }


def _direction_dicts(model: ErrorModel, vecs: np.ndarray) -> list[dict[str, float]]:
    out = []
    for v in vecs.T:
        order = np.argsort(-np.abs(v))[:3]
        sgn = np.sign(v[order[0]]) or 1.0
        out.append({model.param_names[i]: round(float(sgn * v[i]), 3) for i in order if abs(v[i]) > 0.05})
    return out


def observability(
    model: ErrorModel, jac_w: np.ndarray, prior: Prior, ratio: float, posterior_cov: np.ndarray | None = None
) -> tuple[np.ndarray, np.ndarray, int, list[dict[str, float]], np.ndarray]:
    """Which parameter directions the poses determine.

    Parameters
    ----------
    jac_w : ndarray, shape (n, p) — Jacobian of the whitened residuals ``r/sigma``
    prior : Prior
    ratio : float — determined when the posterior sd is below ``ratio`` x prior sd
    posterior_cov : (p, p), optional — ``inv(J^T J + prior precision)`` if already known

    Returns
    -------
    determined : (p,) bool, per parameter
    shrink : (p,) posterior sd / prior sd
    n_directions : number of prior-whitened eigen-directions the data determine
    undetermined : list of {param: weight} for the directions they do not
    eigvals : (p,) eigenvalues of the prior-whitened Fisher information, descending
    """
    fisher = jac_w.T @ jac_w
    low = np.linalg.cholesky(prior.cov)
    fw = low.T @ fisher @ low
    evals, evecs = np.linalg.eigh(fw)
    evals, evecs = evals[::-1], evecs[:, ::-1]
    threshold = 1.0 / ratio**2 - 1.0
    det_dir = evals >= threshold
    post = np.linalg.inv(fisher + prior.precision()) if posterior_cov is None else posterior_cov
    shrink = np.sqrt(np.diag(post) / np.diag(prior.cov))
    # undetermined directions, mapped back to parameter space (unit vectors)
    und = low @ evecs[:, ~det_dir]
    if und.size:
        und = und / np.linalg.norm(und, axis=0, keepdims=True)
    return shrink < ratio, shrink, int(det_dir.sum()), _direction_dicts(model, und), evals


def cramer_rao_std(jac: np.ndarray, sigma: np.ndarray, rcond: float = 1e-10) -> np.ndarray:
    """Cramér-Rao bound (sd) for a pose set with unknown orientations, shape (p,).

    Each pose carries one scalar of information: its norm along the calibrated gravity
    direction (the two orientation angles are nuisance parameters and take the rest).
    ``jac`` is the norm-residual Jacobian (n, p) at the true parameters and ``sigma``
    (n,) the residual sd (g). Parameters the poses do not determine get ``inf``.
    """
    jw = jac / sigma[:, None]
    fisher = jw.T @ jw
    evals, evecs = np.linalg.eigh(fisher)
    keep = evals > rcond * max(evals.max(), 1e-300)
    inv = (evecs[:, keep] / evals[keep]) @ evecs[:, keep].T
    var = np.diag(inv).copy()
    # a parameter with weight on a null direction is undetermined
    null_weight = np.sum(evecs[:, ~keep] ** 2, axis=1)
    var[null_weight > 1e-6] = np.inf
    return np.sqrt(var)


# --------------------------------------------------------------------------- front end


def guess_normalizer(unit: str, mean: np.ndarray | None = None) -> Normalizer:
    """Normaliser for a unit: exact for g and m/s², a sphere fit of ``mean`` for counts."""
    if unit == "g":
        return Normalizer()
    if unit == "mps2":
        from selfcal import STANDARD_GRAVITY_MPS2

        return Normalizer((0.0, 0.0, 0.0), STANDARD_GRAVITY_MPS2)
    if unit == "counts":
        if mean is None:
            raise InputError("counts: a sphere fit of still poses is needed to normalise raw counts")
        return sphere_normalizer(mean)
    raise InputError(f"unit: unknown acceleration unit {unit!r} (g, mps2, counts)")


def sphere_normalizer(mean: np.ndarray) -> Normalizer:
    """Centre and radius of the sphere through still-pose means (raw counts), by linear LS.

    Raises InputError when the poses do not determine a sphere (fewer than 4, or all in
    one plane/orientation).
    """
    mean = np.asarray(mean, dtype=float)
    if len(mean) < 4:
        raise InputError(
            f"counts: {len(mean)} still pose(s); at least 4 distinct orientations are needed "
            "to find the counts-per-g scale of a raw-counts recording"
        )
    ref = mean.mean(axis=0)
    spread = max(float(np.abs(mean - ref).max()), 1e-300)
    x = (mean - ref) / spread  # conditioned: O(1) columns
    design = np.hstack([2 * x, np.ones((len(x), 1))])
    rhs = np.einsum("ij,ij->i", x, x)
    sol, _, rank, sv = np.linalg.lstsq(design, rhs, rcond=None)
    if rank < 4 or sv[-1] < 1e-3 * sv[0]:
        raise InputError("counts: the still poses do not span enough orientations to fit a sphere")
    center_x = sol[:3]
    r2 = (sol[3] + center_x @ center_x) * spread**2
    center = ref + center_x * spread
    if r2 <= 0:
        raise InputError("counts: sphere fit failed (negative radius)")
    return Normalizer(tuple(float(c) for c in center), float(np.sqrt(r2)))


def fit_poses(
    model: ErrorModel | str,
    poses: PoseData,
    *,
    normalizer: Normalizer | None = None,
    prior: Prior | None = None,
    theta0_u: np.ndarray | None = None,
    cfg: FitConfig | None = None,
    robust: bool = False,
    clusters: np.ndarray | None = None,
) -> FitResult:
    """Fit an error model to still poses (MAP with a Gaussian prior).

    Parameters
    ----------
    model : ErrorModel or name
    poses : PoseData — in the recording's unit
    normalizer : Normalizer — raw -> ~g; default identity (poses already in g)
    prior : Prior on normalised parameters; default :func:`datasheet_prior`
    theta0_u : ndarray, shape (p,) — an initial value to consider (warm start or, as
        in the insole paper's test, a random one); the fit also considers the prior
        mean, the axis-aligned least-squares value and the quadric fit, and starts
        from whichever has the lowest cost.
    cfg : FitConfig
    robust : bool — Huber loss on the whitened residuals (threshold ``cfg.robust_c``),
        solved by iteratively reweighted LM; poses beyond ``cfg.reject_z`` carry no
        information in the covariance and the reduced chi² (``extra["weights"]``,
        ``extra["n_rejected"]``).
    clusters : ndarray, shape (n,), optional — a group label per pose (for example the
        direction cell, whatever the time). The covariance is then at least the
        cluster-robust sandwich ``A^-1 (sum_c S_c S_c^T + prior) A^-1`` (``S_c`` the
        summed score of a cluster): a systematic error shared by the poses of a cluster
        widens it, where the Fisher information alone would not see it.

    Returns
    -------
    FitResult
    """
    t0 = time.perf_counter()
    model = ErrorModel(model) if isinstance(model, str) else model
    cfg = cfg or FitConfig()
    normalizer = normalizer or Normalizer()
    prior = prior or datasheet_prior(model, cfg)
    if prior.mean.shape != (model.n_params,):
        raise InputError(f"prior: expected {model.n_params} parameters for {model.name}")
    raw_u = normalizer.to_u(poses.mean)
    sd_u = None if poses.sd is None else poses.sd / normalizer.scale
    noise = NoiseModel.from_poses(raw_u, sd_u, poses.count, cfg, model, poses.temp_c, poses.t_s)
    sigma = noise.sigma(prior.mean)
    temp = poses.temp_c
    if temp is None and any(e.startswith("temperature") for e in model.effects):
        raise InputError(f"model {model.name} needs temperatures (temp_c) for every pose")
    t_s = poses.t_s

    lam_p = prior.precision()

    def cost_of(theta):
        r = model.residuals(theta, raw_u, temp, t_s) / noise.sigma(theta)
        d = theta - prior.mean
        c = 0.5 * (r @ r + d @ lam_p @ d)
        return c if np.isfinite(c) else np.inf

    def good(res: LMResult) -> bool:
        return res.success and 2 * res.cost / max(len(raw_u), 1) < cfg.chi2_restart

    best: LMResult | None = None
    best_name = ""
    tried = 0
    if theta0_u is not None:  # warm start: the usual refit; other starts only if it fails
        best = lm_solve(model, np.asarray(theta0_u, dtype=float), raw_u, noise, prior, temp, t_s, cfg)
        best_name, tried = "given", 1
    if best is None or not good(best):
        # other initial values, built lazily in order of usual quality: the quadric (exact
        # on well-spread sets), the axis-aligned least squares (the insole paper's
        # correction), the prior mean; the first good LM result ends the search
        base = model.with_effects(())

        def quadric():
            q = quadric_fit(base, raw_u)
            return None if q is None else model.extend_theta(q, base)

        def least_squares():
            ls = ls_axis_aligned(base, raw_u, axis_aligned_mask(raw_u, cfg.axis_tol_g))
            return None if ls is None else model.extend_theta(ls, base)

        for name, build in (("quadric", quadric), ("least_squares_axis_aligned", least_squares),
                            ("prior", lambda: prior.mean.copy())):
            th = build()
            if th is None or not np.isfinite(cost_of(th)):
                continue
            res = lm_solve(model, th, raw_u, noise, prior, temp, t_s, cfg)
            tried += 1
            if best is None or not np.isfinite(best.cost) or res.cost < best.cost:
                best, best_name = res, name
            if good(best):
                break
    if best is None or not np.isfinite(best.cost):
        raise InputError("fit: every initial value gives a non-finite cost (check the data)")

    weights = np.ones(len(raw_u))
    scale = 1.0
    if robust:
        # Huber by iteratively reweighted LM (sigma_k / sqrt(w_k)); then the same with the
        # poses beyond reject_z skipped (weight ~0): a redescending end, so that a burst of
        # coherent outliers cannot pull the estimate by its bounded Huber influence. The
        # thresholds apply to the residuals in units of a robust scale of them (never below
        # the stated noise): poses that all scatter k times more than stated are not
        # outliers, and down-weighting them as such had shrunk the chi-square that widens
        # the covariance (a published sd k/c times too small). With few poses the scale is
        # the stated noise's: a fit with barely more poses than parameters bends to an
        # outlier, and the scale of its residuals then hid the outlier
        for skip in (False, True):
            for _ in range(cfg.irls_max):
                z = best.fun / noise.sigma(best.x)
                scale = robust_scale(z) if len(z) >= max(ROBUST_SCALE_MIN_POSES, 3 * model.n_params) else 1.0
                zs = z / scale
                w_new = np.minimum(1.0, cfg.robust_c / np.maximum(np.abs(zs), 1e-300))
                if skip:
                    w_new = np.where(np.abs(zs) > cfg.reject_z, 1e-12, w_new)
                if np.max(np.abs(w_new - weights)) < 1e-3:
                    break
                weights = w_new
                res = lm_solve(model, best.x, raw_u, noise.scaled(weights),
                               prior, temp, t_s, cfg)
                if res.success or not best.success:
                    best = res

    # uncertainty (sigma at the estimate)
    sigma = noise.sigma(best.x)
    z = best.fun / sigma
    inlier = np.abs(z) <= cfg.reject_z * scale if robust else np.ones(len(z), dtype=bool)
    info_w = np.where(inlier, weights, 0.0)
    jw = best.jac / sigma[:, None] * np.sqrt(info_w)[:, None]
    rw = z * np.sqrt(info_w)
    fisher = jw.T @ jw
    post0 = np.linalg.inv(fisher + lam_p)
    p_eff = float(np.trace(post0 @ fisher))
    dof = max(int(inlier.sum()) - p_eff, 1.0)
    chi2_red = float(rw @ rw / dof)
    infl = max(1.0, chi2_red)
    cov_u = np.linalg.inv(fisher / infl + lam_p)
    cov_u = 0.5 * (cov_u + cov_u.T)
    if clusters is not None and len(clusters) == len(rw):
        cov_u = _psd_max(cov_u, _cluster_sandwich(jw, rw, np.asarray(clusters), lam_p, post0))
    jw_infl = jw / np.sqrt(infl)
    if cfg.curvature_cov:
        scale_w = np.sqrt(info_w) / sigma / np.sqrt(infl)
        cov_u = cov_u + curvature_moment(
            lambda th: model.residual_jac(th, raw_u, temp, t_s)[1] * scale_w[:, None], best.x, cov_u,
            jac0=jw_infl)
    determined, shrink, n_dir, und, _ = observability(
        model, jw_infl, prior, cfg.determined_ratio, posterior_cov=cov_u)
    crlb_u = cramer_rao_std(best.jac, sigma * np.sqrt(infl))
    params = normalizer.theta_to_raw(model, best.x)
    cov = normalizer.cov_to_raw(model, cov_u)
    crlb = crlb_u * normalizer.param_scale(model)
    fit_ms = (time.perf_counter() - t0) * 1e3
    return FitResult(
        model=model,
        normalizer=normalizer,
        params=params,
        cov=cov,
        std=np.sqrt(np.maximum(np.diag(cov), 0.0)),
        theta_u=best.x,
        cov_u=cov_u,
        crlb_std=crlb,
        determined=determined,
        shrink_ratio=shrink,
        n_determined_directions=n_dir,
        undetermined_directions=und,
        residuals_g=best.fun,
        sigma_g=sigma,
        residual_rms_mg=float(np.sqrt(np.mean(best.fun**2)) * 1e3),
        chi2_red=chi2_red,
        n_poses=len(raw_u),
        n_iter=best.n_iter,
        nfev=best.nfev,
        status=best.status,
        message=best.message,
        initial_value=best_name,
        fit_ms=fit_ms,
        extra={"starts_tried": tried, "weights": weights, "n_rejected": int((~inlier).sum()), "robust_scale": scale},
        cells_u=(raw_u, temp, t_s),
        poses=poses,
    )


def curvature_moment(jac_w, theta_u: np.ndarray, cov_u: np.ndarray, step: float = 1.0,
                     rel_sd: float = 0.2, probe_tol: float = 1e-3, jac0: np.ndarray | None = None) -> np.ndarray:
    """Second moment (p, p) about the estimate that the model's curvature adds to ``cov_u``.

    The linearised covariance treats the cost's valley as straight. When the poses
    leave a direction loose (early wear: every pose from one hemisphere, so that an
    offset and a scale trade along ``s (1 - b) = const``) the valley bends, and moving
    along it by its own standard deviation ``s_i`` shifts the well-determined
    directions by many of theirs: the truth is then far outside the linear ellipsoid
    although the data fit it as well as the estimate.

    With ``u ~ N(0, I)`` along the eigen-directions ``d_i = s_i v_i`` of ``cov_u``, the
    valley's second-order shift is ``delta = 1/2 sum_ij u_i u_j delta_ij``,
    ``delta_ij = -cov_u J_w^T (d^2 r_w / du_i du_j)`` (the Gauss-Newton profile of the
    second-order residual change), and its second moment about the estimate is
    ``1/4 m m^T + 1/2 sum_ij delta_ij delta_ij^T``, ``m = sum_i delta_ii``. Second
    derivatives by central differences of the Jacobian at ``theta +- step d_i``, for
    the loose directions only (``s_i >= rel_sd * max s``): a term's size goes with
    ``s_i s_j``, so pairs of two tight directions add nothing one could see (on an
    insole's wear the covariance with 0.05 instead of 0.2 differs by at most 2.5 %).
    The loosest direction is probed first: when its moment's whitened trace
    ``tr(cov_u^-1 M)`` is below ``probe_tol`` (the valley is straight: poses from every
    side, or many), the others are not computed.

    Parameters
    ----------
    jac_w : callable
        ``theta_u (p,) -> (n, p)``: the residuals' Jacobian, whitened (rows divided
        by each pose's sigma, times the square root of its weight).
    theta_u : ndarray, shape (p,)
        The estimate (normalised units).
    cov_u : ndarray, shape (p, p)
        Its linearised covariance.
    jac0 : ndarray, shape (n, p), optional
        ``jac_w(theta_u)`` when the caller has it.

    Returns
    -------
    ndarray, shape (p, p), symmetric positive semi-definite (zeros for a linear model).
    """
    cov_u = np.asarray(cov_u, dtype=float)
    p = cov_u.shape[0]
    evals, evecs = np.linalg.eigh(cov_u)
    sd = np.sqrt(np.clip(evals, 0.0, None))
    d = evecs * sd  # columns d_i, one sd each
    loose = np.flatnonzero(sd >= rel_sd * sd.max()) if sd.max() > 0 else np.zeros(0, dtype=int)
    if loose.size == 0:
        return np.zeros((p, p))
    loose = loose[np.argsort(-sd[loose], kind="stable")]
    j0 = jac_w(theta_u) if jac0 is None else jac0
    g = -cov_u @ j0.T  # (p, n): the linear profile of a residual change
    inv_var = np.divide(1.0, evals, out=np.zeros_like(evals), where=evals > 0)

    def moment(k: int) -> np.ndarray:
        """The moment from the ``k`` loosest directions (their pairs with every direction)."""
        idx = loose[:k]
        delta = np.zeros((p, p, p))  # [i, j, k]: delta_ij
        delta[idx] = rr[:k].transpose(0, 2, 1) @ g.T  # [a, j, k] = sum_n g[k, n] rr[a, n, j]: a BLAS product
        # (einsum's loop over n took ~140 us a call at ~1 200 cells, 5 % of a replay)
        both = np.zeros(p, dtype=bool)
        both[idx] = True
        half = np.where(both[:, None] & both[None, :], 0.5, 1.0)  # computed from both ends: their mean
        delta = (delta + delta.transpose(1, 0, 2)) * half[:, :, None]
        m = np.einsum("iik->k", delta)
        flat = delta.reshape(p * p, p)
        out = 0.25 * np.outer(m, m) + 0.5 * flat.T @ flat
        return 0.5 * (out + out.T)

    # rr[a, :, j] = d^2 r_w / du_i du_j for i = loose[a], every j: (k, n, p)
    rr = np.empty((loose.size, j0.shape[0], p))
    for a, i in enumerate(loose.tolist()):
        h = step * d[:, i]
        rr[a] = (jac_w(theta_u + h) - jac_w(theta_u - h)) @ d / (2.0 * step)
        if a == 0 and loose.size > 1:
            # the loosest direction first: where its bend is invisible against the linear
            # covariance (whitened trace below probe_tol) the valley is straight enough
            first = moment(1)
            if float(np.einsum("ij,ij,j->", evecs, first @ evecs, inv_var)) < probe_tol:
                return first
    return moment(loose.size)


# --------------------------------------------------------------------------- noise scale


def _cluster_sandwich(jw: np.ndarray, rw: np.ndarray, clusters: np.ndarray, lam_p: np.ndarray,
                      a_inv: np.ndarray) -> np.ndarray:
    """Cluster-robust covariance ``A^-1 (sum_c S_c S_c^T + prior precision) A^-1`` (p, p)."""
    score = jw * rw[:, None]
    _, inv = np.unique(clusters, return_inverse=True)
    sums = sum_by_group(inv, score, int(inv.max()) + 1 if inv.size else 0)
    meat = sums.T @ sums + lam_p
    out = a_inv @ meat @ a_inv
    return 0.5 * (out + out.T)


#: Poses (and at least 3 per parameter) from which a robust fit measures the scale of its
#: residuals (below: the stated noise's).
ROBUST_SCALE_MIN_POSES = 30


def robust_scale(z: np.ndarray) -> float:
    """The spread of whitened residuals ``z`` (shape (n,)) in units of the stated noise,
    robust to outliers: ``1.4826 * median |z|`` (1 for standard normal residuals), never
    below 1 (the stated noise is a floor, not a guess to shrink)."""
    if len(z) == 0:
        return 1.0
    s = 1.4826 * _median_abs(z)
    return s if np.isfinite(s) and s > 1.0 else 1.0


def _median_abs(z: np.ndarray) -> float:
    """``float(np.median(np.abs(z)))`` of a 1-D ``z`` (n >= 1), the same value bit for bit:
    the same partition, and the mean of the two middle values as ``np.mean`` makes it
    (``(a + b) / 2``), NaN if any is; without ``np.median``'s general-axis machinery
    (3.2 against 8.7 us at 300 cells, measured; every robust fit asks it 2-4 times)."""
    a = np.abs(np.ravel(z))
    n = a.size
    h = n // 2
    part = np.partition(a, (h - 1, h, n - 1) if n % 2 == 0 else (h, n - 1))
    if np.isnan(part[-1]):  # NaNs sort last
        return float("nan")
    return float(part[h]) if n % 2 else float((part[h - 1] + part[h]) / 2.0)


def _psd_max(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """A covariance at least as large as ``a`` and ``b`` in every direction: ``a + (b - a)_+``."""
    evals, evecs = np.linalg.eigh(b - a)
    pos = np.clip(evals, 0.0, None)
    out = a + (evecs * pos) @ evecs.T
    return 0.5 * (out + out.T)



def variance_components(model: ErrorModel, fit: "FitResult", poses: PoseData, floor_g: float,
                        bounds: tuple[tuple[float, float], tuple[float, float]] = ((1.0, 400.0), (1.0, 10.0)),
                        min_poses: int = 30, reject_z: float | None = None) -> tuple[float, float]:
    """Scale factors ``(c_floor, c_noise)`` of a pose's residual variance ``floor^2 + var_k``.

    Method of moments on the fit's residuals: ``r_k^2 / (1 - h_k)`` (``h_k`` the
    leverage, so that poses the fit bends to do not look quiet; from the covariance before
    the fit widened it by its reduced chi-square, which had made every leverage that many
    times too large) is regressed on ``[floor^2, var_k]`` with weights ``1/sigma_k^4`` and
    coefficients within ``bounds`` (by default never below the model: conservative),
    solved as one box-constrained problem (clipping each coefficient of an unconstrained
    solution lost what it clipped: variance put on the noise term beyond its bound did
    not go to the floor).
    ``var_k`` is each pose's noise variance as given (``sd^2 / count`` along gravity),
    ``floor_g`` the shared floor the fit added. Poses beyond ``reject_z`` (the fit's
    ``FitConfig.reject_z``; its default when None) times the robust fit's scale of its
    residuals are left out.
    Returns ``(1, 1)`` with fewer than ``min_poses`` poses.
    """
    from scipy.optimize import lsq_linear

    n = len(poses)
    if n < min_poses:
        return 1.0, 1.0
    mean_u = fit.normalizer.to_u(poses.mean)
    norm = np.linalg.norm(mean_u, axis=1, keepdims=True)
    ghat = mean_u / norm
    sd = poses.sd if poses.sd is not None else np.zeros_like(mean_u)
    var = np.sum(ghat**2 * (sd / fit.normalizer.scale) ** 2, axis=1) / poses.count
    f2 = floor_g**2
    sig2 = var + f2
    r, jac = model.residual_jac(fit.theta_u, mean_u, poses.temp_c, poses.t_s)
    jw = jac / np.sqrt(sig2)[:, None]
    h = np.einsum("ij,ij->i", jw @ (fit.cov_u / max(1.0, fit.chi2_red)), jw)  # the leverages; the product by BLAS
    limit = (FitConfig().reject_z if reject_z is None else reject_z) * fit.extra.get("robust_scale", 1.0)
    keep = np.abs(r) / np.sqrt(sig2) <= limit
    if keep.sum() < min_poses:
        return 1.0, 1.0
    y = r[keep] ** 2 / np.clip(1.0 - h[keep], 0.05, 1.0)
    x = np.column_stack([np.full(int(keep.sum()), f2), var[keep]])
    w = 1.0 / sig2[keep]
    lo, hi = np.array(bounds, dtype=float).T
    coef = lo.copy()  # a coefficient whose bounds meet is that value (the solver needs lo < hi)
    free = lo < hi
    if free.any():
        a = x * w[:, None]
        rhs = y * w - a[:, ~free] @ coef[~free]
        coef[free] = lsq_linear(a[:, free], rhs, bounds=(lo[free], hi[free]), method="bvls").x
    c0 = float(np.clip(coef[0], *bounds[0]))  # (the solver's own bounds, to the last bit)
    c1 = float(np.clip(coef[1], *bounds[1]))
    return c0, c1


# --------------------------------------------------------------------------- sphere


def sphere_directions(n: int = 2000) -> np.ndarray:
    """Quasi-uniform unit directions (Fibonacci sphere), shape (n, 3)."""
    i = np.arange(n) + 0.5
    zc = 1 - 2 * i / n
    r = np.sqrt(1 - zc * zc)
    phi = np.pi * (1 + 5**0.5) * i
    return np.column_stack([r * np.cos(phi), r * np.sin(phi), zc])


@functools.lru_cache(maxsize=8)
def _sphere_directions_read_only(n: int) -> np.ndarray:
    """:func:`sphere_directions` ``(n, 3)``, computed once per ``n`` and read-only (every
    published version's predicted sphere RMS, and each model check's, asks for the same 256)."""
    dirs = sphere_directions(n)
    dirs.setflags(write=False)
    return dirs


def sphere_jacobian(model: ErrorModel, theta_u: np.ndarray, t_s: float | None = None, n_dirs: int = 256) -> np.ndarray:
    """Jacobian (n_dirs, p) of the calibrated norm over the whole sphere.

    Rows: directions spread over the sphere, taken to raw readings through the model's
    own linear part, at the reference temperature and at time ``t_s`` (default the
    model's time origin).
    """
    raw, temp, tt = _sphere_readings(model, theta_u, t_s, n_dirs)
    return model.residual_jac(theta_u, raw, temp, tt)[1]


def _sphere_readings(model: ErrorModel, theta_u: np.ndarray, t_s: float | None,
                     n_dirs: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The sphere's directions as raw readings: ``(raw (n_dirs, 3), temp_c (n_dirs,), t_s
    (n_dirs,))``, through the model's linear part at ``theta_u``, at the reference
    temperature and at ``t_s`` (default the model's time origin)."""
    dirs = _sphere_directions_read_only(n_dirs)
    matrix, offset = model.linear(np.asarray(theta_u, dtype=float))
    raw = dirs @ np.linalg.inv(matrix).T + offset
    temp = np.full(n_dirs, model.temp_ref_c)
    tt = np.full(n_dirs, model.t_ref_s if t_s is None else float(t_s))
    return raw, temp, tt


def predicted_sphere_rms_mg(model: ErrorModel, theta_u: np.ndarray, cov_u: np.ndarray,
                            t_s: float | None = None, n_dirs: int = 256) -> float:
    """Calibrated-norm RMS error over the whole sphere (mg) that a covariance predicts.

    ``sqrt(mean_d J_d cov J_d^T)``: the norm error of a calibrated reading, averaged over
    gravity directions spread on the sphere, at the reference temperature (normalised
    units, ~g; ``cov_u`` (p, p)).
    """
    return _sphere_rms_mg(sphere_jacobian(model, theta_u, t_s, n_dirs), cov_u)


def _sphere_rms_mg(jac: np.ndarray, cov_u: np.ndarray) -> float:
    """``sqrt(mean_d J_d cov J_d^T)`` in mg, from a sphere Jacobian ``jac`` (n_dirs, p)."""
    var = np.einsum("ij,ij->i", jac @ np.asarray(cov_u, dtype=float), jac)
    return float(np.sqrt(max(float(np.mean(var)), 0.0)) * 1e3)


def unmodelled_sphere_rms_mg(fit: FitResult, extended: ErrorModel, prior_small: Prior, prior_extended: Prior,
                             t_s: float | None, cfg: FitConfig) -> tuple[float, float]:
    """Whole-sphere calibrated-norm RMS error (mg) that effects ``fit``'s model lacks can
    add: ``(undetermined, determined)``, what the poses leave open and what they say the
    effects are (the total is their sum in quadrature).

    ``extended`` is the fitted model plus those effects (their terms at 0: the fitted
    model's value), with its prior ``prior_extended`` (``prior_small`` for the shared
    terms, the datasheet for the others). Both models' posterior covariances come from the
    fit's weighted Jacobian (its robust weights and inliers, inflated by its reduced
    chi-square) at the estimate; the result is ``sqrt(max(0, P_ext^2 - P_small^2))`` with
    ``P`` :func:`predicted_sphere_rms_mg` of each: what the effects' own terms move on the
    sphere, and what they take from the shared terms, at their datasheet size where no
    pose tells them apart. A term the poses determine adds little as uncertainty, but
    what they determine it to be is an error of the model without it: the extended model
    fitted to the fit's own poses (``fit.poses``; robust, from the fit's estimate, with
    ``cfg``: the fit's noise floor) moves the sphere's calibrated norms by an RMS that is
    added in quadrature (its square scaled by ``(W - k) / W``, ``W`` the Wald chi-square
    of the ``k`` effect terms: the part of it that noise does not explain). An effect no
    pose can see (a quadratic nonlinearity on an insole's ±1 g axes) adds its whole
    prior; one the poses pin down adds its size. ``(inf, inf)`` when a fit fails.
    """
    if fit.cells_u is None or fit.poses is None:
        raise InputError("unmodelled_sphere_rms_mg: the fit does not carry its poses")
    raw_u, temp, ts = fit.cells_u
    theta = extended.extend_theta(fit.theta_u, fit.model)
    _, jac = extended.residual_jac(theta, raw_u, temp, ts)
    z = fit.residuals_g / fit.sigma_g
    weights = np.asarray(fit.extra.get("weights", np.ones(len(z))), dtype=float)
    w = np.where(np.abs(z) <= cfg.reject_z, weights, 0.0)
    jw = jac / fit.sigma_g[:, None] * np.sqrt(w)[:, None]
    infl = max(1.0, float(fit.chi2_red)) if np.isfinite(fit.chi2_red) else 1.0
    small = [extended.param_names.index(n) for n in fit.model.param_names]
    try:
        cov_ext = np.linalg.inv(jw.T @ jw / infl + prior_extended.precision())
        js = jw[:, small]
        cov_small = np.linalg.inv(js.T @ js / infl + prior_small.precision())
    except np.linalg.LinAlgError:
        return float("inf"), float("inf")
    # predicted_sphere_rms_mg of each, the extended model's sphere Jacobian computed once
    sphere = sphere_jacobian(extended, theta, t_s)
    p_ext = _sphere_rms_mg(sphere, cov_ext)
    p_small = predicted_sphere_rms_mg(fit.model, fit.theta_u, 0.5 * (cov_small + cov_small.T), t_s)
    # what the poses determine the effects to be: the extended model fitted to the same poses
    # (robust, from the fit, its noise and prior), its calibrated norms over the sphere
    # against the fit's. (One Gauss-Newton step from the fit is not enough: the fit is
    # stationary only to its tolerance and in its own noise model, whose sigma depends on
    # the parameters; an effect term nearly in the span of the model's, a quadratic
    # nonlinearity on ±1 g poses, turned that remainder into steps of 100 mg and more.)
    terms = np.setdiff1d(np.arange(extended.n_params), small)
    try:
        ext = fit_poses(extended, fit.poses, normalizer=fit.normalizer, prior=prior_extended, theta0_u=theta,
                        cfg=cfg, robust=True)
    except (InputError, np.linalg.LinAlgError):
        ext = None
    if ext is None or not ext.success:
        return float("inf"), float("inf")
    # over the sphere's readings as sphere_jacobian takes them (through the fit's linear part)
    raw, temp_ref, t_eval = _sphere_readings(extended, theta, t_s, len(sphere))
    moved = (extended.residuals(ext.theta_u, raw, temp_ref, t_eval)
             - extended.residuals(theta, raw, temp_ref, t_eval))
    shift = float(np.sqrt(np.mean(np.square(moved))) * 1e3)
    d = ext.theta_u[terms]
    try:
        wald = float(d @ np.linalg.solve(ext.cov_u[np.ix_(terms, terms)], d))
    except np.linalg.LinAlgError:
        wald = np.inf
    beyond_noise = max(0.0, 1.0 - len(terms) / wald) if wald > 0 else 0.0
    return float(np.sqrt(max(p_ext**2 - p_small**2, 0.0))), float(np.sqrt(beyond_noise) * shift)


# --------------------------------------------------------------------------- guard


@dataclass
class GuardDecision:
    """Whether a candidate model may be published, and why not."""

    publish: bool
    reason: str | None
    message: str
    heldout_rms_mg_new: float | None = None
    heldout_rms_mg_current: float | None = None

    def to_dict(self) -> dict:
        return {
            "published": self.publish,
            "reason": self.reason,
            "message": self.message,
            "heldout_rms_mg_new": self.heldout_rms_mg_new,
            "heldout_rms_mg_current": self.heldout_rms_mg_current,
        }


def implausible(model: ErrorModel, theta_u: np.ndarray, cfg: GuardConfig) -> str | None:
    """A message naming the first parameter outside its plausible range, or None."""
    checks = [("b", cfg.max_bias_g, 0.0), ("s", cfg.max_scale_dev, 1.0)]
    if model.base != "scale6":
        checks.append(("n", cfg.max_nonorth_rad, 0.0))
    limits = {
        "temperature_bias": cfg.max_temp_bias_g_per_c,
        "temperature_scale": cfg.max_temp_scale_per_c,
        "time_drift_bias": cfg.max_drift_g_per_day,
        "scale_nonlinearity": cfg.max_nonlin_per_g,
        "temperature_cross": cfg.max_temp_cross_per_c,
        "bias_step": cfg.max_bias_step_g,
    }
    checks += [(e, limits[e], 0.0) for e in model.effects]
    for key, lim, centre in checks:
        sl = model.index(key)
        vals = theta_u[sl] - centre
        bad = np.flatnonzero(np.abs(vals) > lim)
        if bad.size:
            name = model.param_names[sl.start + bad[0]]
            return f"{name} = {theta_u[sl][bad[0]]:.4g} (normalised) is outside its plausible range ±{lim:g}"
    return None


def heldout_mask(pose_ids: np.ndarray, every: int) -> np.ndarray:
    """Deterministic held-out split: poses whose id is a multiple of ``every``."""
    return (np.asarray(pose_ids) % every) == 0


def rms_mg(model: ErrorModel, theta_u: np.ndarray, normalizer: Normalizer, poses: PoseData) -> float:
    """RMS of the norm residuals (mg) of ``poses`` under a model."""
    r = model.residuals(theta_u, normalizer.to_u(poses.mean), poses.temp_c, poses.t_s)
    return float(np.sqrt(np.mean(r**2)) * 1e3)
