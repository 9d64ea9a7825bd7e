"""``da_lm``: Dragonfly Algorithm + LM (``da-lm-calibration.txt``, Qiao et al. 2021).

The text we have lost its equations and tables (they were images). What is stated:
DA global stage on an ellipsoid fitness ``||V eta - A||``, ``G = K^-T K^-1 = s^T s``,
bias from the quadric centre, bias then fixed so 6 parameters remain (scale
``fx, fy, fz`` and non-orthogonality ``ex, ey, ez``, ``K = S D``); LM with
``lambda0 = trace(J^T J)/N``, stop when ``||J^T F|| <= 1e-4``, gain ratio
``alpha = Ared/Pred``, accept only if ``alpha > 0``, a lambda update using
``mu = max(0.4, min(alpha, 10))``, DA 100 iterations, LM at most 500.
What had to be reconstructed is listed in :func:`da_lm`'s Notes.
"""

from __future__ import annotations

import math

import numpy as np

from selfcal.errors import InputError

from ._common import BaselineResult, check_poses, prescale_poses
from .ellipsoid import quadric_to_calibration

__all__ = ["da_lm", "dragonfly"]

#: Search box of the DA over the quadric coefficients (a1..a9), pre-scaled frame.
#: Our choice (the paper's Table 2 is missing): |bias| <~ 0.25 g, scale within ~25 %.
DA_LB = np.array([0.6, 0.6, 0.6, -0.3, -0.3, -0.3, -0.6, -0.6, -0.6])
DA_UB = np.array([1.6, 1.6, 1.6, 0.3, 0.3, 0.3, 0.6, 0.6, 0.6])


def _levy(dim: int, rng: np.random.Generator) -> np.ndarray:
    beta = 1.5
    sigma = (math.gamma(1 + beta) * math.sin(math.pi * beta / 2)
             / (math.gamma((1 + beta) / 2) * beta * 2 ** ((beta - 1) / 2))) ** (1 / beta)
    r1 = rng.random(dim)
    r2 = rng.random(dim)
    return 0.01 * r1 * sigma / np.abs(r2) ** (1 / beta)


def dragonfly(fobj, lb: np.ndarray, ub: np.ndarray, n_agents: int, max_iter: int,
              rng: np.random.Generator) -> tuple[np.ndarray, float, np.ndarray]:
    """Dragonfly Algorithm (Mirjalili 2016), after the author's reference ``DA.m``.

    Parameters
    ----------
    fobj : callable
        ``fobj(X (n_agents, dim)) -> (n_agents,)`` fitness, lower is better (vectorised).
    lb, ub : ndarray, shape (dim,)
        Search box.
    n_agents, max_iter : int
    rng : numpy.random.Generator

    Returns
    -------
    best_pos : ndarray, shape (dim,)
    best_score : float
    curve : ndarray, shape (max_iter,)
        Best fitness after each iteration.

    Notes
    -----
    Kept from ``DA.m``: per-dimension neighbourhood test ``|x_i - x_j| <= r`` (all
    dims), radius ``r = (ub-lb)/4 + (ub-lb)*2*iter/Max``, inertia ``w`` 0.9 -> 0.4,
    ``my_c`` 0.1 -> 0 at half time, random s/a/c/f weights, Levy flight for agents
    without neighbours, step clamp ``Delta_max = (ub-lb)/10``, the enemy term
    ``Enemy_pos + X`` (sic) and sequential (in-place) agent updates.
    """
    dim = lb.size
    delta_max = (ub - lb) / 10.0
    food_fit, food_pos = np.inf, np.zeros(dim)
    enemy_fit, enemy_pos = -np.inf, np.zeros(dim)
    X = rng.random((n_agents, dim)) * (ub - lb) + lb
    DX = rng.random((n_agents, dim)) * (ub - lb) + lb
    curve = np.empty(max_iter)
    for it in range(1, max_iter + 1):
        r = (ub - lb) / 4 + (ub - lb) * (it / max_iter) * 2
        w = 0.9 - it * ((0.9 - 0.4) / max_iter)
        my_c = max(0.1 - it * ((0.1 - 0) / (max_iter / 2)), 0.0)
        s = 2 * rng.random() * my_c
        a = 2 * rng.random() * my_c
        c = 2 * rng.random() * my_c
        f = 2 * rng.random()
        e = my_c
        fit = fobj(X)
        for i in range(n_agents):  # sequential, as DA.m (food/enemy update order matters)
            if fit[i] < food_fit:
                food_fit, food_pos = fit[i], X[i].copy()
            if fit[i] > enemy_fit and np.all(X[i] < ub) and np.all(X[i] > lb):
                enemy_fit, enemy_pos = fit[i], X[i].copy()
        for i in range(n_agents):
            dist = np.abs(X - X[i])
            nb = np.all(dist <= r, axis=1) & np.all(dist != 0, axis=1)
            n_nb = int(nb.sum())
            if n_nb > 1:
                S = -np.sum(X[nb] - X[i], axis=0)
                A = DX[nb].mean(axis=0)
                C = X[nb].mean(axis=0) - X[i]
            else:
                S = np.zeros(dim)
                A = DX[i].copy()
                C = np.zeros(dim)
            d_food = np.abs(X[i] - food_pos)
            F = food_pos - X[i] if np.all(d_food <= r) else np.zeros(dim)
            d_enemy = np.abs(X[i] - enemy_pos)
            En = enemy_pos + X[i] if np.all(d_enemy <= r) else np.zeros(dim)
            over, under = X[i] > ub, X[i] < lb
            if over.any() or under.any():
                X[i] = np.where(over, lb, np.where(under, ub, X[i]))
                DX[i] = np.where(over | under, rng.random(dim), DX[i])
            if np.any(d_food > r):
                if n_nb > 1:
                    DX[i] = w * DX[i] + rng.random(dim) * A + rng.random(dim) * C + rng.random(dim) * S
                    DX[i] = np.clip(DX[i], -delta_max, delta_max)
                    X[i] = X[i] + DX[i]
                else:
                    X[i] = X[i] + _levy(dim, rng) * X[i]
                    DX[i] = 0.0
            else:
                DX[i] = (a * A + c * C + s * S + f * F + e * En) + w * DX[i]
                DX[i] = np.clip(DX[i], -delta_max, delta_max)
                X[i] = X[i] + DX[i]
            X[i] = np.clip(X[i], lb, ub)
        curve[it - 1] = food_fit
    return food_pos, float(food_fit), curve


def _k_from_theta(th):
    fx, fy, fz, ex, ey, ez = th
    S = np.array([[1.0, ex, ey], [0.0, 1.0, ez], [0.0, 0.0, 1.0]])
    return S, S * np.array([fx, fy, fz])[None, :]


def _resid_jac(th, w):
    """F_k = ||K^-1 w_k||^2 - 1 and dF/dtheta (n, 6); w = u - B."""
    S, K = _k_from_theta(th)
    Ki = np.linalg.inv(K)
    U = w @ Ki.T
    F = np.einsum("ij,ij->i", U, U) - 1.0
    Z = U @ Ki  # rows (K^-T U_k)^T
    fx, fy, fz = th[:3]
    J = np.empty((len(w), 6))
    for j in range(3):  # dK/df_j: column j = S[:, j]
        J[:, j] = -2.0 * (Z @ S[:, j]) * U[:, j]
    J[:, 3] = -2.0 * Z[:, 0] * fy * U[:, 1]  # ex at (0, 1)
    J[:, 4] = -2.0 * Z[:, 0] * fz * U[:, 2]  # ey at (0, 2)
    J[:, 5] = -2.0 * Z[:, 1] * fz * U[:, 2]  # ez at (1, 2)
    return F, J


def da_lm(
    mean,
    sd=None,
    n_samples=None,
    t_s=None,
    temp_c=None,
    *,
    rng: np.random.Generator | int | None = 0,
    n_agents: int = 40,
    da_iterations: int = 100,
    quick: bool = False,
    lm_max_iter: int = 500,
    eps: float = 1e-4,
    prescale: bool | str = "auto",
) -> BaselineResult:
    """DA-LM: Dragonfly global search on the quadric, bias fixed, LM on 6 parameters.

    Parameters
    ----------
    mean : array_like, shape (n, 3), raw unit
        Still-pose mean readings; at least 9 poses.
    sd, n_samples, t_s, temp_c : array_like, optional
        Accepted for the common interface and ignored.
    rng : numpy.random.Generator or int, default 0
        Seed of the DA; the result is reproducible for a given seed.
    n_agents : int, default 40
        DA population (the paper's value is in its missing Table 2; 40 is the
        default of Mirjalili's reference code).
    da_iterations : int, default 100
        DA iterations (paper, section 4.6).
    quick : bool, default False
        Use 20 DA iterations (for tests and quick benchmarks).
    lm_max_iter : int, default 500
        LM iteration limit (paper, section 4.6).
    eps : float, default 1e-4
        Stop when ``||J^T F|| <= eps`` (paper).
    prescale : {"auto", True, False}

    Returns
    -------
    BaselineResult
        ``matrix = K^-1`` (upper triangular), ``offset = B`` (from the DA quadric).
        ``extra``: ``eta`` (DA best), ``da_fitness``, ``da_curve``, ``theta0``/``theta``
        = ``(fx, fy, fz, ex, ey, ez)``, ``bias_da``, ``lambda_history``.

    Notes
    -----
    Reconstructed where the source text lost its equations:

    * fitness ``||V eta - 1||``: the paper's ``V = (x^2, y^2, z^2, xy, yz, zx, x, y, z)``,
      here in ``quadric9``'s column order ``[x^2, y^2, z^2, xy, xz, yz, x, y, z]``, and
      right-hand side
      ``A = ||U||^2 = 1`` (the text lists 9 columns of ``V`` but 10 names in ``eta``; a
      constant column with ``A = 1`` would admit the trivial solution, so it is
      dropped — the same normalisation as the insole paper's quadric);
    * search box :data:`DA_LB`/:data:`DA_UB` (Table 2 missing);
    * ``K = S D``, ``S = [[1, ex, ey], [0, 1, ez], [0, 0, 1]]``, ``D = diag(fx, fy, fz)``,
      initial value from the Cholesky factor of ``G`` (the paper's SVD square root
      ``s`` differs from it by a rotation, which the norm cannot see);
    * LM residual ``F_k = ||K^-1 (V_k - B)||^2 - 1`` (the squared form of eq. (2));
    * lambda update (eqs. 22-24 missing): on acceptance ``lambda /= mu`` with
      ``mu = max(0.4, min(alpha, 10))`` (gain below 0.4 raises lambda up to 2.5x, a
      good gain lowers it up to 10x); on rejection ``lambda *= q`` with ``q``
      doubling on consecutive rejections (starting at 2), reset on acceptance.
    """
    m, *_ = check_poses(mean, sd, n_samples, t_s, temp_c, min_poses=9, method="da_lm")
    gen = rng if isinstance(rng, np.random.Generator) else np.random.default_rng(rng)
    ps = prescale_poses(m, prescale)
    u = ps.forward(m)
    x, y, z = u.T
    V = np.column_stack([x * x, y * y, z * z, x * y, x * z, y * z, x, y, z])
    iters = 20 if quick else int(da_iterations)

    def fobj(P):
        return np.linalg.norm(V @ P.T - 1.0, axis=0)

    eta, da_fit, curve = dragonfly(fobj, DA_LB, DA_UB, int(n_agents), iters, gen)
    try:
        B, G, R = quadric_to_calibration(eta)
    except InputError as exc:
        raise InputError(f"da_lm: the DA quadric is not an ellipsoid ({exc}); try more DA iterations") from None
    K0 = np.linalg.inv(R)
    d0 = np.diag(K0).copy()
    S0 = K0 / d0[None, :]
    th = np.array([d0[0], d0[1], d0[2], S0[0, 1], S0[0, 2], S0[1, 2]])
    theta0 = th.copy()
    w = u - B
    F, J = _resid_jac(th, w)
    lam = np.trace(J.T @ J) / len(w)
    lam_hist = [lam]
    q = 2.0
    converged, msg, k = False, f"LM iteration limit ({lm_max_iter}) reached", 0
    n_rej = 0
    for k in range(1, lm_max_iter + 1):
        g = J.T @ F
        if np.linalg.norm(g) <= eps:
            converged, msg = True, f"||J^T F|| <= {eps:g}"
            k -= 1
            break
        d = -np.linalg.solve(J.T @ J + lam * np.eye(6), g)
        F_new, J_new = _resid_jac(th + d, w)
        ared = F @ F - F_new @ F_new
        pred = F @ F - (F + J @ d) @ (F + J @ d)
        alpha = ared / pred if pred > 0 else -1.0
        if alpha > 0:
            th, F, J = th + d, F_new, J_new
            mu = max(0.4, min(alpha, 10.0))
            lam = lam / mu
            q = 2.0
        else:
            lam = lam * q
            q *= 2.0
            n_rej += 1
        lam_hist.append(lam)
    _, K = _k_from_theta(th)
    matrix, offset = ps.back(np.linalg.inv(K), B)
    return BaselineResult(
        method="da_lm", matrix=matrix, offset=offset, n_iter=k, converged=converged,
        message=f"DA {iters} it x {n_agents} agents (fitness {da_fit:.3g}); LM: {msg}",
        extra=dict(eta=eta, da_fitness=da_fit, da_curve=curve, theta0=theta0, theta=th,
                   bias_da=B, lambda_history=np.array(lam_hist), n_rejected=n_rej,
                   prescale=dict(applied=ps.applied, centre=ps.centre, radius=ps.radius)),
    )
