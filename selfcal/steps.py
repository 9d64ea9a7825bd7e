"""A bias step (the offset jumps at one time: a shock, a drop, a battery change): where.

The step's time is not a parameter of the fit but a constant of the model
(``ErrorModel(..., t_step_s=...)``, effect ``bias_step``); it is found by a scan. At a
handful of candidate times, evenly spaced in the order of the poses, the score statistic
of a step there is computed at the fit without a step: the offset's Jacobian columns on
the poses from that time on, whitened and with the fitted model's columns projected out,
give the linearised chi2 drop of adding the step. The best time is then fitted and
tested by the caller (``selfcal diagnose`` with an F-test, the online calibrator with a
Wald test and held-out cells), its level divided by the number of times scanned.
"""

from __future__ import annotations

import numpy as np


def step_times(t_s: np.ndarray, cfg) -> np.ndarray:
    """Candidate times (s) of a bias step: ``cfg.step_times`` cuts evenly spaced in pose
    order from ``cfg.step_min_side`` to ``1 - step_min_side`` of the poses, each half way
    between two consecutive distinct times (sorted, unique, (k,) with k <= step_times).
    ``cfg``: :class:`DiagnoseConfig` or :class:`selfcal.selection.SelectionConfig`."""
    ts = np.sort(np.asarray(t_s, dtype=float))
    n = len(ts)
    if n < 2:
        return np.zeros(0)
    frac = np.linspace(cfg.step_min_side, 1.0 - cfg.step_min_side, cfg.step_times)
    idx = np.clip(np.rint(frac * n).astype(int), 1, n - 1)
    cuts = 0.5 * (ts[idx - 1] + ts[idx])
    return np.unique(cuts[ts[idx - 1] < ts[idx]])


def whitened_basis(fit, u: np.ndarray, temp_c: np.ndarray | None, t_s: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """``(sigma (n,) g, q (n, p))``: the fit's residual sd and an orthonormal basis of its
    whitened Jacobian columns (the directions the fitted model already explains)."""
    sigma = fit.sigma_g
    jb = fit.model.residual_jac(fit.theta_u, u, temp_c, t_s)[1] / sigma[:, None]
    q, _ = np.linalg.qr(jb)
    return sigma, q


def scan_step(base_fit, u: np.ndarray, temp_c: np.ndarray | None, t_s: np.ndarray, sigma: np.ndarray, q: np.ndarray,
              times: np.ndarray) -> tuple[float, np.ndarray]:
    """The candidate step time (s) whose step explains the base fit's residuals best, and
    the score statistic of every candidate, (k,).

    At the base fit a bias step at ``tau`` has the Jacobian columns of the offset on the
    poses from ``tau`` on; whitened and with the base model's columns projected out (``q``),
    their score statistic ``z' (C'C)^-1 z`` (``z = C' r``, ``r`` the whitened residuals) is
    the linearised chi2 drop of adding that step. ``u`` (n, 3) normalised means, ``temp_c``
    and ``t_s`` (n,) the poses the base fit was made on; ``sigma`` (n,) g its residual sd,
    ``q`` (n, k) its whitened Jacobian's orthonormal columns.
    """
    jb = base_fit.model.residual_jac(base_fit.theta_u, u, temp_c, t_s)[1][:, 0:3] / sigma[:, None]
    rw = base_fit.residuals_g / sigma
    score = np.zeros(len(times))
    for k, tau in enumerate(times.tolist()):  # a handful of candidate times: one (n, 3) product each
        try:
            score[k] = jump_score(jb, q, rw, t_s >= tau)
        except np.linalg.LinAlgError:
            score[k] = 0.0
    return float(times[int(np.argmax(score))]), score


def jump_score(jw_offset: np.ndarray, q: np.ndarray, rw: np.ndarray, after: np.ndarray) -> float:
    """The score statistic ``z' (C'C)^-1 z`` (linearised chi2 drop, 3 dof) of an offset jump
    on the poses ``after`` (n,) bool: ``C`` is the whitened offset Jacobian ``jw_offset``
    (n, 3) on those poses with the fitted model's columns ``q`` (n, k, orthonormal)
    projected out, ``z = C' rw`` with ``rw`` (n,) the whitened residuals. Raises
    LinAlgError when ``C'C`` is singular."""
    cc, z = _jump_system(jw_offset, q, rw, after)
    return float(z @ np.linalg.solve(cc, z))


def jump_fit(jw_offset: np.ndarray, q: np.ndarray, rw: np.ndarray, after: np.ndarray) -> tuple[float, np.ndarray, np.ndarray]:
    """:func:`jump_score` with the jump it scores: ``(score, jump (3,), cov (3, 3))``, the
    least-squares offset jump ``(C'C)^-1 z`` on the poses ``after`` (the offset's units,
    normalised ~g) and its covariance ``(C'C)^-1``. Raises LinAlgError when ``C'C`` is
    singular."""
    cc, z = _jump_system(jw_offset, q, rw, after)
    jump = np.linalg.solve(cc, z)
    return float(z @ jump), jump, np.linalg.inv(cc)


def latest_jump(jw_offset: np.ndarray, q: np.ndarray, rw: np.ndarray, t_s: np.ndarray, recent: np.ndarray,
                n_times: int = 24, min_after: int = 3) -> tuple[float, np.ndarray, np.ndarray]:
    """Where among the poses ``recent`` (n,) bool an offset jump explains the residuals
    best, and its size: ``(tau (s), jump (3,), cov (3, 3))`` as :func:`jump_fit` gives them
    for the poses of ``recent`` from ``tau`` on (``t_s`` (n,) s; ``tau`` is ``-inf`` when
    all of them are best). The cuts are every recent pose's time up to ``n_times`` of
    them, evenly in time order, each leaving at least ``min_after`` poses after it.
    Estimation only (the best of several cuts is no test): a jump that happened after
    most of the recent poses is not diluted over all of them. Raises LinAlgError when
    no cut gives a regular ``C'C``."""
    ts = np.unique(t_s[recent])
    cuts = [-np.inf]
    if len(ts) > min_after:
        idx = np.unique(np.linspace(1, len(ts) - min_after, min(n_times, len(ts) - min_after)).astype(int))
        cuts += (0.5 * (ts[idx - 1] + ts[idx])).tolist()
    best = None
    for tau in cuts:  # a few dozen cuts: one (n, 3) product each, the best one's fit kept
        try:
            score, jump, cov = jump_fit(jw_offset, q, rw, recent & (t_s > tau))
        except np.linalg.LinAlgError:
            continue
        if best is None or score > best[0]:
            best = (score, tau, jump, cov)
    if best is None:
        raise np.linalg.LinAlgError("no cut of the recent poses gives a regular jump system")
    _, tau, jump, cov = best
    return float(tau), jump, cov


def _jump_system(jw_offset: np.ndarray, q: np.ndarray, rw: np.ndarray, after: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """``(C'C (3, 3), z = C' rw (3,))`` of :func:`jump_score`."""
    c = jw_offset * after[:, None]
    c = c - q @ (q.T @ c)
    return c.T @ c, c.T @ rw


def refine_time(base_fit, u: np.ndarray, temp_c: np.ndarray | None, t_s: np.ndarray, sigma: np.ndarray,
                q: np.ndarray, times: np.ndarray, tau: float, max_times: int = 200) -> float:
    """A step time ``tau`` (one of ``times``) refined between its neighbours in ``times``:
    the best by the same score at every gap between two poses there (at most
    ``max_times``, evenly picked). Estimation only: a test of the step keeps ``tau`` and
    its count of looks."""
    k = int(np.searchsorted(times, tau))
    lo = times[k - 1] if k > 0 else -np.inf
    hi = times[k + 1] if k + 1 < len(times) else np.inf
    ts = np.unique(t_s)
    mids = 0.5 * (ts[1:] + ts[:-1])
    fine = mids[(mids > lo) & (mids < hi)]
    if len(fine) > max_times:
        fine = fine[np.linspace(0, len(fine) - 1, max_times).astype(int)]
    if len(fine) == 0:
        return float(tau)
    return scan_step(base_fit, u, temp_c, t_s, sigma, q, fine)[0]
