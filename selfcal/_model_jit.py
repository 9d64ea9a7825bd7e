"""The error models' numba kernel (imported only through :mod:`selfcal.model_numba`): the
norm residuals and their Jacobian of ``scale6`` and ``affine9`` with any effects, in one
pass over the rows. Each value is the numpy code's expression
(:meth:`selfcal.models.ErrorModel.residual_jac`) evaluated in the same order, one rounding
per operation: no fastmath (no reassociation, no fused multiply-add), so the results are
numpy's bit for bit (checked at first use)."""

from __future__ import annotations

import math

import numba
import numpy as np

# error_model "numpy": a division by zero gives inf or NaN, as numpy does (not ZeroDivisionError)
_jit = numba.njit(cache=True, nogil=True, error_model="numpy")


@_jit
def residual_jac(theta, raw, dtemp, dtime, after, has_n, i_sb, i_tb, i_db, i_ts, i_q, i_tn, r, jac):
    """Fill ``r`` (n,) (g) and ``jac`` (n, p) for parameters ``theta`` (p,) and readings
    ``raw`` (n, 3) (normalised units).

    ``dtemp`` (n,) degC from the reference, ``dtime`` (n,) days from the reference and
    ``after`` (n,) 1.0 at or after the step, else 0.0 (each read only when its effect is
    present); ``has_n``: affine9's cross-axis terms at ``theta[6:9]``; ``i_*``: the first
    index of the effect's 3 parameters, -1 without it (``sb`` bias_step, ``tb``
    temperature_bias, ``db`` time_drift_bias, ``ts`` temperature_scale, ``q``
    scale_nonlinearity, ``tn`` temperature_cross).
    """
    n = raw.shape[0]
    has_sb, has_tb, has_db, has_ts, has_q, has_tn = i_sb >= 0, i_tb >= 0, i_db >= 0, i_ts >= 0, i_q >= 0, i_tn >= 0
    s0, s1, s2 = theta[3], theta[4], theta[5]
    n0 = n1 = n2 = 0.0
    if has_n:
        n0, n1, n2 = theta[6], theta[7], theta[8]
    for i in range(n):
        b0, b1, b2 = theta[0], theta[1], theta[2]
        if has_sb:
            st = after[i]
            b0 = b0 + st * theta[i_sb]
            b1 = b1 + st * theta[i_sb + 1]
            b2 = b2 + st * theta[i_sb + 2]
        dt = dtemp[i] if (has_tb or has_ts or has_tn) else 0.0
        if has_tb:
            b0 = b0 + dt * theta[i_tb]
            b1 = b1 + dt * theta[i_tb + 1]
            b2 = b2 + dt * theta[i_tb + 2]
        if has_db:
            dd = dtime[i]
            b0 = b0 + dd * theta[i_db]
            b1 = b1 + dd * theta[i_db + 1]
            b2 = b2 + dd * theta[i_db + 2]
        e0, e1, e2 = s0, s1, s2  # the effective scales
        f0 = f1 = f2 = 1.0
        if has_ts:
            f0 = 1.0 + dt * theta[i_ts]
            f1 = 1.0 + dt * theta[i_ts + 1]
            f2 = 1.0 + dt * theta[i_ts + 2]
            e0, e1, e2 = s0 * f0, s1 * f1, s2 * f2
        y0, y1, y2 = raw[i, 0] - b0, raw[i, 1] - b1, raw[i, 2] - b2
        if has_n:
            m0, m1, m2 = n0, n1, n2
            if has_tn:
                m0 = n0 + dt * theta[i_tn]
                m1 = n1 + dt * theta[i_tn + 1]
                m2 = n2 + dt * theta[i_tn + 2]
            z0 = y0 + (m0 * y1 + m1 * y2)
            z1 = y1 + m2 * y2
        else:
            m0 = m1 = m2 = 0.0
            z0, z1 = y0, y1
        z2 = y2
        l0, l1, l2 = e0 * z0, e1 * z1, e2 * z2
        if has_q:
            q0, q1, q2 = theta[i_q], theta[i_q + 1], theta[i_q + 2]
            a0, a1, a2 = l0 - q0 * (l0 * l0), l1 - q1 * (l1 * l1), l2 - q2 * (l2 * l2)
        else:
            a0, a1, a2 = l0, l1, l2
        norm = math.sqrt((a0 * a0 + a1 * a1) + a2 * a2)
        r[i] = norm - 1.0
        h0, h1, h2 = a0 / norm, a1 / norm, a2 / norm
        if has_q:
            w0 = h0 * (1.0 - (2.0 * q0) * l0)
            w1 = h1 * (1.0 - (2.0 * q1) * l1)
            w2 = h2 * (1.0 - (2.0 * q2) * l2)
            jac[i, i_q] = (-h0) * (l0 * l0)
            jac[i, i_q + 1] = (-h1) * (l1 * l1)
            jac[i, i_q + 2] = (-h2) * (l2 * l2)
        else:
            w0, w1, w2 = h0, h1, h2
        ws0, ws1, ws2 = w0 * e0, w1 * e1, w2 * e2
        if has_n:
            v0 = ws0
            v1 = ws1 + ws0 * m0
            v2 = ws2 + (ws0 * m1 + ws1 * m2)
        else:
            v0, v1, v2 = ws0, ws1, ws2
        jac[i, 0] = -v0
        jac[i, 1] = -v1
        jac[i, 2] = -v2
        wz0, wz1, wz2 = w0 * z0, w1 * z1, w2 * z2
        if has_ts:
            jac[i, i_ts] = (wz0 * s0) * dt
            jac[i, i_ts + 1] = (wz1 * s1) * dt
            jac[i, i_ts + 2] = (wz2 * s2) * dt
            jac[i, 3] = wz0 * f0
            jac[i, 4] = wz1 * f1
            jac[i, 5] = wz2 * f2
        else:
            jac[i, 3] = wz0
            jac[i, 4] = wz1
            jac[i, 5] = wz2
        if has_tb:
            jac[i, i_tb] = (-v0) * dt
            jac[i, i_tb + 1] = (-v1) * dt
            jac[i, i_tb + 2] = (-v2) * dt
        if has_db:
            jac[i, i_db] = (-v0) * dd
            jac[i, i_db + 1] = (-v1) * dd
            jac[i, i_db + 2] = (-v2) * dd
        if has_sb:
            jac[i, i_sb] = (-v0) * st
            jac[i, i_sb + 1] = (-v1) * st
            jac[i, i_sb + 2] = (-v2) * st
        if has_n:
            j6, j7, j8 = ws0 * y1, ws0 * y2, ws1 * y2
            jac[i, 6] = j6
            jac[i, 7] = j7
            jac[i, 8] = j8
            if has_tn:
                jac[i, i_tn] = j6 * dt
                jac[i, i_tn + 1] = j7 * dt
                jac[i, i_tn + 2] = j8 * dt


@_jit
def whitened_residual_jac(theta, raw, dtemp, dtime, after, has_n, i_sb, i_tb, i_db, i_ts, i_q, i_tn, var_axis,
                          floor2, r, jac, rw, jw):
    """:func:`residual_jac`, then the residuals and Jacobian whitened by a noise whose sd
    follows the scales (:class:`selfcal.fit.NoiseModel` without ``scale_nonlinearity``):
    ``sigma = sqrt(((v0 s0² + v1 s1²) + v2 s2²) + floor2)`` per row (``var_axis`` (n, 3),
    ``floor2`` g²), ``rw = r / sigma`` (n,) and ``jw = jac / sigma - (rw / sigma) dsigma``
    (n, p), ``dsigma`` nonzero at the scales only: numpy's expressions, in its order (the
    other columns subtract ``t * 0.0`` as numpy does, so the signs of zeros agree)."""
    residual_jac(theta, raw, dtemp, dtime, after, has_n, i_sb, i_tb, i_db, i_ts, i_q, i_tn, r, jac)
    s0, s1, s2 = theta[3], theta[4], theta[5]
    ss0, ss1, ss2 = s0 * s0, s1 * s1, s2 * s2
    p = jac.shape[1]
    for i in range(raw.shape[0]):
        v0, v1, v2 = var_axis[i, 0], var_axis[i, 1], var_axis[i, 2]
        sig = math.sqrt(((v0 * ss0 + v1 * ss1) + v2 * ss2) + floor2)
        x = r[i] / sig
        rw[i] = x
        t = x / sig
        for k in range(p):
            jw[i, k] = jac[i, k] / sig - t * 0.0
        jw[i, 3] = jac[i, 3] / sig - t * ((v0 * s0) / sig)
        jw[i, 4] = jac[i, 4] / sig - t * ((v1 * s1) / sig)
        jw[i, 5] = jac[i, 5] / sig - t * ((v2 * s2) / sig)
