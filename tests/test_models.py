import numpy as np
import pytest

from selfcal.errors import InputError
from selfcal.models import EFFECT_PARAMS, ErrorModel, Normalizer

ALL = ["scale6", "affine9", "seed9", "affine9+" + "+".join(EFFECT_PARAMS)] + [f"affine9+{e}" for e in EFFECT_PARAMS]


@pytest.mark.parametrize("name", ALL)
@pytest.mark.parametrize("seed", [0, 1, 2])
def test_jacobian_matches_finite_differences(name, seed):
    rng = np.random.default_rng(seed)
    m = ErrorModel(name)
    theta = m.nominal() + rng.normal(0, 0.05, m.n_params)
    raw = rng.normal(0, 1, (25, 3))
    temp = rng.uniform(10, 40, 25)
    t = rng.uniform(0, 30 * 86400, 25)
    r, jac = m.residual_jac(theta, raw, temp, t)
    assert np.allclose(r, m.residuals(theta, raw, temp, t))
    num = np.empty_like(jac)
    h = 1e-6
    for j in range(m.n_params):
        e = np.zeros(m.n_params)
        e[j] = h
        num[:, j] = (m.residuals(theta + e, raw, temp, t) - m.residuals(theta - e, raw, temp, t)) / (2 * h)
    assert np.max(np.abs(jac - num)) < 1e-7


@pytest.mark.parametrize("name", ["scale6", "affine9"])
def test_vector_named_roundtrip_and_linear_part(name):
    rng = np.random.default_rng(3)
    m = ErrorModel(name)
    theta = m.nominal() + rng.normal(0, 0.02, m.n_params)
    assert np.array_equal(m.from_dict(m.to_dict(theta)), theta)
    matrix, offset = m.linear(theta)
    raw = rng.normal(size=(10, 3))
    assert np.allclose(m.apply(theta, raw), (raw - offset) @ matrix.T)


def test_from_linear_drops_rotation_only():
    rng = np.random.default_rng(4)
    m = ErrorModel("affine9")
    theta = m.nominal() + rng.normal(0, 0.02, 9)
    matrix, offset = m.linear(theta)
    q, _ = np.linalg.qr(rng.normal(size=(3, 3)))
    back = m.from_linear(q @ matrix, offset)
    assert np.allclose(back, theta, atol=1e-12)
    raw = rng.normal(size=(50, 3))
    assert np.allclose(np.linalg.norm(m.apply(back, raw), axis=1), np.linalg.norm((raw - offset) @ (q @ matrix).T, axis=1))


def test_seed9_rotation_angles_change_norm_only_at_second_order():
    """The seed's skew T is a first-order rotation: norms move by O(angle^2), so the
    three angles have (numerically) zero Jacobian at T = I: norms cannot determine them."""
    rng = np.random.default_rng(5)
    m = ErrorModel("seed9")
    theta = m.nominal()
    theta[0:3] = rng.normal(0, 0.03, 3)
    theta[3:6] = 1 + rng.normal(0, 0.02, 3)
    raw = rng.normal(size=(40, 3))
    _, jac = m.residual_jac(theta, raw)
    assert np.max(np.abs(jac[:, 6:9])) < 1e-12
    for eps in (1e-2, 1e-3):
        t2 = theta.copy()
        t2[6:9] = eps
        dr = np.abs(m.residuals(t2, raw) - m.residuals(theta, raw)).max()
        assert dr < 5 * eps**2  # second order


def test_unknown_model_and_bad_shapes_are_named():
    with pytest.raises(InputError, match="unknown base model"):
        ErrorModel("affine12")
    with pytest.raises(InputError, match="unknown effect"):
        ErrorModel("affine9+humidity")
    m = ErrorModel("affine9")
    with pytest.raises(InputError, match="raw"):
        m.apply(m.nominal(), np.zeros((4, 2)))
    with pytest.raises(InputError, match="temp_c"):
        ErrorModel("affine9+temperature_bias").apply(np.r_[m.nominal(), 0, 0, 0], np.zeros((4, 3)))


def test_normalizer_roundtrip():
    m = ErrorModel("affine9+temperature_bias+time_drift_bias")
    nz = Normalizer((32768.0, 32000.0, 33000.0), 4050.0)
    rng = np.random.default_rng(6)
    th = m.nominal() + rng.normal(0, 0.01, m.n_params)
    raw_th = nz.theta_to_raw(m, th)
    assert np.allclose(nz.theta_to_u(m, raw_th), th)
    raw = rng.normal(0, 4000, (20, 3)) + 32768
    a_u = m.apply(th, nz.to_u(raw), np.full(20, 30.0), np.full(20, 1e5))
    a_raw = m.apply(raw_th, raw, np.full(20, 30.0), np.full(20, 1e5))
    assert np.allclose(a_u, a_raw)


def test_temperature_cross_inverts_the_simulator_exactly_and_its_jacobian_is_right():
    """affine9+temperature_cross with the simulated device's parameters maps the simulator's
    raw readings back to 1 g (the cross-axis terms vary with temperature), and the analytic
    Jacobian matches finite differences; scale6 has no cross-axis terms to vary."""
    from selfcal.sim.config import SimConfig
    from selfcal.sim.sensor import draw_sensor_truth, sensor_mean

    rng = np.random.default_rng(3)
    truth = draw_sensor_truth(SimConfig().with_effects(["temperature_cross"]), rng)
    a = rng.normal(size=(500, 3))
    a /= np.linalg.norm(a, axis=1, keepdims=True)
    temp = rng.uniform(5, 45, 500)
    raw = sensor_mean(truth, a, temp, np.zeros(500))
    model = ErrorModel("affine9+temperature_cross", truth.temp_ref_c)
    theta = model.from_dict({**truth.params(), **truth.model_params()})
    assert np.abs(model.residuals(theta, raw, temp)).max() < 1e-10
    base = ErrorModel("affine9", truth.temp_ref_c)
    assert np.abs(base.residuals(base.from_dict(truth.params()), raw)).max() > 5e-4  # the effect is there
    _, jac = model.residual_jac(theta, raw, temp)
    num = np.empty_like(jac)
    for k in range(model.n_params):
        d = np.zeros(model.n_params)
        d[k] = 1e-7
        num[:, k] = (model.residuals(theta + d, raw, temp) - model.residuals(theta - d, raw, temp)) / 2e-7
    assert np.abs(jac - num).max() < 1e-6
    with pytest.raises(InputError, match="cross-axis"):
        ErrorModel("scale6+temperature_cross")
    assert ErrorModel("affine9").takes("temperature_cross") and not ErrorModel("scale6").takes("temperature_cross")


def test_bias_step_event_jacobian_and_its_time_is_required():
    """``bias_step``: the offset moves by ``sb`` from ``t_step_s`` on (analytic Jacobian
    checked by finite differences); without a step time the model is a clear error."""
    m = ErrorModel("affine9+bias_step", 25.0, 0.0, 500.0)
    assert m.param_names[-3:] == ("sbx", "sby", "sbz")
    rng = np.random.default_rng(3)
    raw = rng.normal(size=(60, 3))
    raw /= np.linalg.norm(raw, axis=1, keepdims=True)
    t = np.linspace(0.0, 1000.0, 60)
    th = m.nominal()
    th[0:3], th[9:12] = [0.01, 0.0, 0.02], [0.01, -0.02, 0.005]
    _, jac = m.residual_jac(th, raw, None, t)
    eye = np.eye(m.n_params) * 1e-7
    num = np.column_stack([(m.residuals(th + e, raw, None, t) - m.residuals(th - e, raw, None, t)) / 2e-7 for e in eye])
    np.testing.assert_allclose(jac, num, atol=1e-7)
    before = t < 500.0  # the step changes nothing before its time
    base = m.with_effects(())
    np.testing.assert_allclose(m.apply(th, raw[before], None, t[before]), base.apply(th[:9], raw[before]))
    with pytest.raises(InputError, match="t_step_s"):
        ErrorModel("affine9+bias_step")
