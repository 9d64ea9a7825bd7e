"""Norm-based LM baselines: ``lm_fixed``, ``lm_random_init``, ``insole_lm_ls``, ``imu_tk_style``.

All four fit a 9-parameter model ``h = T K (u + b)`` to ``||h|| = 1`` on pose means
``u`` (pre-scaled to ~g when the input is not in g, see ``prescale_poses``):

* ``lm_fixed`` — the seed's model (``T = I + skew``, a first-order rotation) with the
  seed's defects repaired: true residual, exact Jacobian, gain-ratio acceptance,
  proper stopping. The model defect (rotation angles instead of non-orthogonality)
  is kept: it is the seed's model.
* ``lm_random_init`` / ``insole_lm_ls`` — the insole paper
  (``insole-lm-least-squares-self-calibration.txt``), ``theta_cal = [Kyz, Kzy, Kzx, Sxx,
  Syy, Szz, Bx, By, Bz]``, ``O = Tk Ts (R + B)``. The paper's equation (1) is an image
  missing from the text; the parameter names match IMU-TK's (Tedaldi et al. 2014)
  triangular form ``Tk = [[1, -Kyz, Kzy], [0, 1, -Kzx], [0, 0, 1]]``, which we use.
* ``imu_tk_style`` — IMU-TK's accelerometer norm fit (same triangular form, bias
  subtracted), one LM start at the nominal model, via ``scipy.optimize.least_squares``.
"""

from __future__ import annotations

import numpy as np
from scipy.optimize import least_squares

from ._common import (
    ANGLES_SEED,
    ANGLES_TRI,
    BaselineResult,
    affine9_matrix,
    affine9_residual,
    check_poses,
    lm_solve,
    prescale_poses,
)

__all__ = ["lm_fixed", "lm_random_init", "insole_lm_ls", "imu_tk_style", "classify_axis_aligned"]

_NOMINAL = np.array([0.0, 0.0, 0.0, 1.0, 1.0, 1.0, 0.0, 0.0, 0.0])


def _finish(method, ps, x, gens, fit, extra=None) -> BaselineResult:
    M_u = affine9_matrix(x, gens)
    matrix, offset = ps.back(M_u, -x[6:9])
    ex = dict(theta=x.copy(), cost_history=np.asarray(fit.get("cost_history", [])),
              n_rejected=fit.get("n_rejected", 0),
              prescale=dict(applied=ps.applied, centre=ps.centre, radius=ps.radius))
    if extra:
        ex.update(extra)
    return BaselineResult(method=method, matrix=matrix, offset=offset, n_iter=int(fit["n_iter"]),
                          converged=bool(fit["converged"]), message=fit["message"], extra=ex)


def lm_fixed(
    mean,
    sd=None,
    n_samples=None,
    t_s=None,
    temp_c=None,
    *,
    max_iter: int = 200,
    prescale: bool | str = "auto",
) -> BaselineResult:
    """The seed's 9-parameter model with a correct LM.

    Parameters
    ----------
    mean : array_like, shape (n, 3), raw unit
        Still-pose mean readings; at least 9 poses.
    sd, n_samples, t_s, temp_c : array_like, optional
        Accepted for the common interface and ignored (unweighted fit, like the seed).
    max_iter : int, default 200
        Iteration limit of the LM.
    prescale : {"auto", True, False}
        See ``prescale_poses``.

    Returns
    -------
    BaselineResult
        ``extra["theta"]`` = ``(phi, theta, psi, sx, sy, sz, bx, by, bz)`` in the
        pre-scaled frame; ``matrix = T K`` (mapped to the raw unit), ``offset = -b``.

    Notes
    -----
    Residual ``r_k = ||T K (u_k + b)|| - 1`` (not its square), exact Jacobian, start
    at the seed's ``(0, 0, 0, 1, 1, 1, 0, 0, 0)``, Levenberg damping ``mu I`` with
    Nielsen's gain-ratio rule (:func:`lm_solve`): a step that does not lower the cost
    is rejected. What is *not* fixed is the model: ``T = I + skew`` is a first-order
    rotation, invisible to the norm at first order, and it cannot represent axis
    non-orthogonality, which therefore stays in the residual.
    """
    m, *_ = check_poses(mean, sd, n_samples, t_s, temp_c, min_poses=9, method="lm_fixed")
    ps = prescale_poses(m, prescale)
    u = ps.forward(m)
    fit = lm_solve(lambda x: affine9_residual(x, u, ANGLES_SEED), _NOMINAL, max_iter=max_iter)
    return _finish("lm_fixed", ps, fit["x"], ANGLES_SEED, fit)


def lm_random_init(
    mean,
    sd=None,
    n_samples=None,
    t_s=None,
    temp_c=None,
    *,
    rng: np.random.Generator | int | None = 0,
    max_iter: int = 1000,
    prescale: bool | str = "auto",
) -> BaselineResult:
    """Plain LM from a random initial value, as in the insole paper (section 4.1.1).

    Parameters
    ----------
    mean : array_like, shape (n, 3), raw unit
        Still-pose mean readings; at least 9 poses.
    sd, n_samples, t_s, temp_c : array_like, optional
        Accepted for the common interface and ignored.
    rng : numpy.random.Generator or int, default 0
        Source of the initial value: each of the 9 parameters uniform in [0, 1]
        (in the pre-scaled frame, i.e. g for the biases), as the paper states.
    max_iter : int, default 1000
    prescale : {"auto", True, False}

    Returns
    -------
    BaselineResult
        ``extra["theta"]`` = ``(Kyz, Kzy, Kzx, Sx, Sy, Sz, Bx, By, Bz)``,
        ``extra["theta0"]`` the random start. No sign canonicalisation: a start can
        end at a reflected solution (negative scale); it is reported as found.
    """
    m, *_ = check_poses(mean, sd, n_samples, t_s, temp_c, min_poses=9, method="lm_random_init")
    gen = rng if isinstance(rng, np.random.Generator) else np.random.default_rng(rng)
    x0 = gen.uniform(0.0, 1.0, size=9)
    ps = prescale_poses(m, prescale)
    u = ps.forward(m)
    fit = lm_solve(lambda x: affine9_residual(x, u, ANGLES_TRI), x0, max_iter=max_iter)
    return _finish("lm_random_init", ps, fit["x"], ANGLES_TRI, fit, extra=dict(theta0=x0))


def classify_axis_aligned(u: np.ndarray, sigma: float, g: float = 1.0) -> tuple[np.ndarray, np.ndarray]:
    """Insole paper's rule (16): ``|O_ij| - g`` and the other two axes within ``sigma``.

    Parameters
    ----------
    u : ndarray, shape (n, 3), g
        Pose readings.
    sigma : float, g
        Tolerance.
    g : float, g
        Expected norm.

    Returns
    -------
    is_cor : ndarray, shape (n,), bool
        Pose belongs to ``O_cor``.
    face : ndarray, shape (n, 3)
        Assumed true reading ``+-g e_j`` for ``O_cor`` poses (zeros elsewhere).
    """
    j = np.argmax(np.abs(u), axis=1)
    idx = np.arange(len(u))
    main = u[idx, j]
    others = np.abs(u).copy()
    others[idx, j] = 0.0
    is_cor = (np.abs(np.abs(main) - g) < sigma) & np.all(others < sigma, axis=1)
    face = np.zeros_like(u)
    face[idx, j] = np.sign(main) * g
    face[~is_cor] = 0.0
    return is_cor, face


def _tri9_from_affine(M: np.ndarray, c: np.ndarray) -> np.ndarray:
    """(Kyz, Kzy, Kzx, S, B) from ``a = M u + c`` with ``M`` upper triangular."""
    S = np.diag(M).copy()
    kyz = -M[0, 1] / S[1]
    kzy = M[0, 2] / S[2]
    kzx = -M[1, 2] / S[2]
    B = np.linalg.solve(M, c)
    return np.concatenate([[kyz, kzy, kzx], S, B])


def insole_lm_ls(
    mean,
    sd=None,
    n_samples=None,
    t_s=None,
    temp_c=None,
    *,
    sigma: float = 0.15,
    x0=None,
    prior_weight: float = 1e-6,
    max_iter: int = 1000,
    prescale: bool | str = "auto",
) -> BaselineResult:
    """The insole paper's LM & least-squares self-calibration (one batch).

    Parameters
    ----------
    mean : array_like, shape (n, 3), raw unit
        Still-pose mean readings.
    sd, n_samples, t_s, temp_c : array_like, optional
        Accepted for the common interface and ignored (the paper's stillness tests
        belong to the detector, upstream of a pose table).
    sigma : float, g, default 0.15
        Tolerance of the ``O_cor`` rule (16). Not given in the paper; 0.15 g admits
        sensors with ~60 mg bias and ~3 % scale error, and poses tilted by up to
        ~8 deg, whose direction the correction step then takes as exactly axial.
    x0 : array_like, shape (9,), optional
        Previous result ``(Kyz, Kzy, Kzx, Sx, Sy, Sz, Bx, By, Bz)`` (pre-scaled frame)
        for warm starts; default the nominal model. It is the prior of the linear
        correction for whatever ``O_cor`` does not determine, and the LM start if
        ``O_cor`` is empty.
    prior_weight : float, default 1e-6
        Ridge weight (relative to ``trace(A^T A)/9``) pulling the linear correction
        towards ``x0``; it only matters for combinations ``O_cor`` leaves undetermined
        (the paper: "solved together with the existing initial-value data").
    max_iter : int, default 1000
        LM iteration limit.
    prescale : {"auto", True, False}

    Returns
    -------
    BaselineResult
        ``extra``: ``theta``, ``theta_ls`` (corrected initial value), ``n_cor``,
        ``n_train``, ``is_cor`` (n,) bool.

    Notes
    -----
    1. Classify with rule (16): ``O_cor`` = one axis reads ``+-1 g +- sigma`` and the
       other two ``0 +- sigma``; ``O_train`` = all other poses.
    2. Initial-value correction: for ``O_cor`` the true reading is taken as
       ``+-e_j`` exactly, so ``a = M u + c`` (``M = Tk Ts`` upper triangular, ``c = M B``)
       is linear in its 9 unknowns: solved by (ridge-regularised) least squares.
    3. LM (:func:`lm_solve`, norm residual) on ``O_train`` from the corrected value.
       With no ``O_train`` poses the corrected value is returned.
    """
    m, *_ = check_poses(mean, sd, n_samples, t_s, temp_c, min_poses=1, method="insole_lm_ls")
    ps = prescale_poses(m, prescale)
    u = ps.forward(m)
    prior = _NOMINAL.copy() if x0 is None else np.asarray(x0, dtype=float).reshape(9)
    is_cor, face = classify_axis_aligned(u, sigma)
    n_cor, n_train = int(is_cor.sum()), int((~is_cor).sum())
    theta_ls = prior.copy()
    if n_cor:
        uc, ac = u[is_cor], face[is_cor]
        k = len(uc)
        # unknowns z = [M00, M01, M02, M11, M12, M22, c0, c1, c2]
        A = np.zeros((3 * k, 9))
        y = ac.T.reshape(-1)  # rows x (k), y (k), z (k)
        A[0:k, 0:3] = uc
        A[0:k, 6] = 1.0
        A[k:2 * k, 3:5] = uc[:, 1:3]
        A[k:2 * k, 7] = 1.0
        A[2 * k:, 5] = uc[:, 2]
        A[2 * k:, 8] = 1.0
        Mp = affine9_matrix(prior, ANGLES_TRI)
        cp = Mp @ prior[6:9]
        zp = np.array([Mp[0, 0], Mp[0, 1], Mp[0, 2], Mp[1, 1], Mp[1, 2], Mp[2, 2], *cp])
        w = prior_weight * max(np.trace(A.T @ A) / 9.0, 1e-12)
        z = np.linalg.solve(A.T @ A + w * np.eye(9), A.T @ y + w * zp)
        M = np.array([[z[0], z[1], z[2]], [0.0, z[3], z[4]], [0.0, 0.0, z[5]]])
        if np.all(np.diag(M) > 0):
            theta_ls = _tri9_from_affine(M, z[6:9])
    if n_train:
        ut = u[~is_cor]
        fit = lm_solve(lambda x: affine9_residual(x, ut, ANGLES_TRI), theta_ls, max_iter=max_iter)
        if n_train < 9:
            fit["message"] += f" (only {n_train} O_train poses for 9 parameters: damped, underdetermined)"
    else:
        fit = dict(x=theta_ls, n_iter=0, converged=n_cor > 0,
                   message="no O_train poses: least-squares correction only", cost_history=[], n_rejected=0)
    fit["message"] = f"O_cor={n_cor}, O_train={n_train}; " + fit["message"]
    return _finish("insole_lm_ls", ps, fit["x"], ANGLES_TRI, fit,
                   extra=dict(theta_ls=theta_ls, n_cor=n_cor, n_train=n_train, is_cor=is_cor))


def imu_tk_style(
    mean,
    sd=None,
    n_samples=None,
    t_s=None,
    temp_c=None,
    *,
    prescale: bool | str = "auto",
    max_nfev: int | None = None,
) -> BaselineResult:
    """IMU-TK-style accelerometer calibration: 9-parameter norm fit, one LM start.

    Parameters
    ----------
    mean : array_like, shape (n, 3), raw unit
        Still-pose mean readings; at least 9 poses.
    sd, n_samples, t_s, temp_c : array_like, optional
        Accepted for the common interface and ignored.
    prescale : {"auto", True, False}
        Plays the role of IMU-TK's user-supplied initial scale (nominal sensitivity).
    max_nfev : int, optional
        Passed to ``scipy.optimize.least_squares``.

    Returns
    -------
    BaselineResult
        ``n_iter`` counts function evaluations (MINPACK does not report iterations).
        ``extra["theta"]`` = ``(mis_yz, mis_zy, mis_zx, sx, sy, sz, bx, by, bz)``;
        calibration ``T K (u - b)`` with ``T = [[1, -mis_yz, mis_zy], [0, 1, -mis_zx],
        [0, 0, 1]]`` (IMU-TK's ``CalibratedTriad``), ``b`` subtracted.

    Notes
    -----
    Residual ``g^2 - ||T K (u - b)||^2`` with ``g = 1`` as in IMU-TK's
    ``MultiPosAccResidual`` (written from memory of the source, not re-checked here),
    started at identity / zero bias, solved by MINPACK LM
    (``least_squares(method="lm")``) where IMU-TK uses Ceres' LM. IMU-TK's outer loop
    over static-detector thresholds is not reproduced: the poses are given.
    """
    m, *_ = check_poses(mean, sd, n_samples, t_s, temp_c, min_poses=9, method="imu_tk_style")
    ps = prescale_poses(m, prescale)
    u = ps.forward(m)

    def res(p):
        T = np.eye(3) + np.tensordot(p[:3], ANGLES_TRI, axes=1)
        h = ((u - p[6:9]) * p[3:6]) @ T.T
        return 1.0 - np.einsum("ij,ij->i", h, h)

    def jac(p):
        T = np.eye(3) + np.tensordot(p[:3], ANGLES_TRI, axes=1)
        s = p[3:6]
        w = u - p[6:9]
        kw = w * s
        h = kw @ T.T
        J = np.empty((len(u), 9))
        J[:, 0:3] = np.einsum("nj,aij,ni->na", kw, ANGLES_TRI, h)
        J[:, 3:6] = w * (h @ T)
        J[:, 6:9] = -s * (h @ T)
        return -2.0 * J

    kw = {} if max_nfev is None else dict(max_nfev=max_nfev)
    sol = least_squares(res, _NOMINAL.copy(), jac=jac, method="lm", **kw)
    x = sol.x
    M_u = affine9_matrix(x, ANGLES_TRI)
    matrix, offset = ps.back(M_u, x[6:9])
    return BaselineResult(
        method="imu_tk_style", matrix=matrix, offset=offset, n_iter=int(sol.nfev),
        converged=bool(sol.status > 0), message=f"least_squares(lm): {sol.message}",
        extra=dict(theta=x, cost=float(sol.cost), status=int(sol.status), njev=sol.njev,
                   prescale=dict(applied=ps.applied, centre=ps.centre, radius=ps.radius)),
    )
