"""Correlated noise of still windows: a shared error per still bout and an AR(1) term within it.

The norm residual of still window ``i`` (in bout ``k``), in g::

    r_i = e_i + w_i + b_k + u_i

* ``e_i ~ N(0, s_i^2)``: the measured noise of the window mean (its per-axis sd^2 / count,
  projected on gravity), known per window;
* ``w_i ~ N(0, sigma_white^2)``: an independent excess (the fit's residual floor);
* ``b_k ~ N(0, sigma_bout^2)``: one error shared by every window of the bout (wrist
  micro-posture, strap pressure: what a still bout holds and the next one does not);
* ``u_i``: an AR(1) process in continuous time within the bout, variance ``sigma_ar^2``,
  correlation ``exp(-|t_i - t_j| / tau)``; independent between bouts.

A *still bout* is a run of consecutive windows (in time order) whose gaps are at most
``gap_s`` and whose gravity direction turns by at most ``angle_deg`` from one window to the
next. Windows further apart are independent under the model.

Estimation (:func:`estimate_bout_noise`) is by the method of moments on the base fit's
residuals. The mean excess ``C0 = mean(r^2 - s^2)`` is the variance beyond the measured
noise, ``sigma_bout^2 + sigma_ar^2 + sigma_white^2``. Within a bout, differences of two
windows cancel the bout's shared error: their excess semivariance, binned by lag,
``gamma(dt) = sigma_white^2 + sigma_ar^2 (1 - exp(-dt / tau))``, gives the AR(1) and
white parts (pair-weighted non-negative least squares for each ``tau`` on a grid; the
best ``tau`` is kept). The bout part is the rest, ``C0 - sigma_white^2 - sigma_ar^2``.
Standard deviations come from a bootstrap over bouts (bouts resampled with replacement,
every moment recomputed). The correlated part is kept only when a chi-square test on
the bouts' residual sums rejects independence (level ``INDEPENDENCE_ALPHA``); otherwise,
and when too few window pairs lie inside bouts, the model is independent noise with the
floor, as before.

Everything is vectorised: the AR(1) recursions (draws, covariance products) use a
parallel prefix scan (``log2 n`` numpy steps), not a loop over windows or bouts.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np
from scipy import stats

from selfcal.groupsum import sum_by_group

#: fewer window pairs inside bouts than this, or fewer bouts with two windows or more than
#: MIN_MULTI_BOUTS: the correlation is not estimated (independent noise)
MIN_PAIRS = 20
MIN_MULTI_BOUTS = 3
#: level of the test of independence within bouts; the correlated part is kept only when it rejects
INDEPENDENCE_ALPHA = 1e-3
#: the GLS whitener factors bouts of at most this many windows at once (longer ones in pieces)
WHITEN_MAX_BLOCK = 400


# ----------------------------------------------------------------------------- bouts


@dataclass(frozen=True)
class Bouts:
    """Still bouts of a set of windows.

    Attributes
    ----------
    order : (n,) int — indices that sort the windows by time
    label : (n,) int — bout of each window (input order), bouts numbered in time order
    t_sorted : (n,) s — times in time order
    phi_gap_s : (n,) s — in time order, time since the previous window of the same bout
        (``inf`` at the first window of a bout)
    n_bouts : int
    """

    order: np.ndarray
    label: np.ndarray
    t_sorted: np.ndarray
    phi_gap_s: np.ndarray
    n_bouts: int

    @property
    def sizes(self) -> np.ndarray:
        """Windows per bout, shape (n_bouts,)."""
        return np.bincount(self.label, minlength=self.n_bouts)

    @property
    def label_sorted(self) -> np.ndarray:
        """Bout of each window in time order, shape (n,)."""
        return self.label[self.order]

    def first_index(self) -> np.ndarray:
        """Input-order index of each bout's earliest window, shape (n_bouts,)."""
        lab = self.label_sorted
        start = np.r_[True, lab[1:] != lab[:-1]]
        return self.order[start]

    @classmethod
    def singletons(cls, t_s: np.ndarray) -> "Bouts":
        """Every window its own bout (independent windows)."""
        t_s = np.asarray(t_s, float)
        order = np.argsort(t_s, kind="stable")
        label = np.empty(len(t_s), dtype=np.int64)
        label[order] = np.arange(len(t_s))
        return cls(order, label, t_s[order], np.full(len(t_s), np.inf), len(t_s))


def find_bouts(t_s: np.ndarray, gdir: np.ndarray, gap_s: float = 60.0, angle_deg: float = 5.0) -> Bouts:
    """Group windows into still bouts.

    Parameters
    ----------
    t_s : (n,) window times, s
    gdir : (n, 3) unit gravity directions
    gap_s : a bout continues across a gap of at most this, s
    angle_deg : ... and a direction change of at most this between consecutive windows, deg

    Returns
    -------
    Bouts
    """
    t_s = np.asarray(t_s, float)
    order = np.argsort(t_s, kind="stable")
    ts = t_s[order]
    g = np.asarray(gdir, float)[order]
    dt = np.diff(ts)
    cosang = np.clip(np.sum(g[1:] * g[:-1], axis=1), -1.0, 1.0)
    joined = (dt <= gap_s) & (cosang >= np.cos(np.deg2rad(angle_deg)))
    start = np.r_[True, ~joined]
    lab_sorted = np.cumsum(start) - 1
    label = np.empty(len(ts), dtype=np.int64)
    label[order] = lab_sorted
    gap = np.where(start, np.inf, np.r_[0.0, dt])
    return Bouts(order, label, ts, gap, int(lab_sorted[-1] + 1) if len(ts) else 0)


def linear_scan(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """Solve ``u_i = a_i u_{i-1} + b_i`` (``u_{-1} = 0``) by a parallel prefix scan.

    Parameters
    ----------
    a : (n,) coefficients (0 restarts the recursion)
    b : (n,) or (n, m) inputs

    Returns
    -------
    u : same shape as ``b``
    """
    acc_a = np.asarray(a, float).copy()
    acc_b = np.asarray(b, float).copy()
    n = len(acc_a)
    d = 1
    while d < n and acc_a[d:].any():
        coef = acc_a[d:] if acc_b.ndim == 1 else acc_a[d:, None]
        acc_b[d:] = acc_b[d:] + coef * acc_b[:-d]  # the right side is evaluated from the old values
        acc_a[d:] = acc_a[d:] * acc_a[:-d]
        d *= 2
    return acc_b


# ----------------------------------------------------------------------------- model


@dataclass
class BoutNoise:
    """Fitted correlated-noise model of the norm residuals (g, s); see the module docstring.

    ``std`` holds bootstrap sds of ``sigma_*_g`` (g) and the 16-84 % interval of ``tau_s``.
    ``lags`` holds the binned within-bout excess semivariance the fit used: lag (s), pairs,
    measured and model (g²). ``unrestricted`` holds the moment estimates when the test of
    independence did not reject (the model then has no correlated part).
    """

    sigma_bout_g: float = 0.0
    sigma_ar_g: float = 0.0
    tau_s: float = float("nan")
    sigma_white_g: float = 0.0
    excess_var_g2: float = 0.0  # C0: mean(r^2 - s^2) of the residuals used (no correction, not clipped)
    noise_var_g2: float = 0.0  # mean measured noise variance s^2
    n_bouts: int = 0
    n_multi_bouts: int = 0
    n_windows_in_multi: int = 0
    n_pairs: int = 0
    max_lag_s: float = 0.0
    estimated: bool = False
    independence_chi2: float = float("nan")
    independence_dof: int = 0
    independence_p: float = float("nan")
    unrestricted: dict = field(default_factory=dict)
    projection_deltas: dict = field(default_factory=dict)
    why: str = ""
    std: dict = field(default_factory=dict)
    lags: dict = field(default_factory=dict)

    @property
    def correlated_var_g2(self) -> float:
        """Variance shared within a bout at lag 0: ``sigma_bout^2 + sigma_ar^2`` (g²)."""
        return self.sigma_bout_g**2 + self.sigma_ar_g**2

    def covariance(self, dt_s: np.ndarray) -> np.ndarray:
        """Model covariance (g²) of two windows of one bout at lags ``dt_s`` (s, any shape, > 0)."""
        dt_s = np.asarray(dt_s, float)
        ar = self.sigma_ar_g**2 * np.exp(-dt_s / self.tau_s) if self.sigma_ar_g > 0 else 0.0
        return self.sigma_bout_g**2 + ar

    def _phi(self, bouts: Bouts) -> np.ndarray:
        if not (self.sigma_ar_g > 0 and np.isfinite(self.tau_s) and self.tau_s > 0):
            return np.zeros(len(bouts.phi_gap_s))
        return np.exp(-bouts.phi_gap_s / self.tau_s)  # 0 at bout starts (gap inf)

    def draw(self, rng: np.random.Generator, bouts: Bouts, white: bool = True) -> np.ndarray:
        """One draw of ``w + b + u`` (g), shape (n,), input order (the measured noise ``e`` is not included).

        ``white=False`` leaves out the independent excess ``w``. Draws nothing from ``rng``
        for a zero component, so a model with no excess leaves the generator's stream as it was.
        """
        n = len(bouts.label)
        out = np.zeros(n)
        if white and self.sigma_white_g > 0:
            out += self.sigma_white_g * rng.standard_normal(n)
        if self.sigma_bout_g > 0:
            out += self.sigma_bout_g * rng.standard_normal(bouts.n_bouts)[bouts.label]
        if self.sigma_ar_g > 0:
            phi = self._phi(bouts)
            z = rng.standard_normal(n) * self.sigma_ar_g * np.sqrt(1.0 - phi**2)
            u = np.empty(n)
            u[bouts.order] = linear_scan(phi, z)
            out += u
        return out

    def cov_matvec(self, bouts: Bouts, indep_var_g2: np.ndarray, y: np.ndarray) -> np.ndarray:
        """``Sigma @ y`` for the residual covariance of the model.

        Parameters
        ----------
        bouts : Bouts
        indep_var_g2 : (n,) each window's independent variance (g²): its measured noise
            ``s_i^2`` plus ``sigma_white^2``; Sigma's diagonal is this plus
            ``sigma_bout^2 + sigma_ar^2``
        y : (n,) or (n, m), input order

        Returns
        -------
        Sigma @ y, same shape as ``y``
        """
        y = np.asarray(y, float)
        col = (lambda v: v) if y.ndim == 1 else (lambda v: v[:, None])
        out = col(np.asarray(indep_var_g2, float)) * y
        if self.sigma_bout_g > 0:
            sums = sum_by_group(bouts.label, y, bouts.n_bouts)
            out = out + self.sigma_bout_g**2 * sums[bouts.label]
        if self.sigma_ar_g > 0:
            phi = self._phi(bouts)
            ys = y[bouts.order]
            fwd = linear_scan(phi, ys)
            nxt = np.r_[phi[1:], 0.0]  # coefficient linking window i to i+1
            bwd = linear_scan(nxt[::-1], ys[::-1])[::-1]
            ry = np.empty_like(ys)
            ry[bouts.order] = fwd + bwd - ys
            out = out + self.sigma_ar_g**2 * ry
        return out

    def whitener(self, bouts: Bouts, indep_var_g2: np.ndarray, max_block: int = WHITEN_MAX_BLOCK):
        """``W`` with ``W Sigma W' = I``: a function ``y (n,) or (n, m) -> W y`` (input order).

        ``Sigma`` is block-diagonal by bout: ``diag(indep_var_g2) + sigma_bout^2 11' +
        sigma_ar^2 exp(-|t_i - t_j| / tau)``. Each bout's block is factored (Cholesky,
        ``Sigma_k = L_k L_k'``) and ``W_k = L_k^-1``, batched over the bouts of one size. A
        bout longer than ``max_block`` windows is whitened in consecutive pieces of at most
        that many, as if they were separate bouts (the shared error then counts once per
        piece: conservative for differences between pieces, and it bounds the memory at
        ``n * max_block`` values).

        Parameters
        ----------
        bouts : Bouts
        indep_var_g2 : (n,) each window's independent variance (g²): measured noise plus
            ``sigma_white^2``
        """
        indep = np.asarray(indep_var_g2, float)
        lab = bouts.label_sorted
        order = bouts.order
        n = len(order)
        start = np.r_[True, lab[1:] != lab[:-1]] if n else np.zeros(0, bool)
        pos = np.arange(n) - np.maximum.accumulate(np.where(start, np.arange(n), 0))
        piece = np.cumsum(start | (pos % max_block == 0)) - 1  # pieces of at most max_block, time order
        sizes = np.bincount(piece) if n else np.zeros(0, int)
        first = np.r_[0, np.cumsum(sizes)[:-1]].astype(int)
        ar = self.sigma_ar_g > 0 and np.isfinite(self.tau_s) and self.tau_s > 0
        groups = []
        for m in np.unique(sizes).tolist():
            idx = order[first[sizes == m][:, None] + np.arange(m)]  # (k, m) input-order indices, time order
            cov = np.zeros((len(idx), m, m)) + self.sigma_bout_g**2
            if ar:
                t = bouts.t_sorted[first[sizes == m][:, None] + np.arange(m)]
                cov += self.sigma_ar_g**2 * np.exp(-np.abs(t[:, :, None] - t[:, None, :]) / self.tau_s)
            cov[:, np.arange(m), np.arange(m)] += indep[idx]
            groups.append((idx, np.linalg.inv(np.linalg.cholesky(cov))))

        def apply(y: np.ndarray) -> np.ndarray:
            y = np.asarray(y, float)
            out = np.empty_like(y)
            for idx, winv in groups:
                out[idx] = winv @ y[idx] if y.ndim > 1 else (winv @ y[idx][..., None])[..., 0]
            return out

        return apply

    def to_report(self) -> dict:
        """JSON summary in mg and s."""

        def mg(x):
            return None if x is None or not np.isfinite(x) else float(x) * 1e3

        def num(x):
            return None if x is None or not np.isfinite(x) else float(x)

        total = self.noise_var_g2 + self.sigma_white_g**2 + self.correlated_var_g2  # the model's variance
        std = {}
        for k, v in self.std.items():
            if k.endswith("_g"):
                std[k[:-2] + "_mg"] = mg(v)
            elif k.endswith("_g2"):
                std[k[:-3] + "_mg2"] = v * 1e6
            else:
                std[k] = [num(x) for x in v] if isinstance(v, list) else num(v)
        out = {
            "model": "bout + AR(1) within bout + independent excess, on top of each window's measured noise",
            "estimated": self.estimated,
            "sigma_bout_mg": mg(self.sigma_bout_g),
            "sigma_ar_mg": mg(self.sigma_ar_g),
            "tau_s": num(self.tau_s),
            "sigma_white_mg": mg(self.sigma_white_g),
            "correlated_var_mg2": self.correlated_var_g2 * 1e6,
            "measured_noise_mg": mg(np.sqrt(self.noise_var_g2)),
            "excess_var_mg2": self.excess_var_g2 * 1e6,
            "correlated_share": float(self.correlated_var_g2 / total) if total > 0 else 0.0,
            "n_bouts": self.n_bouts,
            "n_multi_window_bouts": self.n_multi_bouts,
            "n_windows_in_multi_window_bouts": self.n_windows_in_multi,
            "n_pairs": self.n_pairs,
            "max_lag_s": self.max_lag_s,
            "independence_test": {"chi2": num(self.independence_chi2), "dof": self.independence_dof,
                                  "p": num(self.independence_p), "alpha": INDEPENDENCE_ALPHA},
            "std": std,
        }
        if self.unrestricted:
            out["unrestricted"] = {k[:-2] + "_mg" if k.endswith("_g") else k: (mg(v) if k.endswith("_g") else num(v))
                                   for k, v in self.unrestricted.items()}
        if self.why:
            out["why"] = self.why
        if self.lags:
            out["lags"] = {"dt_s": self.lags["dt_s"], "n_pairs": self.lags["n_pairs"],
                           "measured_mg2": [x * 1e6 for x in self.lags["measured_g2"]],
                           "model_mg2": [x * 1e6 for x in self.lags["model_g2"]]}
        return out


# ----------------------------------------------------------------------------- estimation


def _lag_moments(r: np.ndarray, s2: np.ndarray, bouts: Bouts, max_lag_s: float, max_lags: int = 5000):
    """Per-bout sums of the excess semivariance ``((r_i - r_j)^2 - s_i^2 - s_j^2) / 2`` over
    window pairs of one bout, binned by lag (12 log-spaced bins up to ``max_lag_s``).

    Returns None without pairs, else (sums (n_bouts, B), counts (n_bouts, B), dt_mean (B,) s).
    """
    rs, ss = r[bouts.order], s2[bouts.order]
    ts = bouts.t_sorted
    lab = bouts.label_sorted
    lab_l, val_l, dt_l = [], [], []
    for k in range(1, min(len(rs), max_lags + 1)):  # lags in windows, each step vectorised over windows
        dt = ts[k:] - ts[:-k]
        ok = (lab[k:] == lab[:-k]) & (dt <= max_lag_s)
        if not ok.any():
            break  # lags only grow with k
        lab_l.append(lab[k:][ok])
        val_l.append((0.5 * ((rs[k:] - rs[:-k]) ** 2 - ss[k:] - ss[:-k]))[ok])
        dt_l.append(dt[ok])
    if not dt_l:
        return None
    lab_p, val, dt = np.concatenate(lab_l), np.concatenate(val_l), np.concatenate(dt_l)
    pos = dt[dt > 0]
    lo = max(float(pos.min()) if len(pos) else 1.0, 1e-3)
    edges = np.geomspace(lo * 0.999, max(float(dt.max()), lo) * 1.001, 13)
    nb = len(edges) - 1
    b = np.clip(np.searchsorted(edges, dt, side="right") - 1, 0, nb - 1)
    flat = lab_p * nb + b
    sums = np.bincount(flat, val, minlength=bouts.n_bouts * nb).reshape(bouts.n_bouts, nb)
    counts = np.bincount(flat, minlength=bouts.n_bouts * nb).reshape(bouts.n_bouts, nb).astype(float)
    cnt = np.bincount(b, minlength=nb)
    dt_mean = np.where(cnt > 0, np.bincount(b, dt, minlength=nb) / np.maximum(cnt, 1), np.sqrt(edges[:-1] * edges[1:]))
    return sums, counts, dt_mean


def _fit_variogram(gbar: np.ndarray, w: np.ndarray, dt: np.ndarray, c0: np.ndarray, taus: np.ndarray):
    """Weighted NNLS of ``gamma(dt) = beta1 + beta2 (1 - exp(-dt/tau))`` with
    ``beta1 + beta2 <= c0``, best ``tau`` on a grid; vectorised over replicates.

    Parameters
    ----------
    gbar, w : (R, B) binned excess semivariance (g²) and weights (pairs) of R replicates
    dt : (B,) bin lags, s
    c0 : (R,) excess variance (g²), the bound (clipped at 0)
    taus : (T,) grid of tau, s

    Returns
    -------
    beta1 (white, g²), beta2 (AR, g²), tau (s; nan where beta2 = 0): each (R,)
    """
    c0 = np.maximum(c0, 0.0)[:, None]  # (R, 1)
    x = 1.0 - np.exp(-dt[None, :] / taus[:, None])  # (T, B)
    w3, y3 = w[:, None, :], gbar[:, None, :]  # (R, 1, B)
    shape = (w.shape[0], len(taus))
    sw = np.broadcast_to(w3.sum(-1), shape)
    sy = np.broadcast_to((w3 * y3).sum(-1), shape)
    syy = np.broadcast_to((w3 * y3 * y3).sum(-1), shape)
    sx = (w3 * x).sum(-1)
    sxx = (w3 * x * x).sum(-1)
    sxy = (w3 * x * y3).sum(-1)  # all (R, T)

    def sse(b1, b2):
        return syy - 2 * b1 * sy - 2 * b2 * sxy + b1 * b1 * sw + 2 * b1 * b2 * sx + b2 * b2 * sxx

    zero = np.zeros(shape)
    with np.errstate(divide="ignore", invalid="ignore"):
        # the constrained optimum lies in the interior or on an edge of the feasible triangle:
        # candidates in order of simplicity (ties keep the simpler one)
        cands = [(zero, zero),
                 (np.clip(np.where(sw > 0, sy / sw, 0.0), 0, c0), zero),  # white only
                 (zero, np.clip(np.where(sxx > 0, sxy / sxx, 0.0), 0, c0))]  # AR only
        # edge beta1 + beta2 = c0: y - c0 = beta2 (x - 1)
        num = sxy - sy - c0 * (sx - sw)
        den = sxx - 2 * sx + sw
        b2 = np.clip(np.where(den > 1e-12 * np.maximum(sw, 1e-300), num / den, 0.0), 0, c0)
        cands.append((c0 - b2, b2))
        det = sw * sxx - sx * sx
        ok = det > 1e-9 * np.maximum(sw * sxx, 1e-300)
        cands.append((np.where(ok, (sxx * sy - sx * sxy) / det, -1.0), np.where(ok, (sw * sxy - sx * sy) / det, -1.0)))
    best = np.full(shape, np.inf)
    b1b, b2b = zero.copy(), zero.copy()
    for b1, b2 in cands:
        b1, b2 = np.broadcast_to(b1, shape), np.broadcast_to(b2, shape)
        feas = (b1 >= 0) & (b2 >= 0) & (b1 + b2 <= c0 * (1 + 1e-12) + 1e-300)
        e = np.where(feas, sse(b1, b2), np.inf)
        with np.errstate(invalid="ignore"):
            better = e < np.where(np.isfinite(best), best - 1e-12 * np.abs(best), np.inf)
        best = np.where(better, e, best)
        b1b, b2b = np.where(better, b1, b1b), np.where(better, b2, b2b)
    k = np.argmin(best, axis=1)
    rows = np.arange(len(k))
    b1, b2 = b1b[rows, k], b2b[rows, k]
    return b1, b2, np.where(b2 > 0, taus[k], np.nan)


def _projection_deltas(q: np.ndarray, sigma_g: np.ndarray, s2: np.ndarray, bouts: Bouts,
                       ar_model: BoutNoise) -> dict[str, float]:
    """``delta_M = 2 tr(P M) - tr(P M P')`` (same units as ``M``'s scale: ``S`` in g², the
    others per unit variance) for the weighted projector ``P = D q q' D^-1`` (``D = diag(sigma_g)``)
    and ``M`` = ``S`` (diag of the measured noise ``s2``), ``Z`` (bout indicator ``Z Z'``),
    ``R`` (the AR(1) correlation of ``ar_model``) and ``I``."""
    dq = sigma_g[:, None] * q
    diq = q / sigma_g[:, None]
    gram = dq.T @ dq

    def delta(apply):
        return float(2.0 * np.sum(diq * apply(dq)) - np.sum((diq.T @ apply(diq)) * gram))

    def bout_sums(x):
        sums = sum_by_group(bouts.label, x, bouts.n_bouts)
        return sums[bouts.label]

    out = {"S": delta(lambda x: s2[:, None] * x), "Z": delta(bout_sums), "I": delta(lambda x: x), "R": 0.0}
    if ar_model.sigma_ar_g > 0:
        unit = BoutNoise(sigma_ar_g=1.0, tau_s=ar_model.tau_s)
        out["R"] = delta(lambda x: unit.cov_matvec(bouts, np.zeros(len(x)), x))
    return out


def estimate_bout_noise(
    res_g: np.ndarray,
    noise_g: np.ndarray,
    bouts: Bouts,
    max_lag_s: float = 900.0,
    n_boot: int = 200,
    seed: int = 0,
    projection: tuple[np.ndarray, np.ndarray] | None = None,
) -> BoutNoise:
    """Estimate the correlated-noise model from the base fit's residuals (method of moments).

    * ``C0 = mean(r^2 - s^2)`` over all windows: the excess variance
      ``sigma_bout^2 + sigma_ar^2 + sigma_white^2``;
    * the excess semivariance of window pairs of one bout, binned by lag ``dt`` (s),
      ``mean((r_i - r_j)^2 - s_i^2 - s_j^2) / 2 = sigma_white^2 + sigma_ar^2 (1 - exp(-dt/tau))``:
      differences within a bout cancel the bout's shared error, so the AR(1) and white
      parts are estimated from within-bout changes only (pair-weighted NNLS per ``tau`` on
      a grid up to twice the longest lag, best ``tau`` kept, subject to
      ``sigma_white^2 + sigma_ar^2 <= C0``);
    * ``sigma_bout^2 = C0 - sigma_white^2 - sigma_ar^2``, corrected for what the fit took:
      residuals projected off ``k`` columns keep ``E[r'r] = sum_M theta_M (tr M - delta_M)``
      with ``delta_M = 2 tr(P M) - tr(P M P')`` for each covariance term ``M`` (``P`` the
      weighted projector). Columns that hardly vary within a bout remove about ``k / K``
      of the bout variance over ``K`` bouts (10 % with 21 columns and 200 bouts), which the
      correction puts back.

    An AR(1) whose ``tau`` exceeds the bouts' durations cannot be told from a bout error:
    the grid stops at twice the longest lag, and a flat variogram gives ``sigma_ar = 0``.

    The correlated part is kept only when independence within bouts is rejected: with
    ``v_i = s_i^2 + C0`` each window's variance under independence, the bout sums
    ``z_k = sum_i r_i / sqrt(sum_i v_i)`` of the bouts of two windows or more give
    ``sum z_k^2 ~ chi2(K)``; at ``p >= INDEPENDENCE_ALPHA`` the model is independent noise
    (``sigma_white^2 = C0``) and the moment estimates are kept as ``unrestricted``.

    Parameters
    ----------
    res_g : (n,) norm residuals of the base fit, g (input order)
    noise_g : (n,) each window's measured noise sd on the norm (no floor), g
    bouts : Bouts (from :func:`find_bouts`)
    max_lag_s : longest lag between two windows of a bout used, s
    n_boot : bootstrap replicates over bouts for the sds (0: none)
    seed : seed of the bootstrap
    projection : ``(q, sigma_g)`` when ``res_g`` are residuals projected off some columns:
        ``q`` (n, k) an orthonormal basis of the columns whitened by ``sigma_g`` (n,) (g),
        the weights of the projection. None: no correction.

    Returns
    -------
    BoutNoise
    """
    r = np.asarray(res_g, float)
    s2 = np.asarray(noise_g, float) ** 2
    sizes = bouts.sizes
    excess = np.bincount(bouts.label, r * r - s2, minlength=bouts.n_bouts)
    nwin = sizes.astype(float)
    c0 = float(excess.sum() / nwin.sum())
    out = BoutNoise(excess_var_g2=c0, noise_var_g2=float(np.mean(s2)), n_bouts=bouts.n_bouts,
                    n_multi_bouts=int(np.sum(sizes >= 2)), n_windows_in_multi=int(np.sum(sizes[sizes >= 2])),
                    max_lag_s=float(max_lag_s))
    out.sigma_white_g = float(np.sqrt(max(c0, 0.0)))
    mom = _lag_moments(r, s2, bouts, max_lag_s)
    n_pairs = 0 if mom is None else int(mom[1].sum())
    out.n_pairs = n_pairs
    if mom is None or n_pairs < MIN_PAIRS or out.n_multi_bouts < MIN_MULTI_BOUTS:
        out.why = (f"{n_pairs} window pairs in {out.n_multi_bouts} bouts of two windows or more "
                   f"(>= {MIN_PAIRS} pairs in >= {MIN_MULTI_BOUTS} bouts needed): independent noise")
        return out
    sums, counts, dt_bin = mom
    npair_bin = counts.sum(0)
    keep = (npair_bin > 0) & (dt_bin > 0)
    if not keep.any():  # every pair at one time (a pose table without times): nothing to fit a lag to
        out.why = "every window pair at the same time: no lag to estimate a correlation over; independent noise"
        return out
    taus = np.geomspace(max(dt_bin[keep].min(), 1e-3) / 3.0, 2.0 * dt_bin[keep].max(), 40)

    def fit(weights):  # weights: (R, n_bouts) -> white, ar, tau, C0, windows (each (R,))
        nw = weights @ nwin
        c0r = (weights @ excess) / np.maximum(nw, 1e-300)
        cnt = weights @ counts
        gbar = np.where(cnt > 0, (weights @ sums) / np.maximum(cnt, 1e-300), 0.0)
        white, ar, tau = _fit_variogram(gbar, cnt, dt_bin, c0r, taus)
        return white, ar, tau, c0r, nw

    def bout_var(c0r, white, ar, nw, d):  # the bout part: the rest of C0, corrected for the projection
        num = nw * c0r + d["S"] - ar * (nw - d["R"]) - white * (nw - d["I"])
        return np.maximum(num / np.maximum(nw - d["Z"], 1.0), 0.0)

    white, ar, tau, c0r, nw = fit(np.ones((1, bouts.n_bouts)))
    deltas = {"S": 0.0, "Z": 0.0, "R": 0.0, "I": 0.0}
    if projection is not None:
        ar_model = BoutNoise(sigma_ar_g=float(np.sqrt(ar[0])), tau_s=float(tau[0]))
        deltas = _projection_deltas(projection[0], projection[1], s2, bouts, ar_model)
    out.projection_deltas = deltas
    bout = bout_var(c0r, white, ar, nw, deltas)
    out.sigma_bout_g = float(np.sqrt(bout[0]))
    out.sigma_ar_g = float(np.sqrt(ar[0]))
    out.tau_s = float(tau[0])
    out.sigma_white_g = float(np.sqrt(white[0]))
    out.estimated = True
    # test of independence within bouts (bout sums of the residuals)
    multi = sizes >= 2
    v = s2 + max(c0, 0.0)
    zsum = np.bincount(bouts.label, r, minlength=bouts.n_bouts)[multi]
    vsum = np.bincount(bouts.label, v, minlength=bouts.n_bouts)[multi]
    out.independence_chi2 = float(np.sum(zsum**2 / np.maximum(vsum, 1e-300)))
    out.independence_dof = int(multi.sum())
    out.independence_p = float(stats.chi2.sf(out.independence_chi2, out.independence_dof))
    gbar_all = sums.sum(0) / np.maximum(npair_bin, 1)
    model = white[0] + (ar[0] * (1 - np.exp(-dt_bin / tau[0])) if ar[0] > 0 else 0.0)
    out.lags = {"dt_s": dt_bin[keep].tolist(), "n_pairs": npair_bin[keep].astype(int).tolist(),
                "measured_g2": gbar_all[keep].tolist(), "model_g2": np.broadcast_to(model, dt_bin.shape)[keep].tolist()}
    if n_boot > 1:
        rng = np.random.default_rng(seed)
        wts = rng.multinomial(bouts.n_bouts, np.full(bouts.n_bouts, 1.0 / bouts.n_bouts), size=n_boot).astype(float)
        bw, ba, btau, bc0, bnw = fit(wts)
        bb = bout_var(bc0, bw, ba, bnw, deltas)
        out.std = {"sigma_bout_g": float(np.std(np.sqrt(bb), ddof=1)),
                   "sigma_ar_g": float(np.std(np.sqrt(ba), ddof=1)),
                   "sigma_white_g": float(np.std(np.sqrt(bw), ddof=1)),
                   "correlated_var_g2": float(np.std(bb + ba, ddof=1))}
        fin = btau[np.isfinite(btau)]
        if len(fin) >= 2:
            out.std["tau_s_16_84"] = [float(np.percentile(fin, 16)), float(np.percentile(fin, 84))]
            out.std["tau_share_with_ar"] = float(len(fin) / n_boot)
    if not out.independence_p < INDEPENDENCE_ALPHA:
        out.unrestricted = {"sigma_bout_g": out.sigma_bout_g, "sigma_ar_g": out.sigma_ar_g, "tau_s": out.tau_s,
                            "sigma_white_g": out.sigma_white_g}
        out.sigma_bout_g = out.sigma_ar_g = 0.0
        out.tau_s = float("nan")
        out.sigma_white_g = float(np.sqrt(max(c0, 0.0)))
        out.std = {}
        out.why = (f"independence within bouts not rejected (chi2 {out.independence_chi2:.1f} for "
                   f"{out.independence_dof} bouts, p={out.independence_p:.2g} >= {INDEPENDENCE_ALPHA:g}): independent noise")
    return out
