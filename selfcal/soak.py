"""Thermal soaks: a device lying still in one orientation while its temperature changes.

In a soak the orientation is one unknown shared by every still window, so any drift of
the calibrated still mean with temperature is sensor error. The drift of the 3-vector
(not only its norm) gives the bias tempco along every axis, and the sensitivity tempco
along gravity. This module finds soaks in a sequence of still windows and fits the
temperature terms of a soak, on top of the current base calibration, with their
covariance and an honest statement of what one orientation can determine.

Model, for the calibrated window means ``a_k`` (g, shape (k, 3)) at temperatures
``T_k`` (°C), ``dT_k = T_k - T_ref``:

* ``temperature_bias``:  ``a_k = g + dT_k * tb``            (tb: 3 offsets, g/°C)
* ``temperature_scale``: ``a_k = g - dT_k * diag(g) * ts``   (ts: 3 relative scales, 1/°C)
* ``temperature_bias+scale``: both (6 terms, of which one orientation sees 3 combinations)

These are the error model's terms (``selfcal.models``: offset ``b + tb dT``, scales
``s (1 + ts dT)``). Given the *raw* window means (``diagnose`` passes them, normalised
to ~g), the bias drift is exactly the model's raw-unit ``tb``, and the scale drift is
``-diag(g) ts dT`` to first order for a near-unit sensor; given base-calibrated means,
``tb`` comes out in the calibrated frame (``A tb``).

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
PRIOR_DRIFT_G_PER_DAY = 2e-3  # as [fit] prior_drift_g_per_day


def _prior_sd(names: list[str], bias: float = PRIOR_BIAS_G_PER_C, scale: float = PRIOR_SCALE_PER_C,
              drift: float = PRIOR_DRIFT_G_PER_DAY) -> np.ndarray:
    """Prior sd of each term (tb*: g/°C, ts*: 1/°C, db*: g/day)."""
    return np.array([{"tb": bias, "ts": scale, "db": drift}[n[:2]] for n in names])


def _display_scale(names: list[str]) -> np.ndarray:
    """Factor to the reported units: mg/°C and mg/day for offsets, ppm/°C for scales."""
    return np.array([1e6 if n.startswith("ts") else 1e3 for n in names])
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
    effect: str               # the model's name, "none" (not significant at ``alpha``) or "undetermined"
    variance_factor: float
    lag1: float
    notes: list[str] = field(default_factory=list)

    def to_dict(self) -> dict:
        """JSON-ready: bias terms in mg/°C, scale terms in ppm/°C."""
        conv = _display_scale(self.names)
        unit = {n: {"tb": "mg/degC", "db": "mg/day"}.get(n[:2], "ppm/degC") for n in self.names}
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
             alpha: float = 0.01, frame: str = "vector", t_s: np.ndarray | None = None,
             prior_drift_g_per_day: float = PRIOR_DRIFT_G_PER_DAY) -> SoakFit:
    """Fit the temperature terms of one soak.

    Parameters
    ----------
    temp_c : (k,) °C — window temperatures, in time order
    mean_g : (k, 3) g — calibrated window means (the base model applied)
    var_g2 : (k,) or (k, 3) or scalar, g² — variance of each window mean (per axis)
    model : one of ``SOAK_MODELS``
    t_ref_c : reference temperature (°C); default the soak's mean
    alpha : false-alarm rate of the "any temperature term" test
    t_s : (k,) s — window times. Given, an offset drift in time (``db``, g/day, the
        ``time_drift_bias`` terms) is fitted beside the temperature terms: an exponential
        cooling separates the two, a linear temperature ramp cannot (the note says so).
    frame : ``vector`` fits the 3-vector drift (a clamped device: every bias tempco from one
        soak); ``norm`` fits only the drift along gravity, which a slow re-settling rotation
        of the device cannot fake (one combination per soak; several orientations combined
        determine more). Real soaks (a band on a table, an insole set down) re-settle by
        tenths of a degree, i.e. mg across gravity: use ``norm`` for them.

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
    names = _names(model) + (["dbx", "dby", "dbz"] if t_s is not None else [])
    p = len(names)
    g0 = np.mean(a, axis=0)
    g0 = g0 / np.linalg.norm(g0)
    blocks = []
    if "bias" in model:
        blocks.append(dt[:, None, None] * np.eye(3)[None])                  # (k, 3, 3)
    if "scale" in model:
        blocks.append(-dt[:, None, None] * np.diag(g0)[None])                # (k, 3, 3)
    if t_s is not None:
        days = (np.asarray(t_s, float) - float(np.mean(t_s))) / 86400.0
        blocks.append(days[:, None, None] * np.eye(3)[None])                # (k, 3, 3)
    j_terms = np.concatenate(blocks, axis=2)                                 # (k, 3, p)
    if frame == "vector":  # unknowns: g (3) and the terms; 3 rows per window
        m, q = 3, 3
        x = np.concatenate([np.broadcast_to(np.eye(3), (k, 3, 3)), j_terms], axis=2).reshape(3 * k, 3 + p)
        y = a.reshape(3 * k)
        v_rows = var.reshape(3 * k)
    elif frame == "norm":  # unknowns: |g| (1) and the terms; the component along gravity only
        m, q = 1, 1
        x = np.concatenate([np.ones((k, 1)), np.einsum("i,kip->kp", g0, j_terms)], axis=1)
        y = a @ g0
        v_rows = var @ (g0**2)
    else:
        raise ValueError(f"frame {frame!r}: 'vector' or 'norm'")
    w = 1.0 / np.maximum(v_rows, 1e-18)
    prior_sd = _prior_sd(names, prior_bias_g_per_c, prior_scale_per_c, prior_drift_g_per_day)
    prior_prec = np.concatenate([np.zeros(q), 1.0 / prior_sd**2])
    xtw = x.T * w
    fisher = xtw @ x
    theta = np.linalg.solve(fisher + np.diag(prior_prec), xtw @ y)
    res = (y - x @ theta).reshape(k, m)
    # long-run variance of the standardised residuals (serially correlated windows): the
    # residuals are white noise plus a slowly settling part, an ARMA(1,1) whose
    # autocovariances decay as r^(l-1) after lag 1; r = gamma2 / gamma1. The covariance
    # is scaled by gamma0 + 2 gamma1 / (1 - r), never down.
    z = res / np.sqrt(v_rows.reshape(k, m))
    dof = max(m * k - q - p, 1)
    gamma0 = float(np.sum(z**2)) / dof
    vf = max(1.0, gamma0)
    lag1, inflate = 0.0, vf
    if k >= 6:
        gamma1 = float(np.sum(z[1:] * z[:-1])) / (m * (k - 1))
        gamma2 = float(np.sum(z[2:] * z[:-2])) / (m * (k - 2))
        if gamma1 > 0:
            r = float(np.clip(gamma2 / gamma1, 0.0, 0.95))
            lag1 = gamma1 / gamma0 if gamma0 > 0 else 0.0
            inflate = max(vf, gamma0 + 2.0 * gamma1 / (1.0 - r))
    post = np.linalg.inv(fisher / inflate + np.diag(prior_prec))
    theta = np.linalg.solve(fisher / inflate + np.diag(prior_prec), xtw @ y / inflate)
    cov = post[q:, q:]
    coef = theta[q:]
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
    else:  # nothing determined: say so, rather than "none"
        chi2, dof_e, effect = 0.0, 0, "undetermined"
        notes.append(f"not determinable: a temperature span of {np.ptp(temp):.2f} degC is too small for the "
                     f"noise of {k} windows")
    if t_s is not None:  # can this soak tell temperature from time?
        sd_all = np.sqrt(np.diag(cov))
        corr = cov / np.outer(sd_all, sd_all)
        ti = [i for i, n in enumerate(names) if n.startswith("tb")]
        di = [i for i, n in enumerate(names) if n.startswith("db")]
        worst = max((abs(corr[i, j]) for i in ti for j in di), default=0.0)
        if worst > 0.95:
            notes.append(f"temperature and time drift are confounded in this soak (correlation {worst:.2f}: the "
                         "temperature changes about linearly in time)")
        elif np.any(determined[ti]):
            notes.append(f"temperature terms separated from time drift (largest correlation {worst:.2f})")
    if len([n for n in names if not n.startswith("db")]) > 3:
        notes.append("one orientation sees 3 combinations of the 6 bias and scale terms; the rest stays at the prior")
    return SoakFit(model=model, names=names, coef=coef, std=std, cov=cov, determined=determined,
                   undetermined_directions=undet,
                   orientation=theta[:3] if frame == "vector" else g0 * theta[0], t_ref_c=t_ref, dtemp_c=float(np.ptp(temp)),
                   n_windows=k, chi2_effect=chi2, dof_effect=dof_e, effect=effect, variance_factor=vf, lag1=lag1,
                   notes=notes)


def combine(fits: list[SoakFit]) -> dict | None:
    """One estimate of the shared terms from several soaks of one model (independent soaks):
    their data information added, the prior counted once. None without a fit."""
    if not fits:
        return None
    names = fits[0].names
    prior_sd = _prior_sd(names)
    prior_prec = np.diag(1.0 / prior_sd**2)
    precision = prior_prec.copy()
    weighted = np.zeros(len(names))
    for f in fits:
        info = np.linalg.inv(f.cov)
        precision += info - prior_prec
        weighted += info @ f.coef
    cov = np.linalg.inv(precision)
    coef = cov @ weighted
    std = np.sqrt(np.diag(cov))
    conv = _display_scale(names)
    corr = cov / np.outer(std, std)
    return {"coef": dict(zip(names, (coef * conv).round(6).tolist())),
            "std": dict(zip(names, (std * conv).round(6).tolist())),
            "corr": {"names": list(names), "matrix": corr.round(6).tolist()},
            "determined": [n for n, s, p in zip(names, std, prior_sd) if s <= DETERMINED_RATIO * p],
            "n_soaks": len(fits)}


def soak_report(t_s: np.ndarray, mean_g: np.ndarray, var_g2: np.ndarray, temp_c: np.ndarray | None,
                config: SoakConfig | None = None, model: str = "temperature_bias", frame: str = "norm") -> dict:
    """Soaks among still windows and what they determine (JSON-ready).

    Parameters
    ----------
    t_s : (k,) s; mean_g : (k, 3) g, base-calibrated window means; var_g2 : (k, 3) or (k,) g²;
    temp_c : (k,) °C or None

    Each soak is fitted twice: with the temperature terms (its answer), and with an offset
    drift in time beside them (``with_time_drift``, whose notes say whether the soak's
    shape separates the two). The answer says in how many soaks they are confounded:
    a temperature term that the soak determined is no longer determined once the drift
    is allowed, or the two correlate beyond 0.95.
    """
    if temp_c is None or not np.any(np.isfinite(np.asarray(temp_c, float))):
        return {"found": 0, "soaks": [], "combined": None, "answer": "no temperature: soaks cannot be looked for",
                "combined_with_time_drift": None, "time_drift_confounded": 0}
    order = np.argsort(t_s, kind="stable")
    t = np.asarray(t_s, float)[order]
    m = np.asarray(mean_g, float)[order]
    v = np.asarray(var_g2, float)[order]
    temp = np.asarray(temp_c, float)[order]
    cfg = config or SoakConfig()
    runs = find_soaks(t, m, temp, cfg)
    fits, rows = [], []
    confounded = 0
    drift_fits = []
    for r in runs:
        f = fit_soak(temp[r], m[r], v[r], model=model, frame=frame)
        fits.append(f)
        row = dict(f.to_dict(), t_start_s=float(t[r.start]), t_end_s=float(t[r.stop - 1]))
        # the same soak with an offset drift in time beside the temperature terms: does the
        # soak's shape tell temperature from time (exponential cooling), or not (a ramp)?
        if r.stop - r.start >= 4:
            fdf = fit_soak(temp[r], m[r], v[r], model=model, frame=frame, t_s=t[r])
            drift_fits.append(fdf)
            fd = fdf.to_dict()
            row["with_time_drift"] = {k: fd[k] for k in ("coef", "std", "determined", "units", "notes")}
            lost = bool(f.determined.any()) and not any(n.startswith("t") for n in fd["determined"])
            confounded += lost or any("confounded" in n for n in fd["notes"])
        rows.append(row)
    comb = combine(fits)
    spans = [f.dtemp_c for f in fits]
    if not runs:
        answer = (f"no soak: no run of >= {cfg.min_windows} still windows in one orientation "
                  f"(within {cfg.max_angle_deg:g} deg) spanning >= {cfg.min_dtemp_c:g} degC")
    elif not comb["determined"]:
        answer = (f"not determinable: {len(runs)} soak(s) of {min(spans):.1f}-{max(spans):.1f} degC; the "
                  f"temperature change is too small for the noise, even combined")
    else:
        det = comb["determined"]
        cw = np.array([comb["coef"][n] for n in det])
        sd = np.array([comb["std"][n] for n in det])
        # combined, determined terms, with their correlations (two soaks 10 deg apart correlate tbx
        # and tbz at -0.7: summing their squares alone gave 1.65 % false answers at a 1 % level)
        pos = [comb["corr"]["names"].index(n) for n in det]
        corr = np.asarray(comb["corr"]["matrix"])[np.ix_(pos, pos)]
        z = cw / sd
        chi2 = float(z @ np.linalg.solve(corr, z))
        terms = ", ".join(f"{n} {comb['coef'][n]:+.3f} ± {comb['std'][n]:.3f}" for n in det)
        if chi2 > float(chdtri(len(det), 0.01)):
            answer = f"{model}: {terms} ({'mg' if model == 'temperature_bias' else 'mg or ppm'}/degC, {len(runs)} soak(s) combined)"
        else:
            answer = f"none: {terms} (not significant at 1 %, {len(runs)} soak(s) combined)"
        comb["chi2"], comb["effect"] = chi2, answer.split(":")[0]
    comb_drift = combine(drift_fits) if len(drift_fits) == len(fits) else None
    if comb is not None and comb["determined"] and comb_drift is not None:
        det_t = [n for n in comb_drift["determined"] if n.startswith("t")]
        if det_t:
            answer += "; allowing an offset drift in time (shared): " + ", ".join(
                f"{n} {comb_drift['coef'][n]:+.3f} ± {comb_drift['std'][n]:.3f}" for n in det_t)
        else:
            answer += "; allowing an offset drift in time (shared), no temperature term stays determined"
    if confounded:
        answer += (f"; in {confounded} of {len(runs)} soak(s) an offset drift in time would fit as well (the "
                   "temperature changes about linearly in time, or too little beside the drift prior: see "
                   "with_time_drift)")
    return {"found": len(runs), "frame": frame, "soaks": rows, "combined": comb, "answer": answer,
            "combined_with_time_drift": comb_drift,
            "time_drift_confounded": confounded}
