"""Baselines that need the true orientation of each pose: ``six_face``, ``twelve_position``."""

from __future__ import annotations

import numpy as np

from selfcal.errors import InputError

from ._common import BaselineResult, Prescale, check_gravity_dir, check_poses, prescale_poses

__all__ = ["six_face", "twelve_position", "classify_faces", "FACE_NAMES"]

#: Face labels in the order of ``classify_faces`` codes 0..5.
FACE_NAMES = ("+x", "-x", "+y", "-y", "+z", "-z")


def _pinfo(ps: Prescale) -> dict:
    return dict(applied=ps.applied, centre=ps.centre, radius=ps.radius)


def classify_faces(directions: np.ndarray, tolerance_deg: float) -> np.ndarray:
    """Label each pose by the +-axis it points along, or -1.

    Parameters
    ----------
    directions : ndarray, shape (n, 3)
        Reading directions (any length; only the direction is used).
    tolerance_deg : float, deg
        Largest angle between the direction and the axis.

    Returns
    -------
    ndarray, shape (n,), int
        Code ``2 j + (0 if positive else 1)`` (see :data:`FACE_NAMES`), -1 if none.
    """
    d = directions / np.linalg.norm(directions, axis=1, keepdims=True)
    j = np.argmax(np.abs(d), axis=1)
    comp = d[np.arange(len(d)), j]
    ok = np.abs(comp) >= np.cos(np.radians(tolerance_deg))
    return np.where(ok, 2 * j + (comp < 0), -1)


def _faces(u, gravity_dir, tolerance_deg, n):
    if gravity_dir is not None:
        gd = check_gravity_dir(gravity_dir, n)
        return classify_faces(gd, tolerance_deg), gd, "gravity_dir"
    return classify_faces(u, tolerance_deg), None, "auto-classified readings"


def six_face(
    mean,
    sd=None,
    n_samples=None,
    t_s=None,
    temp_c=None,
    *,
    gravity_dir=None,
    tolerance_deg: float = 10.0,
    prescale: bool | str = "auto",
) -> BaselineResult:
    """Six-face min/max calibration (``ellipsoid-fit-calibration.txt`` section 1.2.1).

    Parameters
    ----------
    mean : array_like, shape (n, 3), raw unit
        Still-pose mean readings.
    sd, n_samples, t_s, temp_c : array_like, optional
        Accepted for the common interface and ignored.
    gravity_dir : array_like, shape (n, 3), optional
        True direction of each pose's ideal reading (the specific force, pointing up;
        flat with +z up reads ``(0, 0, 1)``). Poses within ``tolerance_deg`` of a
        +-axis are the faces. Without it, the poses are auto-classified from the
        readings themselves (after pre-scaling) with the same tolerance.
    tolerance_deg : float, deg, default 10
    prescale : {"auto", True, False}

    Returns
    -------
    BaselineResult
        ``matrix = diag(1 / ((max - min)/2))``, ``offset = (max + min)/2``; ``extra``:
        ``max``, ``min`` (3,) raw unit, ``n_per_face`` (6,).

    Raises
    ------
    InputError
        (``ValueError``) naming the missing faces when one of the six has no pose.

    Notes
    -----
    ``max_j`` is the axis-``j`` reading of the ``+j`` face (mean over its poses),
    ``min_j`` that of the ``-j`` face. The seed writes the calibrated value as
    ``x_c = k_x x_m + b_x`` with ``b_x = (min + max)/2`` — the bias added, not
    subtracted, and not scaled; that slip is not reproduced: ``a = k (x - b)``.
    Off-axis readings of the faces are ignored (no cross-axis terms).
    """
    m, *_ = check_poses(mean, sd, n_samples, t_s, temp_c, min_poses=6, method="six_face")
    ps = prescale_poses(m, prescale)
    u = ps.forward(m)
    codes, _, src = _faces(u, gravity_dir, tolerance_deg, len(m))
    counts = np.bincount(codes[codes >= 0], minlength=6)
    missing = [FACE_NAMES[i] for i in range(6) if counts[i] == 0]
    if missing:
        raise InputError(
            f"six_face needs at least one pose on each of the six faces; missing {', '.join(missing)} "
            f"({src}, tolerance_deg={tolerance_deg}). Pass gravity_dir (n, 3) with the true "
            f"orientations, or record the missing faces."
        )
    mx = np.array([u[codes == 2 * j, j].mean() for j in range(3)])
    mn = np.array([u[codes == 2 * j + 1, j].mean() for j in range(3)])
    half = (mx - mn) / 2
    matrix, offset = ps.back(np.diag(1.0 / half), (mx + mn) / 2)
    return BaselineResult(
        method="six_face", matrix=matrix, offset=offset, n_iter=0, converged=True,
        message=f"min/max of the six faces ({src})",
        extra=dict(max=ps.centre + ps.radius * mx, min=ps.centre + ps.radius * mn, n_per_face=counts,
                   face_code=codes, prescale=_pinfo(ps)),
    )


def twelve_position(
    mean,
    sd=None,
    n_samples=None,
    t_s=None,
    temp_c=None,
    *,
    gravity_dir=None,
    tolerance_deg: float = 10.0,
    min_spread_ratio: float = 0.05,
    prescale: bool | str = "auto",
) -> BaselineResult:
    """12-parameter linear least squares with known orientations (jig methods).

    Parameters
    ----------
    mean : array_like, shape (n, 3), raw unit
        Still-pose mean readings.
    sd, n_samples, t_s, temp_c : array_like, optional
        Accepted for the common interface and ignored.
    gravity_dir : array_like, shape (n, 3), optional
        True direction of each pose's ideal reading (see :func:`six_face`); any
        orientations, not only axis-aligned ones. Without it, poses within
        ``tolerance_deg`` of a +-axis are auto-classified and taken as exactly axial;
        the others are dropped.
    tolerance_deg : float, deg, default 10
    min_spread_ratio : float, default 0.05
        The readings must span 3-D: smallest / largest singular value of the centred
        readings above this ratio.
    prescale : {"auto", True, False}

    Returns
    -------
    BaselineResult
        Full ``matrix`` (3, 3) (rotation included: it is referred to the frame of
        ``gravity_dir``) and ``offset`` (3,).

    Raises
    ------
    InputError
        If fewer than 4 poses with known orientation are available or their readings
        do not span 3-D (e.g. only the +-z faces), naming what is present.

    Notes
    -----
    ``g_k = M raw_k + c`` for every pose with known unit direction ``g_k``: 12 unknowns,
    linear, solved per output row by least squares; ``offset = -M^-1 c``. The
    dodecahedron procedure of the insole paper (rotate 0/90/180/270 deg about x, y, z)
    fits two 6-pose groups and weights them; with balanced groups that is the joint
    least-squares solution computed here.
    """
    m, *_ = check_poses(mean, sd, n_samples, t_s, temp_c, min_poses=1, method="twelve_position")
    ps = prescale_poses(m, prescale)
    u = ps.forward(m)
    codes, gd, src = _faces(u, gravity_dir, tolerance_deg, len(m))
    if gd is None:
        use = codes >= 0
        target = np.zeros((len(m), 3))
        j = codes[use] // 2
        target[np.flatnonzero(use), j] = np.where(codes[use] % 2 == 0, 1.0, -1.0)
    else:
        use = np.ones(len(m), dtype=bool)
        target = gd
    present = sorted({FACE_NAMES[c] for c in codes if c >= 0})
    X = np.column_stack([u[use], np.ones(int(use.sum()))])
    spread_ok = False
    if X.shape[0] >= 4:
        sv = np.linalg.svd(u[use] - u[use].mean(axis=0), compute_uv=False)
        spread_ok = sv[-1] > min_spread_ratio * sv[0]
    if not spread_ok:
        raise InputError(
            f"twelve_position needs >= 4 poses with known orientation whose readings span 3-D; "
            f"got {int(use.sum())} usable poses ({src}; faces present: {present or 'none'}, "
            f"tolerance_deg={tolerance_deg}). Pass gravity_dir (n, 3) or add poses on other faces."
        )
    W, *_ = np.linalg.lstsq(X, target[use], rcond=None)  # (4, 3)
    M = W[:3].T
    c = W[3]
    o = -np.linalg.solve(M, c)
    matrix, offset = ps.back(M, o)
    return BaselineResult(
        method="twelve_position", matrix=matrix, offset=offset, n_iter=0, converged=True,
        message=f"12-parameter linear least squares on {int(use.sum())} poses ({src})",
        extra=dict(n_used=int(use.sum()), faces_present=present, face_code=codes, prescale=_pinfo(ps)),
    )
