"""Attitude: roll/pitch from gravity, and a Madgwick IMU orientation filter.

Conventions
-----------
* Sensor frame S, earth frame E with z up. At rest, a calibrated accelerometer
  reads the specific force ``+1 g`` along the sensor axis that points up, so a
  sensor lying flat reads ``(0, 0, 1)`` g.
* Quaternions are ``(w, x, y, z)`` (scalar first, Hamilton product) and rotate
  sensor-frame vectors into the earth frame; the gravity direction seen by the
  sensor is then ``R(q).T @ (0, 0, 1)``. This is the convention of Madgwick's
  report and of ``ahrs.filters.Madgwick``.
* Euler angles are Z-Y-X (yaw, pitch, roll): a static sensor with roll ``phi`` and
  pitch ``theta`` reads ``(-sin(theta), sin(phi) cos(theta), cos(phi) cos(theta))`` g.
* Radians inside (``*_rad``), degrees at the edges (``*_deg``).

The filter follows the seed ``madgwick-orientation-filter.txt`` (digest: method.md
section 5): gyro integration ``q_dot = 1/2 q (x) (0, w)``, one normalised
gradient-descent step on the accelerometer objective with gain ``beta``, and the
gyro bias drift compensation ``w_eps = 2 q* (x) s_hat``, ``w_b = zeta * sum(w_eps dt)``,
``w_c = w - w_b``. No magnetometer: yaw is gyro-only and drifts.
"""

from __future__ import annotations

import math

import numpy as np

from selfcal.errors import InputError

__all__ = [
    "MadgwickFilter",
    "gravity_from_quaternion",
    "gravity_from_roll_pitch_rad",
    "madgwick_imu",
    "quaternion_from_euler_rad",
    "quaternion_to_euler_rad",
    "roll_pitch_deg",
    "roll_pitch_rad",
    "tilt_error_rad",
]


# --------------------------------------------------------------------------- tilt from gravity


def _as_vectors(name: str, value, width: int) -> np.ndarray:
    arr = np.asarray(value, dtype=np.float64)
    if arr.ndim == 0 or arr.shape[-1] != width:
        raise InputError(f"{name} must have shape (n, {width}) or ({width},), got {arr.shape}")
    return arr


def roll_pitch_rad(gravity_g) -> tuple[np.ndarray, np.ndarray]:
    """Roll and pitch from gravity vectors measured in the sensor frame.

    Parameters
    ----------
    gravity_g : array_like, shape (n, 3) or (3,), g
        Calibrated specific force at rest (any positive scale: only the direction
        is used).

    Returns
    -------
    roll_rad : ndarray, shape (n,) or (), rad
        ``atan2(gy, gz)`` in (-pi, pi].
    pitch_rad : ndarray, shape (n,) or (), rad
        ``atan2(-gx, hypot(gy, gz))`` in [-pi/2, pi/2].
        Both are NaN for a zero vector.

    Examples
    --------
    >>> r, p = roll_pitch_rad([0.1, 0.5, 0.5])
    >>> round(float(np.degrees(r)), 6), round(float(np.degrees(p)), 6)
    (45.0, -8.049467)
    """
    g = _as_vectors("gravity_g", gravity_g, 3)
    gx, gy, gz = g[..., 0], g[..., 1], g[..., 2]
    roll = np.arctan2(gy, gz)
    pitch = np.arctan2(-gx, np.hypot(gy, gz))
    zero = ~(np.abs(g).max(axis=-1) > 0)
    if np.any(zero):
        roll = np.where(zero, np.nan, roll)
        pitch = np.where(zero, np.nan, pitch)
    return roll, pitch


def roll_pitch_deg(gravity_g) -> tuple[np.ndarray, np.ndarray]:
    """Roll and pitch in degrees (see :func:`roll_pitch_rad`).

    Parameters
    ----------
    gravity_g : array_like, shape (n, 3) or (3,), g
        Calibrated specific force at rest.

    Returns
    -------
    roll_deg : ndarray, shape (n,) or (), deg
    pitch_deg : ndarray, shape (n,) or (), deg
    """
    roll, pitch = roll_pitch_rad(gravity_g)
    return np.degrees(roll), np.degrees(pitch)


def gravity_from_roll_pitch_rad(roll_rad, pitch_rad) -> np.ndarray:
    """Unit gravity vector a static sensor reads at a given roll and pitch.

    Parameters
    ----------
    roll_rad : array_like, shape (n,) or (), rad
    pitch_rad : array_like, shape (n,) or (), rad

    Returns
    -------
    gravity_g : ndarray, shape (n, 3) or (3,), g
        ``(-sin(pitch), sin(roll) cos(pitch), cos(roll) cos(pitch))``.
    """
    roll = np.asarray(roll_rad, dtype=np.float64)
    pitch = np.asarray(pitch_rad, dtype=np.float64)
    cp = np.cos(pitch)
    return np.stack([-np.sin(pitch) * np.ones_like(roll), np.sin(roll) * cp, np.cos(roll) * cp], axis=-1)


# --------------------------------------------------------------------------- quaternions


def quaternion_from_euler_rad(roll_rad, pitch_rad, yaw_rad=0.0) -> np.ndarray:
    """Quaternion of Z-Y-X Euler angles (sensor to earth).

    Parameters
    ----------
    roll_rad, pitch_rad, yaw_rad : array_like, shape (n,) or (), rad
        Broadcast together.

    Returns
    -------
    q : ndarray, shape (n, 4) or (4,)
        Unit quaternion ``(w, x, y, z)``.
    """
    r, p, y = np.broadcast_arrays(*(np.asarray(a, dtype=np.float64) * 0.5 for a in (roll_rad, pitch_rad, yaw_rad)))
    cr, sr, cp, sp, cy, sy = np.cos(r), np.sin(r), np.cos(p), np.sin(p), np.cos(y), np.sin(y)
    return np.stack(
        [
            cr * cp * cy + sr * sp * sy,
            sr * cp * cy - cr * sp * sy,
            cr * sp * cy + sr * cp * sy,
            cr * cp * sy - sr * sp * cy,
        ],
        axis=-1,
    )


def quaternion_to_euler_rad(q) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Z-Y-X Euler angles of quaternions.

    Parameters
    ----------
    q : array_like, shape (n, 4) or (4,)
        Quaternions ``(w, x, y, z)``; normalised here.

    Returns
    -------
    roll_rad : ndarray, shape (n,) or (), rad
    pitch_rad : ndarray, shape (n,) or (), rad
        Clipped to [-pi/2, pi/2] (gimbal lock at the ends).
    yaw_rad : ndarray, shape (n,) or (), rad
    """
    q = _as_vectors("q", q, 4)
    q = q / np.linalg.norm(q, axis=-1, keepdims=True)
    w, x, y, z = q[..., 0], q[..., 1], q[..., 2], q[..., 3]
    roll = np.arctan2(2.0 * (w * x + y * z), 1.0 - 2.0 * (x * x + y * y))
    pitch = np.arcsin(np.clip(2.0 * (w * y - x * z), -1.0, 1.0))
    yaw = np.arctan2(2.0 * (w * z + x * y), 1.0 - 2.0 * (y * y + z * z))
    return roll, pitch, yaw


def gravity_from_quaternion(q) -> np.ndarray:
    """Unit gravity direction in the sensor frame, ``R(q).T @ (0, 0, 1)``.

    Parameters
    ----------
    q : array_like, shape (n, 4) or (4,)
        Quaternions ``(w, x, y, z)``; normalised here.

    Returns
    -------
    gravity_g : ndarray, shape (n, 3) or (3,), g
        What a perfect static accelerometer at attitude `q` reads.
    """
    q = _as_vectors("q", q, 4)
    q = q / np.linalg.norm(q, axis=-1, keepdims=True)
    w, x, y, z = q[..., 0], q[..., 1], q[..., 2], q[..., 3]
    return np.stack([2.0 * (x * z - w * y), 2.0 * (w * x + y * z), 1.0 - 2.0 * (x * x + y * y)], axis=-1)


def tilt_error_rad(q_est, q_true) -> np.ndarray:
    """Angle between the gravity directions of two attitudes (yaw ignored).

    Parameters
    ----------
    q_est, q_true : array_like, shape (n, 4) or (4,)
        Quaternions ``(w, x, y, z)``.

    Returns
    -------
    tilt_error_rad : ndarray, shape (n,) or (), rad
        In [0, pi]; the roll/pitch error that matters for gravity-based calibration.
    """
    a, b = gravity_from_quaternion(q_est), gravity_from_quaternion(q_true)
    cross = np.linalg.norm(np.cross(a, b), axis=-1)
    return np.arctan2(cross, np.sum(a * b, axis=-1))


# --------------------------------------------------------------------------- Madgwick kernel


def madgwick_imu(gyro_rad_s, acc_g, dt_s, beta, zeta=0.0, q0=(1.0, 0.0, 0.0, 0.0), gyro_bias0_rad_s=(0.0, 0.0, 0.0)):
    """Madgwick IMU filter (gyro + accelerometer) with gyro bias drift compensation.

    Pure kernel: arrays in, arrays out. For each sample ``i``, from ``q`` (state
    before the sample):

    1. ``s = J(q).T f(q, a_i)``, normalised (``f`` the accelerometer objective of
       Madgwick eq. 25 with ``a_i`` normalised); skipped when ``|a_i| = 0``.
    2. bias: ``w_eps = vec(2 q* (x) s)``, ``b += zeta * w_eps * dt_i``;
       ``w_c = w_i - b``.
    3. ``q_dot = 1/2 q (x) (0, w_c) - beta * s``; ``q += q_dot * dt_i``; normalise.

    Parameters
    ----------
    gyro_rad_s : ndarray, shape (n, 3), rad/s
        Angular rate in the sensor frame.
    acc_g : ndarray, shape (n, 3), g
        Specific force (only its direction is used; any unit works).
    dt_s : ndarray, shape (n,), s
        Time step integrated at each sample (``t_i - t_{i-1}``; 0 for a sample that
        is the initial state itself). Must be >= 0.
    beta : float, rad/s
        Gradient-step gain (Madgwick's gyro measurement error).
    zeta : float, 1/s
        Gyro bias drift gain; 0 disables the compensation.
    q0 : array_like, shape (4,)
        Attitude before the first sample, ``(w, x, y, z)``; normalised here.
    gyro_bias0_rad_s : array_like, shape (3,), rad/s
        Bias estimate before the first sample.

    Returns
    -------
    q : ndarray, shape (n, 4)
        Attitude after each sample (unit quaternions, sensor to earth).
    gyro_bias_rad_s : ndarray, shape (n, 3), rad/s
        Bias estimate after each sample. ``(q[-1], gyro_bias_rad_s[-1])`` is the
        state to continue with on the next chunk (chunking does not change the
        result).

    Notes
    -----
    The gradient compares the previous estimate ``q[k-1]`` with ``acc[k]`` (as in
    Madgwick's and ``ahrs``'s code), so during rotation the estimate can lead the
    truth by up to one sample of rotation; at rest it chatters within about
    ``2 * beta * dt`` rad because the gradient step is normalised.

    The recursion is sequential. The loop runs on plain Python floats (no numpy
    call inside), about 60 floating-point operations per sample: roughly 2-4 us per
    sample on one core of a laptop, i.e. 0.1-0.2 s for 50 000 samples. Inputs are
    validated by :class:`MadgwickFilter`; this kernel does not repeat the checks.

    References
    ----------
    S. O. H. Madgwick, A. J. L. Harrison, R. Vaidyanathan, "Estimation of IMU and
    MARG orientation using a gradient descent algorithm", ICORR 2011.
    """
    gyro = np.asarray(gyro_rad_s, dtype=np.float64)
    acc = np.asarray(acc_g, dtype=np.float64)
    norm = np.linalg.norm(acc, axis=1, keepdims=True)
    acc_unit = np.divide(acc, norm, out=np.zeros_like(acc), where=norm > 0)  # zero row: no correction
    n_rows = gyro.shape[0]
    q_arr = np.asarray(q0, dtype=np.float64)
    q_arr = q_arr / np.linalg.norm(q_arr)
    q_w, q_x, q_y, q_z = (float(v) for v in q_arr)
    b_x, b_y, b_z = (float(v) for v in np.asarray(gyro_bias0_rad_s, dtype=np.float64))
    beta = float(beta)
    zeta = float(zeta)
    out_q = [None] * n_rows
    out_b = [None] * n_rows
    rows = zip(gyro.tolist(), acc_unit.tolist(), np.asarray(dt_s, dtype=np.float64).tolist())
    for i, ((g_x, g_y, g_z), (a_x, a_y, a_z), dt) in enumerate(rows):
        # objective f (eq. 25) and gradient J^T f (eq. 34)
        s_w = s_x = s_y = s_z = 0.0
        if a_x or a_y or a_z:
            f_1 = 2.0 * (q_x * q_z - q_w * q_y) - a_x
            f_2 = 2.0 * (q_w * q_x + q_y * q_z) - a_y
            f_3 = 1.0 - 2.0 * (q_x * q_x + q_y * q_y) - a_z
            s_w = -2.0 * q_y * f_1 + 2.0 * q_x * f_2
            s_x = 2.0 * q_z * f_1 + 2.0 * q_w * f_2 - 4.0 * q_x * f_3
            s_y = -2.0 * q_w * f_1 + 2.0 * q_z * f_2 - 4.0 * q_y * f_3
            s_z = 2.0 * q_x * f_1 + 2.0 * q_y * f_2
            s_norm = math.sqrt(s_w * s_w + s_x * s_x + s_y * s_y + s_z * s_z)
            if s_norm > 1e-12:
                s_w /= s_norm
                s_x /= s_norm
                s_y /= s_norm
                s_z /= s_norm
            else:
                s_w = s_x = s_y = s_z = 0.0
        # gyro bias drift: w_eps = 2 q* (x) s_hat (vector part); w_b += zeta w_eps dt
        if zeta:
            k = 2.0 * zeta * dt
            b_x += k * (q_w * s_x - q_x * s_w - q_y * s_z + q_z * s_y)
            b_y += k * (q_w * s_y + q_x * s_z - q_y * s_w - q_z * s_x)
            b_z += k * (q_w * s_z - q_x * s_y + q_y * s_x - q_z * s_w)
        w_x, w_y, w_z = g_x - b_x, g_y - b_y, g_z - b_z
        # q_dot = 1/2 q (x) (0, w_c) - beta s_hat
        d_w = 0.5 * (-q_x * w_x - q_y * w_y - q_z * w_z) - beta * s_w
        d_x = 0.5 * (q_w * w_x + q_y * w_z - q_z * w_y) - beta * s_x
        d_y = 0.5 * (q_w * w_y - q_x * w_z + q_z * w_x) - beta * s_y
        d_z = 0.5 * (q_w * w_z + q_x * w_y - q_y * w_x) - beta * s_z
        q_w += d_w * dt
        q_x += d_x * dt
        q_y += d_y * dt
        q_z += d_z * dt
        inv = 1.0 / math.sqrt(q_w * q_w + q_x * q_x + q_y * q_y + q_z * q_z)
        q_w *= inv
        q_x *= inv
        q_y *= inv
        q_z *= inv
        out_q[i] = (q_w, q_x, q_y, q_z)
        out_b[i] = (b_x, b_y, b_z)
    return np.array(out_q, dtype=np.float64).reshape(n_rows, 4), np.array(out_b, dtype=np.float64).reshape(n_rows, 3)


# --------------------------------------------------------------------------- filter class


class MadgwickFilter:
    """Madgwick IMU orientation filter over a whole recording.

    Parameters
    ----------
    beta : float, rad/s
        Gradient-step gain. Madgwick suggests ``sqrt(3/4) * gyro error``;
        0.033 (the ``ahrs`` IMU default) suits a still-to-walking insole.
    zeta : float, 1/s
        Gyro bias drift gain (``sqrt(3/4) * gyro drift rate``); 0 disables it.
    q0 : array_like, shape (4,), or None
        Attitude at the first sample ``(w, x, y, z)``; None: from the first
        accelerometer sample (roll and pitch, yaw 0).
    gyro_bias0_dps : array_like, shape (3,), deg/s, or None
        Initial gyro bias estimate; None: zero.

    Attributes
    ----------
    quaternion_ : ndarray, shape (n, 4)
        Attitude at each sample, sensor to earth ``(w, x, y, z)``.
    gyro_bias_dps_ : ndarray, shape (n, 3), deg/s
        Gyro bias estimate at each sample (constant if ``zeta == 0``).
    roll_deg_, pitch_deg_, yaw_deg_ : ndarray, shape (n,), deg
        Z-Y-X Euler angles of ``quaternion_`` (yaw is gyro-only: it drifts).
    dt_s_ : ndarray, shape (n,), s
        Time step used at each sample (``dt_s_[0] == 0``: ``q0`` is the attitude at
        the first sample).

    Examples
    --------
    >>> acc_g = np.tile([0.0, 0.5, 0.866025], (200, 1))
    >>> f = MadgwickFilter(beta=0.05).estimate(acc_g, np.zeros((200, 3)), rate_hz=100.0)
    >>> round(float(f.roll_deg_[-1]), 3)
    30.0
    """

    def __init__(self, beta: float = 0.033, zeta: float = 0.0, q0=None, gyro_bias0_dps=None):
        self.beta = beta
        self.zeta = zeta
        self.q0 = q0
        self.gyro_bias0_dps = gyro_bias0_dps

    def _validate_parameters(self) -> None:
        for name in ("beta", "zeta"):
            value = getattr(self, name)
            if not (isinstance(value, (int, float, np.floating)) and math.isfinite(value) and value >= 0):
                raise InputError(f"{name} must be a finite number >= 0, got {value!r}")
        if self.q0 is not None:
            q0 = np.asarray(self.q0, dtype=np.float64)
            if q0.shape != (4,) or not np.all(np.isfinite(q0)) or not np.linalg.norm(q0) > 0:
                raise InputError(f"q0 must be a finite non-zero quaternion of shape (4,), got {self.q0!r}")
        if self.gyro_bias0_dps is not None:
            b0 = np.asarray(self.gyro_bias0_dps, dtype=np.float64)
            if b0.shape != (3,) or not np.all(np.isfinite(b0)):
                raise InputError(f"gyro_bias0_dps must be finite with shape (3,), got {self.gyro_bias0_dps!r}")

    def estimate(self, acc_g, gyro_dps, t_s=None, rate_hz=None) -> "MadgwickFilter":
        """Run the filter over a recording.

        Other Parameters
        ----------------
        acc_g : array_like, shape (n, 3), g
            Calibrated specific force.
        gyro_dps : array_like, shape (n, 3), deg/s
            Angular rate.
        t_s : array_like, shape (n,), s, optional
            Sample times (non-decreasing). Give exactly one of `t_s` and `rate_hz`.
        rate_hz : float, Hz, optional
            Constant sample rate.

        Returns
        -------
        self : MadgwickFilter
            With the result attributes set.

        Raises
        ------
        InputError
            Naming the argument: wrong shapes, non-finite values, decreasing
            `t_s`, neither or both of `t_s`/`rate_hz`, bad parameters.
        """
        self._validate_parameters()
        acc = _as_vectors("acc_g", acc_g, 3)
        gyro = _as_vectors("gyro_dps", gyro_dps, 3)
        if acc.ndim != 2 or gyro.shape != acc.shape:
            raise InputError(f"acc_g and gyro_dps must both have shape (n, 3), got {acc.shape} and {gyro.shape}")
        for name, arr in (("acc_g", acc), ("gyro_dps", gyro)):
            if not np.all(np.isfinite(arr)):
                row = int(np.flatnonzero(~np.all(np.isfinite(arr), axis=1))[0])
                raise InputError(f"{name} has a NaN/inf value at row {row}")
        n_rows = acc.shape[0]
        if (t_s is None) == (rate_hz is None):
            raise InputError("give exactly one of t_s (sample times) and rate_hz (constant rate)")
        if t_s is not None:
            t = np.asarray(t_s, dtype=np.float64)
            if t.shape != (n_rows,) or not np.all(np.isfinite(t)):
                raise InputError(f"t_s must be finite with shape ({n_rows},), got shape {t.shape}")
            dt = np.diff(t, prepend=t[:1])
            if np.any(dt < 0):
                raise InputError(f"t_s decreases at row {int(np.flatnonzero(dt < 0)[0])}")
        else:
            if not (isinstance(rate_hz, (int, float, np.floating)) and math.isfinite(rate_hz) and rate_hz > 0):
                raise InputError(f"rate_hz must be a finite number > 0, got {rate_hz!r}")
            dt = np.full(n_rows, 1.0 / float(rate_hz))
            dt[:1] = 0.0
        self.acc_g = acc
        self.gyro_dps = gyro
        self.t_s = t_s
        self.rate_hz = rate_hz

        if self.q0 is not None:
            q0 = np.asarray(self.q0, dtype=np.float64)
        elif n_rows:
            roll, pitch = roll_pitch_rad(acc[0])
            q0 = quaternion_from_euler_rad(np.nan_to_num(roll), np.nan_to_num(pitch), 0.0)
        else:
            q0 = np.array([1.0, 0.0, 0.0, 0.0])
        b0 = np.zeros(3) if self.gyro_bias0_dps is None else np.asarray(self.gyro_bias0_dps, dtype=np.float64)
        q, bias = madgwick_imu(np.radians(gyro), acc, dt, self.beta, self.zeta, q0, np.radians(b0))
        self.dt_s_ = dt
        self.quaternion_ = q
        self.gyro_bias_dps_ = np.degrees(bias)
        roll, pitch, yaw = quaternion_to_euler_rad(q)
        self.roll_deg_, self.pitch_deg_, self.yaw_deg_ = np.degrees(roll), np.degrees(pitch), np.degrees(yaw)
        return self
