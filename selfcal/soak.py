"""Thermal soaks: a device lying still in one orientation while its temperature changes.

In a soak the orientation is one unknown shared by every still window, so any drift of
the calibrated still mean with temperature is sensor error. The drift of the 3-vector
(not only its norm) gives the bias tempco along every axis, and the sensitivity tempco
along gravity. This module finds soaks in a sequence of still windows and fits the
temperature terms of a soak, on top of the current base calibration, with their
covariance and an honest statement of what one orientation can determine.

Model, for the calibrated window means ``a_k`` (g, shape (k, 3)) at temperatures
``T_k`` (°C), ``dT_k = T_k - T_ref``:

* ``temperature_bias``:  ``a_k = g - dT_k * tb``            (tb: 3 offsets, g/°C)
* ``temperature_scale``: ``a_k = g + dT_k * diag(g) * ts``   (ts: 3 relative scales, 1/°C)
* ``temperature_bias+scale``: both (6 terms, of which one orientation sees 3 combinations)

``g`` (the orientation, 3 numbers: its norm is the base model's business) is free.
The terms have the datasheet prior (bias 1 mg/°C, scale 300 ppm/°C by default); a
term, or a combination, that the data do not shrink below 0.3 of its prior sd is
reported undetermined and stays at the prior, as in the base fit. Windows of one
soak are serially correlated (slow settling, micro-motion): the covariance is
inflated by the residuals' long-run variance (white noise plus a settling part whose
autocorrelation decays geometrically), never deflated.

Angles inside are radians; the public thresholds name their unit.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np
from scipy.special import chdtri

#: datasheet prior sds of the temperature terms
PRIOR_BIAS_G_PER_C = 1e-3
PRIOR_SCALE_PER_C = 300e-6
DETERMINED_RATIO = 0.3
SOAK_MODELS = ("temperature_bias", "temperature_scale", "temperature_bias+scale")


@dataclass(frozen=True)
class SoakConfig:
    """How soaks are found: one orientation within ``max_angle_deg``, gaps ≤ ``max_gap_s``,
    at least ``min_windows`` windows and a temperature change of ``min_dtemp_c`` °C."""

    max_angle_deg: float = 2.0
    max_gap_s: float = 120.0
    min_windows: int = 5
    min_dtemp_c: float = 1.0


def find_soaks(t_s: np.ndarray, mean_g: np.ndarray, temp_c: np.ndarray,
               config: SoakConfig | None = None) -> list[slice]:
    """Soak segments among still windows sorted by time.

    Parameters
    ----------
    t_s : (k,) s — window times; mean_g : (k, 3) g — window means; temp_c : (k,) °C

    Returns the slices (into the arrays) of maximal runs of windows in one orientation
    (within ``max_angle_deg`` of the run's first window, consecutive gaps ≤ ``max_gap_s``)
    whose temperature spans at least ``min_dtemp_c``.
    """
    cfg = config or SoakConfig()
    t_s = np.asarray(t_s, float)
    u = np.asarray(mean_g, float)
    u = u / np.linalg.norm(u, axis=1, keepdims=True)
    temp = np.asarray(temp_c, float)
    cos_tol = np.cos(np.deg2rad(cfg.max_angle_deg))
    out: list[slice] = []
    start = 0
    k = len(t_s)
    for i in range(1, k + 1):  # runs are few and long: one pass over the windows
        if i < k and t_s[i] - t_s[i - 1] <= cfg.max_gap_s and float(u[i] @ u[start]) >= cos_tol:
            continue
        run = slice(start, i)
        if i - start >= cfg.min_windows and np.ptp(temp[run]) >= cfg.min_dtemp_c:
            out.append(run)
        start = i
    return out


@dataclass
class SoakFit:
    """The temperature terms one soak determines (see the module docstring)."""

    model: str
    names: list[str]
    coef: np.ndarray          # (p,) bias terms in g/°C, scale terms in 1/°C
    std: np.ndarray           # (p,) posterior sd, same units
    cov: np.ndarray           # (p, p)
    determined: np.ndarray    # (p,) bool: data shrank the prior sd below 0.3 of it
    undetermined_directions: list[list[float]]  # prior-whitened combinations the soak cannot see
    orientation: np.ndarray   # (3,) fitted g at T_ref
    t_ref_c: float
    dtemp_c: float            # temperature span of the soak
    n_windows: int
    chi2_effect: float        # evidence for any temperature term (determined part)
    dof_effect: int
    effect: str               # the model's name, or "none" (not significant at ``alpha``)
    variance_factor: float
    lag1: float
    notes: list[str] = field(default_factory=list)

    def to_dict(self) -> dict:
        """JSON-ready: bias terms in mg/°C, scale terms in ppm/°C."""
        conv = np.array([1e3 if n.startswith("tb") else 1e6 for n in self.names])
        unit = {n: ("mg/degC" if n.startswith("tb") else "ppm/degC") for n in self.names}
        return {
            "model": self.model, "effect": self.effect, "units": unit,
            "coef": dict(zip(self.names, (self.coef * conv).round(6).tolist())),
            "std": dict(zip(self.names, (self.std * conv).round(6).tolist())),
            "determined": [n for n, d in zip(self.names, self.determined) if d],
            "undetermined": [n for n, d in zip(self.names, self.determined) if not d],
            "undetermined_directions": self.undetermined_directions,
            "orientation_g": self.orientation.round(6).tolist(), "t_ref_c": self.t_ref_c,
            "dtemp_c": self.dtemp_c, "n_windows": self.n_windows,
            "chi2_effect": self.chi2_effect, "dof_effect": self.dof_effect,
            "variance_factor": self.variance_factor, "lag1": self.lag1, "notes": self.notes,
        }


def _names(model: str) -> list[str]:
    names = []
    if "bias" in model:
        names += ["tbx", "tby", "tbz"]
    if "scale" in model:
        names += ["tsx", "tsy", "tsz"]
    return names


def fit_soak(temp_c: np.ndarray, mean_g: np.ndarray, var_g2: np.ndarray | float, *,
             model: str = "temperature_bias", t_ref_c: float | None = None,
             prior_bias_g_per_c: float = PRIOR_BIAS_G_PER_C, prior_scale_per_c: float = PRIOR_SCALE_PER_C,
             alpha: float = 0.01) -> SoakFit:
    """Fit the temperature terms of one soak.

    Parameters
    ----------
    temp_c : (k,) °C — window temperatures, in time order
    mean_g : (k, 3) g — calibrated window means (the base model applied)
    var_g2 : (k,) or (k, 3) or scalar, g² — variance of each window mean (per axis)
    model : one of ``SOAK_MODELS``
    t_ref_c : reference temperature (°C); default the soak's mean
    alpha : false-alarm rate of the "any temperature term" test

    Returns a :class:`SoakFit`; never raises for a soak too small to tell: its terms are
    then undetermined and its effect ``none``, with a note saying why.
    """
    if model not in SOAK_MODELS:
        raise ValueError(f"model {model!r}: choose one of {SOAK_MODELS}")
    temp = np.asarray(temp_c, float)
    a = np.asarray(mean_g, float)
    k = len(temp)
    if a.shape != (k, 3) or k < 3:
        raise ValueError(f"mean_g: expected shape ({k}, 3) with at least 3 windows, got {a.shape}")
    var = np.broadcast_to(np.asarray(var_g2, float).reshape(-1, 1) if np.ndim(var_g2) == 1 else var_g2, (k, 3))
    t_ref = float(np.mean(temp)) if t_ref_c is None else float(t_ref_c)
    dt = temp - t_ref
    names = _names(model)
    p = len(names)
    g0 = np.mean(a, axis=0)
    g0 = g0 / np.linalg.norm(g0)
    # design: unknowns (g (3), terms (p)); rows k*3 (axis-major per window)
    blocks = []
    if "bias" in model:
        blocks.append(-dt[:, None, None] * np.eye(3)[None])                 # (k, 3, 3)
    if "scale" in model:
        blocks.append(dt[:, None, None] * np.diag(g0)[None])                 # (k, 3, 3)
    j_terms = np.concatenate(blocks, axis=2)                                 # (k, 3, p)
    x = np.concatenate([np.broadcast_to(np.eye(3), (k, 3, 3)), j_terms], axis=2).reshape(3 * k, 3 + p)
    y = a.reshape(3 * k)
    w = 1.0 / np.maximum(var.reshape(3 * k), 1e-18)
    prior_sd = np.array([prior_bias_g_per_c if n.startswith("tb") else prior_scale_per_c for n in names])
    prior_prec = np.concatenate([np.zeros(3), 1.0 / prior_sd**2])
    xtw = x.T * w
    fisher = xtw @ x
    theta = np.linalg.solve(fisher + np.diag(prior_prec), xtw @ y)
    res = (y - x @ theta).reshape(k, 3)
    # long-run variance of the standardised residuals (serially correlated windows): the
    # residuals are white noise plus a slowly settling part, an ARMA(1,1) whose
    # autocovariances decay as r^(l-1) after lag 1; r = gamma2 / gamma1. The covariance
    # is scaled by gamma0 + 2 gamma1 / (1 - r), never down.
    z = res / np.sqrt(var)
    dof = max(3 * k - 3 - p, 1)
    gamma0 = float(np.sum(z**2)) / dof
    vf = max(1.0, gamma0)
    lag1, inflate = 0.0, vf
    if k >= 6:
        gamma1 = float(np.sum(z[1:] * z[:-1])) / (3 * (k - 1))
        gamma2 = float(np.sum(z[2:] * z[:-2])) / (3 * (k - 2))
        if gamma1 > 0:
            r = float(np.clip(gamma2 / gamma1, 0.0, 0.95))
            lag1 = gamma1 / gamma0 if gamma0 > 0 else 0.0
            inflate = max(vf, gamma0 + 2.0 * gamma1 / (1.0 - r))
    post = np.linalg.inv(fisher / inflate + np.diag(prior_prec))
    theta = np.linalg.solve(fisher / inflate + np.diag(prior_prec), xtw @ y / inflate)
    cov = post[3:, 3:]
    coef = theta[3:]
    std = np.sqrt(np.diag(cov))
    determined = std <= DETERMINED_RATIO * prior_sd
    # undetermined combinations: eigen-directions of the prior-whitened information of the
    # terms (g profiled out) that the data barely shrink
    info = np.linalg.inv(cov) - np.diag(1.0 / prior_sd**2)                   # data information of the terms
    white = info * np.outer(prior_sd, prior_sd)
    evals, evecs = np.linalg.eigh((white + white.T) / 2)
    shrink = 1.0 / np.sqrt(1.0 + np.maximum(evals, 0.0))                     # posterior / prior sd along each
    undet = [evecs[:, i].round(4).tolist() for i in range(p) if shrink[i] > DETERMINED_RATIO]
    # evidence for any temperature term, on the determined subspace, against the data-only covariance
    notes: list[str] = []
    good = evals > (1.0 / DETERMINED_RATIO**2 - 1.0)
    if good.any():
        v = evecs[:, good]
        cw = coef / prior_sd
        proj = v.T @ cw
        chi2 = float(np.sum(proj**2 * evals[good]))
        dof_e = int(good.sum())
        effect = model if chi2 > float(chdtri(dof_e, alpha)) else "none"
    else:
        chi2, dof_e, effect = 0.0, 0, "none"
        notes.append(f"not determinable: a temperature span of {np.ptp(temp):.2f} degC is too small for the "
                     f"noise of {k} windows")
    if p > 3:
        notes.append("one orientation sees 3 combinations of the 6 bias and scale terms; the rest stays at the prior")
    return SoakFit(model=model, names=names, coef=coef, std=std, cov=cov, determined=determined,
                   undetermined_directions=undet, orientation=theta[:3], t_ref_c=t_ref, dtemp_c=float(np.ptp(temp)),
                   n_windows=k, chi2_effect=chi2, dof_effect=dof_e, effect=effect, variance_factor=vf, lag1=lag1,
                   notes=notes)
