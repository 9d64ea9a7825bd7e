"""Tests for selfcal.attitude: tilt from gravity and the Madgwick IMU filter."""

from __future__ import annotations

import numpy as np
import pytest

from selfcal.attitude import (
    MadgwickFilter,
    gravity_from_quaternion,
    gravity_from_roll_pitch_rad,
    madgwick_imu,
    quaternion_from_euler_rad,
    quaternion_to_euler_rad,
    roll_pitch_deg,
    roll_pitch_rad,
    tilt_error_rad,
)
from selfcal.errors import InputError

RATE_HZ = 100.0


def _smooth_motion(n: int, rate_hz: float = RATE_HZ):
    """Closed-form roll/pitch sinusoids at constant yaw, with matching body rates.

    Returns t_s (n,), roll_rad (n,), pitch_rad (n,), gyro_rad_s (n, 3) where the
    gyro is the Z-Y-X body rate for yaw_dot = 0: p = roll_dot,
    q = pitch_dot cos(roll), r = -pitch_dot sin(roll).
    """
    t = np.arange(n) / rate_hz
    roll = 0.6 * np.sin(2 * np.pi * 0.3 * t) + 0.2
    pitch = 0.4 * np.sin(2 * np.pi * 0.17 * t + 1.0)
    roll_dot = 0.6 * 2 * np.pi * 0.3 * np.cos(2 * np.pi * 0.3 * t)
    pitch_dot = 0.4 * 2 * np.pi * 0.17 * np.cos(2 * np.pi * 0.17 * t + 1.0)
    gyro = np.stack([roll_dot, pitch_dot * np.cos(roll), -pitch_dot * np.sin(roll)], axis=1)
    return t, roll, pitch, gyro


# ----------------------------------------------------------------------------- tilt from gravity


@pytest.mark.parametrize(
    ("gravity", "roll_deg", "pitch_deg"),
    [
        ((0.0, 0.0, 1.0), 0.0, 0.0),
        ((0.0, 1.0, 0.0), 90.0, 0.0),
        ((0.0, 0.0, -1.0), 180.0, 0.0),
        ((-1.0, 0.0, 0.0), 0.0, 90.0),
        ((1.0, 0.0, 0.0), 0.0, -90.0),
        ((0.0, 0.5, np.sqrt(3) / 2), 30.0, 0.0),
        ((-0.5, 0.0, np.sqrt(3) / 2), 0.0, 30.0),
        ((0.0, -0.98, 0.98), -45.0, 0.0),  # scale does not matter (norm 1.386 g)
    ],
)
def test_static_tilt_known_vectors(gravity, roll_deg: float, pitch_deg: float) -> None:
    roll, pitch = roll_pitch_deg(gravity)
    assert float(roll) == pytest.approx(roll_deg, abs=1e-12)
    assert float(pitch) == pytest.approx(pitch_deg, abs=1e-12)


def test_static_tilt_grid_round_trip() -> None:
    roll, pitch = np.meshgrid(np.radians(np.arange(-175, 180, 5.0)), np.radians(np.arange(-85, 90, 5.0)))
    gravity = gravity_from_roll_pitch_rad(roll.ravel(), pitch.ravel()) * 0.97  # uncalibrated-looking norm
    roll_back, pitch_back = roll_pitch_rad(gravity)
    np.testing.assert_allclose(roll_back, roll.ravel(), atol=1e-12)
    np.testing.assert_allclose(pitch_back, pitch.ravel(), atol=1e-12)
    # the quaternion path agrees: gravity of q(roll, pitch, any yaw) is the same vector
    q = quaternion_from_euler_rad(roll.ravel(), pitch.ravel(), 1.234)
    np.testing.assert_allclose(gravity_from_quaternion(q), gravity / 0.97, atol=1e-12)
    r2, p2, y2 = quaternion_to_euler_rad(q)
    np.testing.assert_allclose(np.c_[r2, p2], np.c_[roll.ravel(), pitch.ravel()], atol=1e-12)
    np.testing.assert_allclose(y2, 1.234, atol=1e-12)


def test_zero_vector_gives_nan_and_bad_shape_raises() -> None:
    roll, pitch = roll_pitch_rad(np.array([[0.0, 0.0, 0.0], [0.0, 0.0, 1.0]]))
    assert np.isnan(roll[0]) and np.isnan(pitch[0]) and roll[1] == 0.0
    with pytest.raises(InputError, match=r"gravity_g must have shape \(n, 3\)"):
        roll_pitch_rad(np.zeros((4, 2)))


# ----------------------------------------------------------------------------- Madgwick filter


def test_filter_static_tilt_is_exact() -> None:
    g = gravity_from_roll_pitch_rad(np.radians(-35.0), np.radians(20.0))
    f = MadgwickFilter().estimate(np.tile(g, (300, 1)), np.zeros((300, 3)), rate_hz=RATE_HZ)
    np.testing.assert_allclose(f.roll_deg_, -35.0, atol=1e-9)
    np.testing.assert_allclose(f.pitch_deg_, 20.0, atol=1e-9)


@pytest.mark.parametrize(
    ("axis", "rate_dps", "duration_s"),
    [(0, 45.0, 2.0), (0, -120.0, 1.0), (1, 30.0, 2.0), (2, 90.0, 1.0)],
)
def test_constant_rate_integrates_to_the_right_angle(axis: int, rate_dps: float, duration_s: float) -> None:
    n = int(duration_s * RATE_HZ) + 1
    t = np.arange(n) / RATE_HZ
    angle = np.radians(rate_dps) * t
    zeros = np.zeros(n)
    euler = [zeros, zeros, zeros]
    euler[axis] = angle  # single-axis rotation: body rate == Euler rate
    gyro = np.zeros((n, 3))
    gyro[:, axis] = rate_dps
    acc = gravity_from_quaternion(quaternion_from_euler_rad(*euler))
    expected = [0.0, 0.0, 0.0]
    expected[axis] = rate_dps * duration_s
    # pure gyro integration (beta = 0) reaches the angle up to the Euler-step error
    f0 = MadgwickFilter(beta=0.0).estimate(acc, gyro, t_s=t)
    np.testing.assert_allclose([f0.roll_deg_[-1], f0.pitch_deg_[-1], f0.yaw_deg_[-1]], expected, atol=0.01)
    # with the accelerometer step the estimate may lead by at most one sample of
    # rotation (the gradient compares q[k-1] with acc[k], as in Madgwick's code)
    f = MadgwickFilter(beta=0.033).estimate(acc, gyro, t_s=t)
    final = np.array([f.roll_deg_[-1], f.pitch_deg_[-1], f.yaw_deg_[-1]])
    lead = (final - expected) * np.sign(rate_dps)
    assert np.all(lead >= -0.01) and np.all(lead <= abs(rate_dps) / RATE_HZ + 0.01), final


def test_gyro_bias_compensation_reduces_tilt_error() -> None:
    rng = np.random.default_rng(11)
    n = 6000  # 60 s still at a tilt
    q_true = quaternion_from_euler_rad(np.radians(20.0), np.radians(-10.0))
    g = gravity_from_quaternion(q_true)
    acc = g + rng.normal(0.0, 0.005, (n, 3))
    bias_dps = np.array([1.5, -1.0, 0.5])
    gyro = bias_dps + rng.normal(0.0, 0.2, (n, 3))

    def tilt_err_deg(zeta: float) -> tuple[np.ndarray, MadgwickFilter]:
        f = MadgwickFilter(beta=0.01, zeta=zeta, q0=q_true).estimate(acc, gyro, rate_hz=RATE_HZ)
        return np.degrees(tilt_error_rad(f.quaternion_, q_true))[n // 2:], f

    err_off, _ = tilt_err_deg(0.0)
    err_on, f_on = tilt_err_deg(0.01)
    assert err_on.mean() < 0.2 * err_off.mean()
    assert err_on.max() < 0.5
    # the bias component perpendicular to gravity is observable and is learnt
    perp = lambda b: b - np.dot(b, g) * g  # noqa: E731
    np.testing.assert_allclose(perp(f_on.gyro_bias_dps_[-1]), perp(bias_dps), atol=0.15)


def test_converges_from_wrong_initial_attitude() -> None:
    n = 1000
    q_true = quaternion_from_euler_rad(np.radians(40.0), np.radians(-25.0))
    acc = np.tile(gravity_from_quaternion(q_true), (n, 1))
    gyro = np.zeros((n, 3))
    f = MadgwickFilter(beta=0.1, q0=[1.0, 0.0, 0.0, 0.0]).estimate(acc, gyro, rate_hz=RATE_HZ)
    err_deg = np.degrees(tilt_error_rad(f.quaternion_, q_true))
    assert err_deg[0] > 40.0
    # the normalised gradient step corrects at 2*beta rad/s, then chatters within
    # about 2*beta*dt (0.11 deg here)
    chatter_deg = np.degrees(2 * 0.1 / RATE_HZ)
    assert err_deg[n // 2:].max() < 1.2 * chatter_deg
    assert f.roll_deg_[-1] == pytest.approx(40.0, abs=0.15)
    assert f.pitch_deg_[-1] == pytest.approx(-25.0, abs=0.15)


def test_tracks_smooth_motion_with_noise() -> None:
    rng = np.random.default_rng(3)
    t, roll, pitch, gyro = _smooth_motion(3000)
    acc = gravity_from_roll_pitch_rad(roll, pitch) + rng.normal(0, 0.01, (t.size, 3))
    gyro_dps = np.degrees(gyro) + rng.normal(0, 0.3, gyro.shape)
    q_true = quaternion_from_euler_rad(roll, pitch)
    err_deg = np.degrees(tilt_error_rad(MadgwickFilter(beta=0.033).estimate(acc, gyro_dps, t_s=t).quaternion_, q_true))
    gyro_only_deg = np.degrees(tilt_error_rad(MadgwickFilter(beta=0.0).estimate(acc, gyro_dps, t_s=t).quaternion_, q_true))
    assert err_deg[100:].max() < 1.0  # after 1 s of settling from the noisy first sample
    assert np.median(err_deg) < 0.5 * np.median(gyro_only_deg)


def test_kernel_chunking_does_not_change_the_result() -> None:
    rng = np.random.default_rng(4)
    _, roll, pitch, gyro = _smooth_motion(1000)
    acc = gravity_from_roll_pitch_rad(roll, pitch) + rng.normal(0, 0.01, (1000, 3))
    gyro = gyro + np.radians(0.5)
    dt = np.full(1000, 1.0 / RATE_HZ)
    q_all, b_all = madgwick_imu(gyro, acc, dt, beta=0.05, zeta=0.02)
    q_a, b_a = madgwick_imu(gyro[:377], acc[:377], dt[:377], beta=0.05, zeta=0.02)
    q_b, b_b = madgwick_imu(gyro[377:], acc[377:], dt[377:], beta=0.05, zeta=0.02, q0=q_a[-1], gyro_bias0_rad_s=b_a[-1])
    np.testing.assert_array_equal(np.vstack([q_a, q_b]), q_all)
    np.testing.assert_array_equal(np.vstack([b_a, b_b]), b_all)
    assert np.any(b_all[-1] != 0.0)


def test_ahrs_madgwick_gives_the_same_quaternions() -> None:
    ahrs_filters = pytest.importorskip("ahrs.filters")
    rng = np.random.default_rng(8)
    n = 1500
    _, roll, pitch, gyro = _smooth_motion(n)
    gyro = gyro + rng.normal(0, 0.005, gyro.shape)  # ahrs skips samples with an exactly zero gyro
    acc = gravity_from_roll_pitch_rad(roll, pitch) + rng.normal(0, 0.02, (n, 3))
    q0 = quaternion_from_euler_rad(0.3, -0.2, 0.1)
    ref = ahrs_filters.Madgwick(gyr=gyro, acc=acc, frequency=RATE_HZ, gain=0.041, q0=q0).Q
    ours = MadgwickFilter(beta=0.041, q0=q0).estimate(acc, np.degrees(gyro), rate_hz=RATE_HZ).quaternion_
    np.testing.assert_allclose(ours, ref, atol=1e-9)


@pytest.mark.parametrize(
    ("kwargs", "estimate_kwargs", "needle"),
    [
        ({"beta": -0.1}, {"rate_hz": 100.0}, "beta must be"),
        ({"zeta": float("nan")}, {"rate_hz": 100.0}, "zeta must be"),
        ({"q0": [0, 0, 0, 0]}, {"rate_hz": 100.0}, "q0 must be"),
        ({}, {}, "exactly one of t_s"),
        ({}, {"rate_hz": 100.0, "t_s": np.arange(5.0)}, "exactly one of t_s"),
        ({}, {"rate_hz": 0.0}, "rate_hz must be"),
        ({}, {"t_s": np.array([0.0, 0.1, 0.05, 0.2, 0.3])}, "t_s decreases at row 2"),
        ({}, {"t_s": np.arange(4.0)}, r"t_s must be finite with shape \(5,\)"),
    ],
)
def test_filter_validates_inputs(kwargs: dict, estimate_kwargs: dict, needle: str) -> None:
    acc = np.tile([0.0, 0.0, 1.0], (5, 1))
    with pytest.raises(InputError, match=needle):
        MadgwickFilter(**kwargs).estimate(acc, np.zeros((5, 3)), **estimate_kwargs)


def test_filter_rejects_bad_arrays() -> None:
    acc = np.tile([0.0, 0.0, 1.0], (5, 1))
    with pytest.raises(InputError, match="both have shape"):
        MadgwickFilter().estimate(acc, np.zeros((4, 3)), rate_hz=RATE_HZ)
    gyro = np.zeros((5, 3))
    gyro[3, 1] = np.inf
    with pytest.raises(InputError, match="gyro_dps has a NaN/inf value at row 3"):
        MadgwickFilter().estimate(acc, gyro, rate_hz=RATE_HZ)


def test_estimate_does_not_change_parameters() -> None:
    f = MadgwickFilter(beta=0.05, zeta=0.01)
    before = dict(vars(f))
    f.estimate(np.tile([0.0, 0.0, 1.0], (10, 1)), np.ones((10, 3)), rate_hz=RATE_HZ)
    assert {k: vars(f)[k] for k in before} == before
    assert f.quaternion_.shape == (10, 4) and f.gyro_bias_dps_.shape == (10, 3)
