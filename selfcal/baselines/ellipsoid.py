"""Closed-form ellipsoid baselines: ``ellipsoid6`` and ``quadric9``."""

from __future__ import annotations

import numpy as np

from selfcal.errors import InputError

from ._common import BaselineResult, Prescale, check_poses, prescale_poses

__all__ = ["ellipsoid6", "quadric9", "quadric_to_calibration"]


def _pinfo(ps: Prescale) -> dict:
    return dict(applied=ps.applied, centre=ps.centre, radius=ps.radius)


def ellipsoid6(
    mean,
    sd=None,
    n_samples=None,
    t_s=None,
    temp_c=None,
    *,
    prescale: bool | str = "auto",
) -> BaselineResult:
    """Axis-aligned ellipsoid fit of ``ellipsoid-fit-calibration.txt`` (6 parameters).

    Parameters
    ----------
    mean : array_like, shape (n, 3), raw unit
        Still-pose mean readings; at least 6 poses.
    sd, n_samples, t_s, temp_c : array_like, optional
        Accepted for the common interface and ignored.
    prescale : {"auto", True, False}
        The fit is exactly equivariant under the translation + uniform scaling of
        ``prescale_poses`` (the algebraic residual only gets multiplied by ``r^2``), so
        pre-scaling changes nothing but the conditioning of the normal equations
        (in counts with a 32768 offset they are hopeless in float64 without it).

    Returns
    -------
    BaselineResult
        ``matrix = diag(1/A, 1/B, 1/C)``, ``offset = (x0, y0, z0)``;
        ``extra["v"]`` = ``(a, b, c, d, e, f)`` in the pre-scaled frame.

    Raises
    ------
    InputError
        If the fitted quadric is not an ellipsoid (``a <= 0``, ``b <= 0`` or ``A^2 <= 0``),
        e.g. when the poses do not cover the sphere.

    Notes
    -----
    Seed: ``x^2 + a y^2 + b z^2 + c x + d y + e z + f = 0``, rows ``[y^2, z^2, x, y, z, 1]``,
    ``p = -x^2``, ``v = (M^T M)^-1 M^T p`` (normal equations, as the seed);
    ``x0 = -c/2, y0 = -d/(2a), z0 = -e/(2b)``, ``A = sqrt(x0^2 + a y0^2 + b z0^2 - f)``,
    ``B = A/sqrt(a)``, ``C = A/sqrt(b)``; calibrated ``g (x - x0)/A`` etc. Here ``g = 1``
    (unit norm). No cross-axis terms: non-orthogonality stays in the residual.
    """
    m, *_ = check_poses(mean, sd, n_samples, t_s, temp_c, min_poses=6, method="ellipsoid6")
    ps = prescale_poses(m, prescale)
    u = ps.forward(m)
    x, y, z = u.T
    M = np.column_stack([y**2, z**2, x, y, z, np.ones_like(x)])
    p = -(x**2)
    v = np.linalg.solve(M.T @ M, M.T @ p)
    a, b, c, d, e, f = v
    if not (a > 0 and b > 0):
        raise InputError("mean: ellipsoid6 fit is not an ellipsoid (a or b <= 0); poses do not cover the sphere")
    x0, y0, z0 = -c / 2, -d / (2 * a), -e / (2 * b)
    A2 = x0 * x0 + a * y0 * y0 + b * z0 * z0 - f
    if not A2 > 0:
        raise InputError("mean: ellipsoid6 fit is not an ellipsoid (A^2 <= 0)")
    A = np.sqrt(A2)
    B, C = A / np.sqrt(a), A / np.sqrt(b)
    matrix, offset = ps.back(np.diag([1 / A, 1 / B, 1 / C]), np.array([x0, y0, z0]))
    return BaselineResult(method="ellipsoid6", matrix=matrix, offset=offset, n_iter=0, converged=True,
                          message="linear least squares (seed normal equations)",
                          extra=dict(v=v, radii=np.array([A, B, C]), prescale=_pinfo(ps)))


def quadric_to_calibration(eta: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Centre and unit-norm triangular calibration of ``x^T Q x + l^T x = 1``.

    Parameters
    ----------
    eta : ndarray, shape (9,)
        ``(a1..a9)`` of ``a1 x^2 + a2 y^2 + a3 z^2 + a4 xy + a5 xz + a6 yz + a7 x + a8 y + a9 z = 1``.

    Returns
    -------
    centre : ndarray, shape (3,)
        ``c = -Q^-1 l / 2``.
    G : ndarray, shape (3, 3)
        ``Q / (1 + c^T Q c)``, so that ``(x - c)^T G (x - c) = 1`` on the quadric.
    R : ndarray, shape (3, 3)
        Upper-triangular Cholesky factor, ``R^T R = G``, positive diagonal; the
        calibration is ``a = R (x - c)``.

    Raises
    ------
    InputError
        If ``G`` is not positive definite (the quadric is not an ellipsoid).
    """
    a1, a2, a3, a4, a5, a6, a7, a8, a9 = eta
    Q = np.array([[a1, a4 / 2, a5 / 2], [a4 / 2, a2, a6 / 2], [a5 / 2, a6 / 2, a3]])
    lvec = np.array([a7, a8, a9])
    try:
        c = -0.5 * np.linalg.solve(Q, lvec)
    except np.linalg.LinAlgError:
        raise InputError("mean: quadric is degenerate (singular quadratic form)") from None
    G = Q / (1.0 + c @ Q @ c)
    try:
        L = np.linalg.cholesky(G)
    except np.linalg.LinAlgError:
        raise InputError("mean: fitted quadric is not an ellipsoid (form not positive definite)") from None
    return c, G, L.T


def quadric9(
    mean,
    sd=None,
    n_samples=None,
    t_s=None,
    temp_c=None,
    *,
    prescale: bool | str = "auto",
) -> BaselineResult:
    """General quadric fit of the insole paper, eq. (5)-(7) (9 coefficients).

    Parameters
    ----------
    mean : array_like, shape (n, 3), raw unit
        Still-pose mean readings; at least 9 poses.
    sd, n_samples, t_s, temp_c : array_like, optional
        Accepted for the common interface and ignored.
    prescale : {"auto", True, False}
        Unlike ``ellipsoid6``, this fit is *not* translation invariant (see Notes), so
        pre-scaling (which centres the data) changes the algebraic weighting slightly
        and removes the normalisation's singularity.

    Returns
    -------
    BaselineResult
        ``matrix = R`` (upper triangular, ``R^T R = G``), ``offset = c``;
        ``extra["eta"]`` the 9 coefficients in the pre-scaled frame.

    Notes
    -----
    ``a1 x^2 + a2 y^2 + a3 z^2 + a4 xy + a5 xz + a6 yz + a7 x + a8 y + a9 z = 1`` by linear
    least squares; centre ``c = -Q^-1 l / 2`` is the bias and
    ``(x - c)^T Q (x - c) = 1 + c^T Q c`` (paper eq. 6), so ``G = Q / (1 + c^T Q c)`` and
    the calibration matrix is the Cholesky factor of ``G``.

    Normalisation: the paper fixes the constant term of the general quadric to -1
    (right-hand side 1). That excludes quadrics through the origin of the *raw*
    coordinates and is ill-conditioned near them: it fails when the offset is close
    to one g-radius from zero (e.g. unsigned counts), and it makes the algebraic
    residual depend on where the origin is. In raw counts with a 32768 offset the
    coefficients become tiny and negative; the formulas above still hold (Q and
    ``1 + c^T Q c`` change sign together), but conditioning is poor — hence the
    default pre-scaling.
    """
    m, *_ = check_poses(mean, sd, n_samples, t_s, temp_c, min_poses=9, method="quadric9")
    ps = prescale_poses(m, prescale)
    u = ps.forward(m)
    x, y, z = u.T
    V = np.column_stack([x * x, y * y, z * z, x * y, x * z, y * z, x, y, z])
    eta, *_ = np.linalg.lstsq(V, np.ones(len(u)), rcond=None)
    c, G, R = quadric_to_calibration(eta)
    matrix, offset = ps.back(R, c)
    return BaselineResult(method="quadric9", matrix=matrix, offset=offset, n_iter=0, converged=True,
                          message="linear least squares, RHS-1 normalisation, Cholesky of the form",
                          extra=dict(eta=eta, G=G, prescale=_pinfo(ps)))
