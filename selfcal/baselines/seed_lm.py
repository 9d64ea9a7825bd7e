"""``seed_lm``: faithful port of the LM loop of ``lm-accelerometer-calibration.txt``.

The seed is MATLAB code (after Quan Quan, *Introduction to Multicopter Design and
Control*) for an MPU9250 at 100 Hz: 2000 samples, g = 9.8, ``N = 17``, ``lamda = 1000``.
This module reproduces it statement by statement, **defects included**, because it is
(1) the comparison row "seed" of the benchmark and (2) the baseline of the fit-speed
benchmark. It therefore keeps the seed's per-sample Python loops (``ComputeF`` /
``ComputeJacobi``); nothing here is meant to be fast or correct. For the corrected
algorithm see :func:`selfcal.baselines.lm_fixed`.
"""

from __future__ import annotations

import math

import numpy as np

from ._common import BaselineResult, check_poses, prescale_poses

__all__ = ["seed_lm"]


def _compute_f(a1, a2, a3, s1, s2, s3, b1, b2, b3, accx, accy, accz, g):
    """Seed ``ComputeF``: the *squared* residual ``V = (||T K (acc + b)|| - g)^2``."""
    T = np.array([[1.0, a3, -a2], [-a3, 1.0, a1], [a2, -a1, 1.0]])
    K = np.array([[s1, 0.0, 0.0], [0.0, s2, 0.0], [0.0, 0.0, s3]])
    B = np.array([b1, b2, b3])
    ACC = np.array([accx, accy, accz])
    F = T @ K @ (ACC + B)
    return (math.sqrt(F @ F) - g) ** 2


def _compute_jacobi(a1, a2, a3, s1, s2, s3, b1, b2, b3, acc, g, num, fix_bz_sign):
    """Seed ``ComputeJacobi``: rows ``r * dr/dTheta`` (not ``dV/dTheta = 2 r dr/dTheta``).

    Reproduces the seed's sign error in column 9 (``d/d bz``): the seed writes
    ``- hz * sz`` where the derivative has ``+ hz * sz``, unless ``fix_bz_sign``.
    """
    phi, theta, psi = a1, a2, a3
    sx, sy, sz = s1, s2, s3
    bx, by, bz = b1, b2, b3
    amx, amy, amz = acc[0], acc[1], acc[2]
    sgn9 = 1.0 if fix_bz_sign else -1.0
    J = np.zeros((num, 9))
    for k in range(num):
        ux, uy, uz = amx[k] + bx, amy[k] + by, amz[k] + bz
        hx = sx * ux + psi * sy * uy - theta * sz * uz
        hy = -psi * sx * ux + sy * uy + phi * sz * uz
        hz = theta * sx * ux - phi * sy * uy + sz * uz
        Fx = math.sqrt(hx**2 + hy**2 + hz**2) - g
        c = Fx / (Fx + g)
        J[k, 0] = (hy * sz * uz - hz * sy * uy) * c
        J[k, 1] = (-hx * sz * uz + hz * sx * ux) * c
        J[k, 2] = (hx * sy * uy - hy * sx * ux) * c
        J[k, 3] = (hx * ux - hy * psi * ux + hz * theta * ux) * c
        J[k, 4] = (hx * psi * uy + hy * uy - hz * phi * uy) * c
        J[k, 5] = (-hx * theta * uz + hy * phi * uz + hz * uz) * c
        J[k, 6] = (hx * sx - hy * psi * sx + hz * theta * sx) * c
        J[k, 7] = (hx * psi * sy + hy * sy - hz * phi * sy) * c
        J[k, 8] = (-hx * theta * sz + hy * phi * sz + sgn9 * hz * sz) * c
    return J


def seed_lm(
    mean,
    sd=None,
    n_samples=None,
    t_s=None,
    temp_c=None,
    *,
    g: float = 9.8,
    n_iterations: int = 17,
    lam0: float = 1000.0,
    prescale: bool | str = False,
    fix_bz_sign: bool = False,
) -> BaselineResult:
    """Seed LM calibration, ported as written (defects included).

    Model ``a = T K (raw + b)``, ``T = [[1, psi, -theta], [-psi, 1, phi], [theta, -phi, 1]]``,
    ``K = diag(sx, sy, sz)``, parameters ``Theta = (phi, theta, psi, sx, sy, sz, bx, by, bz)``
    started at ``(0, 0, 0, 1, 1, 1, 0, 0, 0)``.

    Parameters
    ----------
    mean : array_like, shape (n, 3), raw unit
        Still readings (the seed uses every sample of its recording; pose means work
        the same way). No weighting by ``n_samples``: the seed has none.
    sd, n_samples, t_s, temp_c : array_like, optional
        Accepted for the common interface and ignored.
    g : float, default 9.8
        Target norm **in the input unit**. The seed hard-codes ``g = 9.8`` (input in
        m/s^2); pass ``g=1.0`` for input in g. ``lam0`` is *not* rescaled with it (the
        seed's lambda is tied to m/s^2 magnitudes), so other units behave differently.
    n_iterations : int, default 17
        The seed's ``N``: the length of its parameter history. The loop runs
        ``for i = 2:N``, i.e. ``N - 1 = 16`` parameter updates.
    lam0 : float, default 1000
        Initial damping ``lamda``.
    prescale : {False, True, "auto"}, default False
        The seed does no normalisation, so counts (or any unit far from ``g``) need a
        pre-scaling by the caller. With ``True``/``"auto"`` the data are mapped to a
        sphere of radius ``g`` first (sphere fit, see ``prescale_poses``) — a
        convenience that is *not* in the seed.
    fix_bz_sign : bool, default False
        Repair the seed's sign error in the ``bz`` column of its Jacobian (for
        diagnosis only; the default reproduces the seed).

    Returns
    -------
    BaselineResult
        ``matrix = T K / g`` (so the calibrated norm is 1), ``offset = -b``.
        ``n_iter`` = number of updates (16 by default), ``converged`` is always False
        (the seed has no convergence test; its ``minvalue = 0.5`` is never used).
        ``extra``: ``theta`` (9,), ``cost_history`` (N,) sums of ``V`` per iterate,
        ``lambda_history`` (N,), ``n_cost_increases``, ``n_rejected`` (always 0),
        ``seed_N``.

    Notes
    -----
    Defects of the seed reproduced here (see ``docs/method.md`` section 1):

    * the vector fed to the update is ``V_k = r_k^2`` where ``r_k`` belongs;
    * the Jacobian rows are ``r_k dr_k/dTheta`` (the seed's ``*(Fx/(Fx+g))``), which is
      half the gradient of ``V_k``, and column 9 has a sign error on its ``hz sz``
      term (found while porting; not listed in method.md);
    * every step is accepted, even one that raised the cost; only ``lamda`` changes
      (``*0.9`` if the cost did not increase, ``*1.1`` if it did);
    * a fixed number of iterations from ``lamda = 1000`` and a fixed ``g``;
    * the three angles form a first-order *rotation*, unobservable from norms.

    The per-sample loops are deliberate: this is a faithful port and the speed
    baseline, so it runs at the seed's (interpreted, per-sample) cost.
    """
    m, *_ = check_poses(mean, sd, n_samples, t_s, temp_c, min_poses=1, method="seed_lm")
    ps = prescale_poses(m, prescale)
    data = ps.forward(m) * (g if ps.applied else 1.0)
    Acc = data.T.copy()  # (3, acqSize), like the seed
    acqSize = Acc.shape[1]
    N = int(n_iterations)
    a1 = np.zeros(N); a2 = np.zeros(N); a3 = np.zeros(N)  # noqa: E702
    s1 = np.ones(N); s2 = np.ones(N); s3 = np.ones(N)  # noqa: E702
    b1 = np.zeros(N); b2 = np.zeros(N); b3 = np.zeros(N)  # noqa: E702
    lamda = float(lam0)
    Fk = np.zeros(acqSize)
    Fk1 = np.zeros(acqSize)
    lam_hist = [lamda]
    cost0 = sum(_compute_f(0, 0, 0, 1, 1, 1, 0, 0, 0, *Acc[:, j], g) for j in range(acqSize))
    cost_hist = [cost0]
    n_up = 0
    for i in range(1, N):
        value_latest = 0.0
        value_new = 0.0
        for j in range(acqSize):
            Fk[j] = _compute_f(a1[i - 1], a2[i - 1], a3[i - 1], s1[i - 1], s2[i - 1], s3[i - 1],
                               b1[i - 1], b2[i - 1], b3[i - 1], Acc[0, j], Acc[1, j], Acc[2, j], g)
            value_latest += Fk[j]
        Jac = _compute_jacobi(a1[i - 1], a2[i - 1], a3[i - 1], s1[i - 1], s2[i - 1], s3[i - 1],
                              b1[i - 1], b2[i - 1], b3[i - 1], Acc, g, acqSize, fix_bz_sign)
        D = np.ones(9)
        X = np.array([a1[i - 1], a2[i - 1], a3[i - 1], s1[i - 1], s2[i - 1], s3[i - 1],
                      b1[i - 1], b2[i - 1], b3[i - 1]])
        X = X - np.linalg.inv(Jac.T @ Jac + lamda * np.diag(D)) @ Jac.T @ Fk
        a1[i], a2[i], a3[i], s1[i], s2[i], s3[i], b1[i], b2[i], b3[i] = X
        for k in range(acqSize):
            Fk1[k] = _compute_f(a1[i], a2[i], a3[i], s1[i], s2[i], s3[i], b1[i], b2[i], b3[i],
                                Acc[0, k], Acc[1, k], Acc[2, k], g)
            value_new += Fk1[k]
        if value_new <= value_latest:
            lamda = lamda * 0.9
        else:
            lamda = lamda * 1.1
        lam_hist.append(lamda)
        cost_hist.append(value_new)
        n_up += 1
    theta = np.array([a1[-1], a2[-1], a3[-1], s1[-1], s2[-1], s3[-1], b1[-1], b2[-1], b3[-1]])
    T = np.array([[1.0, theta[2], -theta[1]], [-theta[2], 1.0, theta[0]], [theta[1], -theta[0], 1.0]])
    M_u = T @ np.diag(theta[3:6]) / g
    o_u = -theta[6:9]
    if ps.applied:
        # data = g * (raw - c) / r  ->  raw-unit calibration
        M_u = M_u * g
        o_u = o_u / g
    matrix, offset = ps.back(M_u, o_u)
    n_incr = int(np.sum(np.diff(cost_hist) > 0))
    return BaselineResult(
        method="seed_lm",
        matrix=matrix,
        offset=offset,
        n_iter=n_up,
        converged=False,
        message=(f"seed loop finished: fixed N={N} ({n_up} updates, none rejected, "
                 f"{n_incr} raised the cost); the seed has no convergence test"),
        extra=dict(theta=theta, cost_history=np.array(cost_hist), lambda_history=np.array(lam_hist),
                   n_cost_increases=n_incr, n_rejected=0, seed_N=N, g=g,
                   prescale=dict(applied=ps.applied, centre=ps.centre, radius=ps.radius)),
    )
