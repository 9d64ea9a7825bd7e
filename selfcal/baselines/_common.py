"""Shared pieces of the baselines: result object, input checks, pre-scaling, LM core.

Everything here is private to :mod:`selfcal.baselines`; it does not depend on the
selfcal engine (``selfcal.models`` / ``selfcal.fit``) on purpose, so the baselines stay
an independent reference.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any, Callable

import numpy as np

from selfcal.errors import InputError

__all__ = [
    "BaselineResult",
    "Prescale",
    "check_poses",
    "check_gravity_dir",
    "prescale_poses",
    "lm_solve",
    "affine9_residual",
    "ANGLES_SEED",
    "ANGLES_TRI",
]


@dataclass
class BaselineResult:
    """Outcome of one baseline calibration.

    The calibration follows the selfcal convention (docs/internals.md)::

        a_cal_g = matrix @ (raw - offset) [+ temp_coef * (temp_c - temp_ref_c)]

    Attributes
    ----------
    method : str
        Registry name of the method that produced the result (e.g. ``"ggir_autocal"``).
    matrix : ndarray, shape (3, 3), g per raw unit
        Calibration matrix. It absorbs the input unit: every method calibrates to a
        unit norm, so ``matrix`` maps counts, m/s^2 or g to g.
    offset : ndarray, shape (3,), raw unit
        Zero-g offset, subtracted from the raw reading.
    n_iter : int
        Iterations the method ran (0 for closed-form methods).
    converged : bool
        Whether the method met its own stopping rule (closed-form methods: whether
        the solution is valid, e.g. the quadric is an ellipsoid).
    message : str
        Human-readable outcome, in the words of the method where it has them.
    extra : dict
        Method-specific diagnostics (parameter vectors in the method's own
        convention, cost history, QC flags, ...).
    temp_coef : ndarray, shape (3,), g/degC, or None
        Additive temperature term, for methods that model one (GGIR).
    temp_ref_c : float, degC
        Reference temperature of ``temp_coef`` (the term is zero there).
    """

    method: str
    matrix: np.ndarray
    offset: np.ndarray
    n_iter: int = 0
    converged: bool = True
    message: str = ""
    extra: dict[str, Any] = field(default_factory=dict)
    temp_coef: np.ndarray | None = None
    temp_ref_c: float = 0.0

    def apply(self, raw: np.ndarray, temp_c: np.ndarray | None = None) -> np.ndarray:
        """Calibrate raw readings.

        Parameters
        ----------
        raw : ndarray, shape (n, 3) or (3,), raw unit
            Readings in the unit the calibration was fitted in.
        temp_c : ndarray, shape (n,) or float, degC, optional
            Temperature of each reading. Used only by results with a temperature
            term; if omitted there, the readings are taken to be at ``temp_ref_c``
            (the temperature term is zero).

        Returns
        -------
        ndarray, shape (n, 3) or (3,), g
            Calibrated specific force.
        """
        raw = np.asarray(raw, dtype=float)
        out = (raw - self.offset) @ self.matrix.T
        if self.temp_coef is not None and temp_c is not None:
            dt = np.asarray(temp_c, dtype=float) - self.temp_ref_c
            out = out + np.multiply.outer(dt, self.temp_coef)
        return out

    def norm_error_g(self, raw: np.ndarray, temp_c: np.ndarray | None = None) -> np.ndarray:
        """Calibrated-norm error ``||apply(raw)|| - 1``.

        Parameters
        ----------
        raw : ndarray, shape (n, 3), raw unit
            Still-pose readings.
        temp_c : ndarray, shape (n,), degC, optional
            Temperatures, see :meth:`apply`.

        Returns
        -------
        ndarray, shape (n,), g
        """
        return np.linalg.norm(self.apply(raw, temp_c), axis=-1) - 1.0


# --------------------------------------------------------------------------- inputs


def _as_array(x: Any, name: str, shape_tail: tuple[int, ...], n: int | None) -> np.ndarray:
    try:
        a = np.asarray(x, dtype=float)
    except (TypeError, ValueError) as exc:
        raise InputError(f"{name}: expected a numeric array ({exc})") from None
    want_ndim = 1 + len(shape_tail)
    if a.ndim != want_ndim or a.shape[1:] != shape_tail:
        raise InputError(
            f"{name}: expected shape (n{''.join(', ' + str(s) for s in shape_tail)}), "
            f"got {a.shape}"
        )
    if n is not None and a.shape[0] != n:
        raise InputError(f"{name}: expected {n} rows (one per pose), got {a.shape[0]}")
    return a


def check_poses(
    mean: Any,
    sd: Any = None,
    n_samples: Any = None,
    t_s: Any = None,
    temp_c: Any = None,
    *,
    min_poses: int = 1,
    method: str = "",
) -> tuple[np.ndarray, np.ndarray | None, np.ndarray | None, np.ndarray | None, np.ndarray | None]:
    """Validate the common still-pose inputs and return them as float arrays.

    Parameters
    ----------
    mean : array_like, shape (n, 3), raw unit
    sd : array_like, shape (n, 3), raw unit, optional
    n_samples : array_like, shape (n,), optional
    t_s : array_like, shape (n,), s, optional
    temp_c : array_like, shape (n,), degC, optional
    min_poses : int
        Fewest poses the method can work with.
    method : str
        Method name, for the error message.

    Returns
    -------
    tuple of ndarray or None
        ``(mean, sd, n_samples, t_s, temp_c)``.

    Raises
    ------
    InputError
        (a ``ValueError``) naming the offending argument.
    """
    m = _as_array(mean, "mean", (3,), None)
    if not np.all(np.isfinite(m)):
        raise InputError("mean: contains NaN or infinite values")
    n = m.shape[0]
    if n < min_poses:
        raise InputError(f"mean: {method or 'this method'} needs at least {min_poses} poses, got {n}")
    s = None if sd is None else _as_array(sd, "sd", (3,), n)
    if s is not None and np.any(s < 0):
        raise InputError("sd: standard deviations must be >= 0")
    ns = None if n_samples is None else _as_array(n_samples, "n_samples", (), n)
    ts = None if t_s is None else _as_array(t_s, "t_s", (), n)
    tc = None if temp_c is None else _as_array(temp_c, "temp_c", (), n)
    return m, s, ns, ts, tc


def check_gravity_dir(gravity_dir: Any, n: int) -> np.ndarray:
    """Validate ``gravity_dir`` (n, 3) and normalise its rows to unit length.

    Parameters
    ----------
    gravity_dir : array_like, shape (n, 3), dimensionless
        Direction of the ideal (calibrated) reading of each pose, i.e. of the specific
        force, which points *up*: a sensor lying flat with +z up reads ``(0, 0, +1)``.
    n : int
        Number of poses.

    Returns
    -------
    ndarray, shape (n, 3)
    """
    gd = _as_array(gravity_dir, "gravity_dir", (3,), n)
    norms = np.linalg.norm(gd, axis=1)
    if not np.all(np.isfinite(gd)) or np.any(norms < 1e-9):
        raise InputError("gravity_dir: rows must be finite, non-zero direction vectors")
    return gd / norms[:, None]


# --------------------------------------------------------------------------- prescale


@dataclass(frozen=True)
class Prescale:
    """Affine change of variables ``u = (raw - centre) / radius``.

    Attributes
    ----------
    centre : ndarray, shape (3,), raw unit
    radius : float, raw unit per g
    applied : bool
    """

    centre: np.ndarray
    radius: float
    applied: bool

    def forward(self, raw: np.ndarray) -> np.ndarray:
        """raw (n, 3) raw unit -> u (n, 3), ~g."""
        return (raw - self.centre) / self.radius

    def back(self, matrix_u: np.ndarray, offset_u: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Map a calibration fitted on ``u`` to the raw unit.

        ``a = M_u (u - o_u) = (M_u / r) (raw - (c + r o_u))``.
        """
        return matrix_u / self.radius, self.centre + self.radius * offset_u


def prescale_poses(mean: np.ndarray, mode: bool | str = "auto") -> Prescale:
    """Choose a pre-scaling that brings the poses to a near-unit sphere.

    The centre and radius come from an algebraic sphere fit
    ``||x||^2 = 2 c.x + d`` (linear least squares, exact for any unit), ``r^2 = d + ||c||^2``.
    The map is a translation plus a *uniform* scaling, so every linear calibration
    family used here is closed under it and the result is mapped back exactly
    (:meth:`Prescale.back`); only the starting point of iterative methods and the
    weighting of algebraic (non-geometric) fits can change.

    Parameters
    ----------
    mean : ndarray, shape (n, 3), raw unit
    mode : {"auto", True, False}
        ``"auto"`` pre-scales unless the median norm of the data already lies in
        [0.5, 2] (i.e. the data look like g); ``True`` always; ``False`` never.

    Returns
    -------
    Prescale
    """
    if mode not in ("auto", True, False):
        raise InputError(f"prescale: expected 'auto', True or False, got {mode!r}")
    ident = Prescale(np.zeros(3), 1.0, False)
    if mode is False:
        return ident
    if mode == "auto":
        med = float(np.median(np.linalg.norm(mean, axis=1)))
        if 0.5 <= med <= 2.0:
            return ident
    if mean.shape[0] >= 4:
        A = np.column_stack([2.0 * mean, np.ones(len(mean))])
        y = np.einsum("ij,ij->i", mean, mean)
        sol, *_ = np.linalg.lstsq(A, y, rcond=None)
        c, d = sol[:3], sol[3]
        r2 = d + c @ c
        if np.isfinite(r2) and r2 > 0:
            return Prescale(c, float(np.sqrt(r2)), True)
    # degenerate geometry: scale by the median norm only
    med = float(np.median(np.linalg.norm(mean, axis=1)))
    if not np.isfinite(med) or med <= 0:
        return ident
    return Prescale(np.zeros(3), med, True)


# --------------------------------------------------------------------------- 9-param affine model

# Generators E_i of the 3x3 "axis error" matrix T = I + sum_i x_i E_i.
#: seed model (lm-accelerometer-calibration.txt): T = [[1, psi, -theta], [-psi, 1, phi],
#: [theta, -phi, 1]], parameter order (phi, theta, psi) = (a1, a2, a3) of the seed code.
ANGLES_SEED = np.array(
    [
        [[0, 0, 0], [0, 0, 1], [0, -1, 0]],  # phi
        [[0, 0, -1], [0, 0, 0], [1, 0, 0]],  # theta
        [[0, 1, 0], [-1, 0, 0], [0, 0, 0]],  # psi
    ],
    dtype=float,
)
#: triangular non-orthogonality (insole paper / IMU-TK):
#: T = [[1, -Kyz, Kzy], [0, 1, -Kzx], [0, 0, 1]], parameter order (Kyz, Kzy, Kzx).
ANGLES_TRI = np.array(
    [
        [[0, -1, 0], [0, 0, 0], [0, 0, 0]],  # Kyz
        [[0, 0, 1], [0, 0, 0], [0, 0, 0]],  # Kzy
        [[0, 0, 0], [0, 0, -1], [0, 0, 0]],  # Kzx
    ],
    dtype=float,
)


def affine9_matrix(x: np.ndarray, gens: np.ndarray) -> np.ndarray:
    """``T K`` of the 9-parameter model ``h = T K (u + b)``.

    Parameters
    ----------
    x : ndarray, shape (9,)
        ``(angle_1, angle_2, angle_3, s_x, s_y, s_z, b_x, b_y, b_z)``; angles in rad,
        scales in g per input unit, biases in the input unit (added to the reading).
    gens : ndarray, shape (3, 3, 3)
        Generators of ``T`` (:data:`ANGLES_SEED` or :data:`ANGLES_TRI`).

    Returns
    -------
    ndarray, shape (3, 3)
    """
    T = np.eye(3) + np.tensordot(x[:3], gens, axes=1)
    return T * x[3:6][None, :]


def affine9_residual(
    x: np.ndarray, u: np.ndarray, gens: np.ndarray, g: float = 1.0
) -> tuple[np.ndarray, np.ndarray]:
    """Norm residual and exact Jacobian of ``h = T K (u + b)``.

    Parameters
    ----------
    x : ndarray, shape (9,)
        See :func:`affine9_matrix`.
    u : ndarray, shape (n, 3), input unit
    gens : ndarray, shape (3, 3, 3)
    g : float
        Target norm, input unit after calibration.

    Returns
    -------
    r : ndarray, shape (n,)
        ``||h|| - g``.
    J : ndarray, shape (n, 9)
        ``dr/dx``.
    """
    T = np.eye(3) + np.tensordot(x[:3], gens, axes=1)
    s = x[3:6]
    w = u + x[6:9]  # (n, 3)
    kw = w * s  # K w
    h = kw @ T.T
    nh = np.linalg.norm(h, axis=1)
    r = nh - g
    dh = np.empty((u.shape[0], 9, 3))
    dh[:, 0:3, :] = np.einsum("nj,aij->nai", kw, gens)  # d h / d angle_a
    dh[:, 3:6, :] = w[:, :, None] * T.T[None, :, :]  # d h / d s_j = T[:, j] w_j
    dh[:, 6:9, :] = (s[:, None] * T.T)[None, :, :]  # d h / d b_j = T[:, j] s_j
    J = np.einsum("nai,ni->na", dh, h) / np.where(nh > 0, nh, 1.0)[:, None]
    return r, J


# --------------------------------------------------------------------------- LM core


def lm_solve(
    fun: Callable[[np.ndarray], tuple[np.ndarray, np.ndarray]],
    x0: np.ndarray,
    *,
    max_iter: int = 200,
    tau: float = 1e-3,
    gtol: float = 1e-12,
    xtol: float = 1e-12,
    ftol: float = 1e-15,
) -> dict[str, Any]:
    """Levenberg-Marquardt with gain-ratio acceptance (Madsen, Nielsen & Tingleff 2004).

    Minimises ``0.5 ||r(x)||^2``. Step ``(J^T J + mu I) h = -J^T r`` (Levenberg's
    identity damping, as in the sources); a step is accepted only if the gain ratio
    ``rho = (F(x) - F(x+h)) / (L(0) - L(h)) > 0``; ``mu`` follows Nielsen's rule
    (``mu *= max(1/3, 1 - (2 rho - 1)^3)`` on success, ``mu *= nu, nu *= 2`` on failure).

    Parameters
    ----------
    fun : callable
        ``fun(x) -> (r (m,), J (m, p))``.
    x0 : ndarray, shape (p,)
    max_iter : int
        Maximum number of iterations (accepted or rejected steps).
    tau : float
        ``mu0 = tau * max(diag(J^T J))``.
    gtol, xtol, ftol : float
        Stop when ``||J^T r||_inf <= gtol``, when ``||h|| <= xtol (||x|| + xtol)``, or
        when an accepted step lowers the cost by less than ``ftol`` relative.

    Returns
    -------
    dict
        ``x``, ``cost`` (0.5 ||r||^2), ``n_iter``, ``converged``, ``message``,
        ``n_rejected``, ``cost_history`` (list, accepted iterates).
    """
    x = np.array(x0, dtype=float)
    r, J = fun(x)
    if not (np.all(np.isfinite(r)) and np.all(np.isfinite(J))):
        return dict(x=x, cost=np.inf, n_iter=0, converged=False,
                    message="residuals at x0 are not finite", n_rejected=0, cost_history=[])
    cost = 0.5 * r @ r
    A = J.T @ J
    gvec = J.T @ r
    mu = tau * float(np.max(np.diag(A))) if np.max(np.diag(A)) > 0 else tau
    nu = 2.0
    hist = [cost]
    n_rej = 0
    p = x.size
    msg = f"maximum number of iterations ({max_iter}) reached"
    converged = False
    it = 0
    if np.max(np.abs(gvec)) <= gtol:
        return dict(x=x, cost=cost, n_iter=0, converged=True,
                    message="gradient below gtol at x0", n_rejected=0, cost_history=hist)
    for it in range(1, max_iter + 1):
        try:
            h = np.linalg.solve(A + mu * np.eye(p), -gvec)
        except np.linalg.LinAlgError:
            mu *= nu
            nu *= 2.0
            n_rej += 1
            continue
        if np.linalg.norm(h) <= xtol * (np.linalg.norm(x) + xtol):
            msg, converged = "step size below xtol", True
            break
        x_new = x + h
        r_new, J_new = fun(x_new)
        cost_new = 0.5 * r_new @ r_new if np.all(np.isfinite(r_new)) else np.inf
        pred = 0.5 * h @ (mu * h - gvec)
        rho = (cost - cost_new) / pred if pred > 0 else -1.0
        if rho > 0 and np.isfinite(cost_new):
            rel = (cost - cost_new) / max(cost, 1e-300)
            x, r, J, cost = x_new, r_new, J_new, cost_new
            A = J.T @ J
            gvec = J.T @ r
            mu *= max(1.0 / 3.0, 1.0 - (2.0 * rho - 1.0) ** 3)
            nu = 2.0
            hist.append(cost)
            if np.max(np.abs(gvec)) <= gtol:
                msg, converged = "gradient below gtol", True
                break
            if rel < ftol:
                msg, converged = "relative cost reduction below ftol", True
                break
        else:
            mu *= nu
            nu *= 2.0
            n_rej += 1
    return dict(x=x, cost=cost, n_iter=it, converged=converged, message=msg,
                n_rejected=n_rej, cost_history=hist)
