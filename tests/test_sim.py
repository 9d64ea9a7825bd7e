"""Tests of the insole simulator (selfcal.sim) and `selfcal simulate`."""

from __future__ import annotations

import json

import numpy as np
import pytest

from selfcal.errors import InputError
from selfcal.sim import (
    EFFECT_NAMES, SensorTruth, SimConfig, Simulation, SimTruth, canonical_params, canonical_qr, make_schedule,
)
from selfcal.sim.motion import gait_force, gravity_foot, world_to_foot
from selfcal.sim.sensor import sensor_mean
from selfcal.sim.temperature import segment_start_states, temperature_at
from selfcal.sim.wearer import GAIT, OFF, SIT, STAND, STILL, WALK

# wear from 00:06 to 23:00 (no breaks): short simulations see the worn day
WORN = {"wear_start_h": 0.1, "wear_start_sd_h": 0.0, "wear_end_h": 23.0, "breaks_per_day": 0.0}
CLEAN = {"noise_sd_mg": (0.0, 0.0, 0.0), "lsb_mg": 0.0, "range_g": 100.0}


def worn_config(**sections) -> SimConfig:
    return SimConfig().updated(day=WORN, **sections)


@pytest.fixture(scope="module")
def day_sim() -> Simulation:
    return Simulation(SimConfig(), np.random.default_rng(11), days=1.0)


@pytest.fixture(scope="module")
def day_samples(day_sim):
    return day_sim.samples()


@pytest.fixture(scope="module")
def worn_samples():
    sim = Simulation(worn_config(), np.random.default_rng(5), days=0.1)
    return sim, sim.samples()


# ----------------------------------------------------------------- reproducibility
def test_same_seed_same_data_different_seed_different_data():
    cfg = worn_config()
    a = Simulation(cfg, np.random.default_rng(3), days=0.03).samples()
    b = Simulation(cfg, np.random.default_rng(3), days=0.03).samples()
    c = Simulation(cfg, np.random.default_rng(4), days=0.03).samples()
    for name in ("t_s", "acc_g", "temp_c", "pressure_kpa", "a_true_g", "activity"):
        np.testing.assert_array_equal(getattr(a, name), getattr(b, name))
    assert len(a) != len(c) or not np.array_equal(a.acc_g, c.acc_g)


def test_iterating_twice_and_chunk_size_keep_the_schedule_and_sensor():
    sim = Simulation(worn_config(), np.random.default_rng(8), days=0.05)
    first = sim.samples()
    again = sim.samples()
    np.testing.assert_array_equal(first.acc_g, again.acc_g)
    small = list(sim.iter_samples(chunk_s=300.0))
    assert len(small) > 5
    joined = type(first).concatenate(small)
    # the radio loss and the plan do not depend on the chunking
    np.testing.assert_array_equal(joined.index, first.index)
    np.testing.assert_array_equal(joined.activity, first.activity)


# ----------------------------------------------------------------------- sensor truth
def test_truth_draw_within_limits_and_canonical_params_reconstruct_r():
    cfg = SimConfig()
    for seed in range(20):
        sim = Simulation(cfg, np.random.default_rng(seed), days=0.01)
        t = sim.truth.sensor
        assert np.all(np.abs(t.offset) <= 0.060 + 1e-12)
        q, r = canonical_qr(t.matrix)
        np.testing.assert_allclose(q @ r, t.matrix, atol=1e-14)
        np.testing.assert_allclose(q.T @ q, np.eye(3), atol=1e-14)
        assert np.all(np.diag(r) > 0)
        p = t.params()
        s = np.array([p["sx"], p["sy"], p["sz"]])
        u = np.array([[1, p["nxy"], p["nxz"]], [0, 1, p["nyz"]], [0, 0, 1]])
        np.testing.assert_allclose(np.diag(s) @ u, r, atol=1e-14)
        # scale within +-3 % and axis errors within about the two 0.6 deg draws
        assert np.all(np.abs(s - 1) < 0.031)
        assert np.all(np.abs([p["nxy"], p["nxz"], p["nyz"]]) < np.deg2rad(2.5))


def test_canonical_r_reproduces_the_norm_of_the_true_specific_force(worn_samples):
    sim = Simulation(worn_config(sensor=CLEAN, ble={"packet_loss_rate": 0.0}), np.random.default_rng(5), days=0.05)
    c = sim.samples()
    t = sim.truth.sensor
    _, r = canonical_qr(t.matrix)
    cal = (c.acc_g - t.offset) @ r.T
    np.testing.assert_allclose(np.linalg.norm(cal, axis=1), np.linalg.norm(c.a_true_g, axis=1), rtol=0, atol=1e-12)
    # and the full matrix gives back the foot-frame vector itself
    np.testing.assert_allclose((c.acc_g - t.offset) @ t.matrix.T, c.a_true_g, atol=1e-12)
    # the raw norm is off by up to several percent: calibration matters
    assert np.max(np.abs(np.linalg.norm(c.acc_g, axis=1) - np.linalg.norm(c.a_true_g, axis=1))) > 0.005


def test_canonical_params_of_a_known_matrix():
    m = np.diag([1.02, 0.99, 1.01]) @ np.array([[1, 0.01, -0.005], [0, 1, 0.003], [0, 0, 1]])
    p = canonical_params(m, np.array([0.01, -0.02, 0.03]))
    assert p["sx"] == pytest.approx(1.02) and p["sz"] == pytest.approx(1.01)
    assert p["nxy"] == pytest.approx(0.01) and p["nyz"] == pytest.approx(0.003)
    assert p["by"] == pytest.approx(-0.02)


# -------------------------------------------------------------------------- effects
def _pair(effect: str, coef, days=0.06):
    """Samples with one effect on and off, same seed, no quantisation/clipping."""
    base = worn_config(sensor={"lsb_mg": 0.0, "range_g": 100.0}, ble={"packet_loss_rate": 0.0})
    on = base.updated(effects={effect: {"enabled": True, "magnitude": (1.0, 1.0, 1.0), "coefficients": coef}})
    s_on = Simulation(on, np.random.default_rng(21), days=days)
    s_off = Simulation(base, np.random.default_rng(21), days=days)
    a, b = s_on.samples(), s_off.samples()
    np.testing.assert_array_equal(s_on.truth.sensor.matrix, s_off.truth.sensor.matrix)
    np.testing.assert_array_equal(a.a_true_g, b.a_true_g)
    return s_on.truth.sensor, a, b


def test_temperature_bias_adds_coefficient_times_delta_t():
    coef = (0.8, -0.5, 0.3)  # mg/degC
    truth, a, b = _pair("temperature_bias", coef)
    d_temp = a.temp_true_c - truth.temp_ref_c
    assert np.ptp(d_temp) > 5  # the run heats up in the shoe
    expected = 1e-3 * d_temp[:, None] * np.array(coef)
    np.testing.assert_allclose(a.acc_g - b.acc_g, expected, atol=1e-12)
    assert truth.model_params()["tbx"] == pytest.approx(0.8e-3)


def test_time_drift_bias_is_linear_in_days():
    coef = (0.3, 0.2, -0.4)  # mg/day
    truth, a, b = _pair("time_drift_bias", coef)
    expected = 1e-3 * (a.t_s[:, None] / 86400.0) * np.array(coef)
    np.testing.assert_allclose(a.acc_g - b.acc_g, expected, atol=1e-12)


def test_temperature_scale_follows_the_matrix_at_temperature():
    coef = (300.0, -200.0, 250.0)  # ppm/degC
    truth, a, b = _pair("temperature_scale", coef)
    d_temp = a.temp_true_c - truth.temp_ref_c
    k = 1e-6 * np.array(coef)
    # the noise is identical, so the difference is the noise-free difference
    minv = np.linalg.inv(truth.matrix)
    expected = (a.a_true_g / (1 + d_temp[:, None] * k) - a.a_true_g) @ minv.T
    np.testing.assert_allclose(a.acc_g - b.acc_g, expected, atol=1e-12)
    # exact inverse: a = diag(1 + k dT) M (raw - offset - noise)
    clean = truth.offset + (a.a_true_g / (1 + d_temp[:, None] * k)) @ minv.T
    back = ((1 + d_temp[:, None] * k) * ((clean - truth.offset) @ truth.matrix.T))
    np.testing.assert_allclose(back, a.a_true_g, atol=1e-12)


def test_scale_nonlinearity_is_quadratic_in_the_true_force():
    coef = (3.0, -2.0, 4.0)  # mg/g^2
    truth, a, b = _pair("scale_nonlinearity", coef)
    minv = np.linalg.inv(truth.matrix)
    expected = (1e-3 * np.array(coef) * a.a_true_g**2) @ minv.T
    np.testing.assert_allclose(a.acc_g - b.acc_g, expected, atol=1e-12)
    assert np.max(np.abs(a.a_true_g)) > 1.5  # walking reaches the quadratic range


def test_bias_step_adds_its_size_from_its_time_on():
    coef = (1.5, -2.0, 0.7)  # mg
    base = worn_config(sensor={"lsb_mg": 0.0, "range_g": 100.0}, ble={"packet_loss_rate": 0.0})
    on = base.updated(effects={"bias_step": {"enabled": True, "coefficients": coef, "at_day": 0.03}})
    s_on, s_off = Simulation(on, np.random.default_rng(21), days=0.06), Simulation(base, np.random.default_rng(21), days=0.06)
    a, b = s_on.samples(), s_off.samples()
    truth = s_on.truth.sensor
    after = a.t_s >= 0.03 * 86400
    assert 0 < after.sum() < len(after) and truth.step_at_s == 0.03 * 86400
    np.testing.assert_allclose(a.acc_g - b.acc_g, 1e-3 * after[:, None] * np.array(coef), atol=1e-12)
    # the truth is the sensor as it is at a time: before, the offset; after, with the step
    np.testing.assert_array_equal(truth.offset_at(0.0), truth.offset)
    np.testing.assert_allclose(truth.offset_at(0.05 * 86400), truth.offset + 1e-3 * np.array(coef))
    assert truth.params_at(0.05 * 86400)["bz"] == pytest.approx(truth.params()["bz"] + 0.7e-3)
    assert "sbx" not in truth.model_params()  # a step is not a term of a continuous model
    back = SensorTruth.from_dict(json.loads(json.dumps(truth.to_dict())))
    assert back.step_at_s == truth.step_at_s and back.enabled == ("bias_step",)
    assert SensorTruth.from_dict(json.loads(json.dumps(s_off.truth.sensor.to_dict()))).step_at_s == np.inf
    # the poses level has it too (a window's mean at its mid time)
    p_on, p_off = s_on.poses(), s_off.poses()
    mid_after = p_on.t_s + p_on.duration_s / 2 >= 0.03 * 86400
    d = p_on.mean_g - p_off.mean_g
    assert np.abs(d[~mid_after]).max() == 0.0
    np.testing.assert_allclose(d[mid_after], 1e-3 * np.tile(coef, (mid_after.sum(), 1)), atol=1e-12)


def test_an_effect_section_without_magnitude_keeps_its_default():
    cfg = SimConfig.from_section({"effects": {"bias_step": {"at_day": 4.0}, "temperature_cross": {"enabled": True}}})
    assert cfg.effects.bias_step.magnitude == (2.0, 2.0, 2.0) and cfg.effects.bias_step.at_day == 4.0
    assert cfg.effects.temperature_cross.magnitude == (100.0, 100.0, 100.0)
    with pytest.raises(InputError, match="at_day"):
        SimConfig.from_section({"effects": {"bias_step": {"at_day": -1.0}}})


def test_enabling_an_effect_changes_no_other_draw():
    cfg = SimConfig()
    base = Simulation(cfg, np.random.default_rng(2), days=0.02).truth.sensor
    for name in EFFECT_NAMES:
        t = Simulation(cfg.with_effects([name]), np.random.default_rng(2), days=0.02).truth.sensor
        np.testing.assert_array_equal(t.matrix, base.matrix)
        np.testing.assert_array_equal(t.offset, base.offset)
        assert t.enabled == (name,)
        mag = np.asarray(getattr(cfg.effects, name).magnitude)
        assert np.all((np.abs(t.effects[name]) >= 0.5 * mag) & (np.abs(t.effects[name]) <= mag))
        assert all(np.all(t.effects[n] == 0) for n in EFFECT_NAMES if n != name)


# --------------------------------------------------------------------- wearer / day
def test_a_day_has_rare_short_still_moments_in_the_designed_range():
    fr, per_h, p50, still = [], [], [], []
    for seed in range(6):
        s = make_schedule(SimConfig(), np.random.default_rng(seed), days=1.0)
        act = s.activity_fractions()
        worn = 1 - act["off_foot"] - act["handling"]
        assert 10 < worn * 24 < 17  # hours worn
        fr.append([act["sit"] / worn, act["stand"] / worn, (act["walk"] + act["stairs"]) / worn])
        st0, n, seg = s.still_periods()
        on = s.activity[seg] != OFF
        dur = n / s.rate_hz
        stand_dur = dur[s.activity[seg] == STAND]
        per_h.append(np.sum(on & (dur >= 2)) / (worn * 24))
        p50.append(np.median(stand_dur))
        still.append(dur[on].sum() / (worn * 86400))
        # the night is one still period, on the shoe's sole, side or back
        assert dur[~on].max() > 6 * 3600
    fr = np.mean(fr, axis=0)
    assert 0.5 < fr[0] < 0.8 and 0.12 < fr[1] < 0.35 and 0.05 < fr[2] < 0.2
    # quiet standing: a few seconds between weight shifts
    assert 2.0 < np.mean(p50) < 8.0
    assert 40 < np.mean(per_h) < 300
    assert 0.5 < np.mean(still) < 0.9


def test_walking_is_never_still_for_long_but_has_brief_mid_stance(worn_samples):
    _, c = worn_samples
    walk = c.activity == WALK
    assert walk.sum() > 2000
    assert not np.any(c.still & walk)
    a = c.a_true_g
    norm = np.linalg.norm(a[walk], axis=1)
    assert np.percentile(norm, 95) > 2.0 and np.percentile(norm, 99) < 8.0
    # near-still: every axis within 30 mg of the flat-foot gravity vector
    flat = np.all(np.abs(a - gravity_foot(np.full(len(a), np.deg2rad(-2)), np.zeros(len(a)))) < 0.08, axis=1)
    steps = np.diff(a, axis=0, prepend=a[:1])
    quiet = walk & flat & np.all(np.abs(steps) < 0.03, axis=1)
    d = np.diff(np.r_[0, quiet.astype(int), 0])
    runs = (np.flatnonzero(d == -1) - np.flatnonzero(d == 1)) / 20.0
    assert len(runs) > 0.5 * walk.sum() / 20 / 1.1  # about one per stride
    assert 0.1 <= np.median(runs) <= 0.35
    assert np.max(runs) < 1.0  # below any still detector's minimum duration


def test_gait_cycle_and_heel_strike_in_a_bout():
    from selfcal.sim.config import GaitConfig

    cfg = GaitConfig(cycle_jitter=0.0, midstance_sd_g=0.0)
    rate = 100.0
    f, phase = gait_force(2000, rate, 1.0, 1.35, 0.0, 0.0, 0.0, False, cfg, np.random.default_rng(0))
    # heel strikes where the phase wraps: 20 strides in 20 s
    hs = np.flatnonzero(np.diff(phase) < -0.5)
    assert len(hs) == 20
    np.testing.assert_allclose(np.diff(hs) / rate, 1.0, atol=0.02)
    # the impact is the largest vertical force, right after heel strike
    peak = np.argmax(np.linalg.norm(f, axis=1))
    assert phase[peak] < 0.05 or phase[peak] > 0.98
    assert np.max(np.linalg.norm(f, axis=1)) > 2.5
    # mid-stance: flat foot, 1 g along z
    mid = (phase > 0.2) & (phase < 0.35)
    np.testing.assert_allclose(f[mid], np.tile([0, 0, 1.0], (mid.sum(), 1)), atol=1e-9)


def test_orientation_helpers():
    g = gravity_foot(np.deg2rad([0, 90, 0, 0]), np.deg2rad([0, 0, 90, 180]))
    np.testing.assert_allclose(g, [[0, 0, 1], [1, 0, 0], [0, 1, 0], [0, 0, -1]], atol=1e-12)
    th, ph = np.deg2rad([10.0, -30.0]), np.deg2rad([5.0, 120.0])
    np.testing.assert_allclose(world_to_foot(np.tile([0, 0, 1.0], (2, 1)), th, ph), gravity_foot(th, ph), atol=1e-12)


# --------------------------------------------------------------------------- pressure
def test_pressure_follows_the_activity(worn_samples, day_samples):
    _, c = worn_samples
    p = c.pressure_kpa
    stand_still = (c.activity == STAND) & c.still
    walk = c.activity == WALK
    assert p[stand_still].sum(axis=1).mean() > 60
    # steady when standing still: slow sway of a few % only
    rel_sd = p[stand_still].std(axis=0) / p[stand_still].mean(axis=0)
    assert np.all(rel_sd[[0, 2]] < 0.5)
    # walking: every channel swings between near zero (swing) and above standing
    assert np.all(np.percentile(p[walk], 10, axis=0) < 2.0)
    assert np.percentile(p[walk][:, 0], 99) > p[stand_still][:, 0].mean()
    # off the foot: near zero
    off = day_samples.activity == OFF
    assert np.all(day_samples.pressure_kpa[off].mean(axis=0) < 1.5)
    assert np.all(day_samples.pressure_kpa >= 0)


# ------------------------------------------------------------------------ temperature
def test_closed_form_temperature_matches_the_ode():
    dt = 0.5
    tau = np.arange(0, 3600, dt)
    ones = np.ones_like(tau)
    temp, heat = temperature_at(tau, 20.0 * ones, 1.0 * ones, 31.0 * ones, 4.0 * ones, 600.0 * ones,
                                900.0 * ones, np.ones_like(tau, bool))
    # explicit midpoint integration of dh = (H - h)/tau_h, dT = (A + h - T)/tau_T
    t, h = 20.0, 1.0
    for _ in range(len(tau) - 1):
        hm = h + 0.5 * dt * (4.0 - h) / 900.0
        tm = t + 0.5 * dt * (31.0 + h - t) / 600.0
        h, t = h + dt * (4.0 - hm) / 900.0, t + dt * (31.0 + hm - tm) / 600.0
    assert temp[-1] == pytest.approx(t, abs=1e-4)
    assert heat[-1] == pytest.approx(h, abs=1e-6)
    # the recurrence over segments agrees with evaluating one long segment
    t0, h0 = segment_start_states(np.array([1800.0, 1800.0, 10.0]), np.full(3, 31.0), np.full(3, 4.0),
                                  np.full(3, 600.0), np.full(3, 900.0), np.ones(3, bool), 20.0)
    at_3600, _ = temperature_at(np.array([3600.0]), np.array([20.0]), np.array([0.0]), np.array([31.0]),
                                np.array([4.0]), np.array([600.0]), np.array([900.0]), np.array([True]))
    assert t0[2] == pytest.approx(at_3600[0], abs=1e-9)
    assert t0[0] == 20.0 and h0[0] == 0.0


def test_temperature_ranges_over_a_day(day_sim, day_samples):
    c = day_samples
    t = c.temp_true_c
    amb = day_sim.schedule.days[:, 0]
    foot = day_sim.schedule.days[:, 1]
    heat = day_sim.schedule.days[:, 2]
    assert np.all((amb >= 15) & (amb <= 25)) and np.all((foot >= 28) & (foot <= 33))
    assert np.all((heat >= 2) & (heat <= 5))
    assert t.min() >= 15 - 2.5 and t.max() <= 33 + 5 + 0.1
    night = (c.t_s > 3 * 3600) & (c.t_s < 5 * 3600)
    assert np.all(np.abs(t[night] - amb[0]) < 3.0)
    worn_start = c.t_s[np.flatnonzero(c.activity != OFF)[0]]
    late = (c.activity == SIT) & (c.t_s > worn_start + 3600)
    # in the shoe: the plateau (plus walking heat); cooler only right after a shoe-off break
    assert np.mean(t[late] > 27.0) > 0.9
    assert foot[0] - 1 < np.median(t[late]) < foot[0] + heat[0] + 0.1
    # reported temperature: noisy and quantised copy
    assert np.max(np.abs(c.temp_c - t)) < 0.5


# ---------------------------------------------------------------------- radio, poses
def test_packet_loss_rate_is_honoured_per_packet():
    cfg = worn_config(ble={"packet_loss_rate": 0.1, "samples_per_packet": 4})
    sim = Simulation(cfg, np.random.default_rng(9), days=0.05)
    chunks = list(sim.iter_samples(chunk_s=123.0))  # packets straddle chunk edges
    idx = np.concatenate([c.index for c in chunks])
    total = sim.schedule.n_samples
    lost = 1 - len(idx) / total
    n_pk = total / 4
    assert abs(lost - 0.1) < 4 * np.sqrt(0.1 * 0.9 / n_pk)
    # whole packets are lost: every received packet is complete
    counts = np.bincount(idx // 4)
    assert set(np.unique(counts[counts > 0])) <= {4}
    zero = Simulation(worn_config(ble={"packet_loss_rate": 0.0}), np.random.default_rng(9), days=0.01)
    assert len(zero.samples()) == zero.schedule.n_samples


def test_poses_agree_with_the_samples_of_the_same_generator():
    cfg = worn_config()
    sim = Simulation(cfg, np.random.default_rng(4), days=0.08)
    c = sim.samples()
    poses = sim.poses()
    assert len(poses) > 50
    assert np.all(poses.duration_s >= cfg.pose_min_s) and np.all(poses.duration_s <= cfg.pose_window_s + 1e-9)
    t = c.t_s
    lo = np.searchsorted(t, poses.t_s)
    hi = np.searchsorted(t, poses.t_s + poses.duration_s)
    z = []
    for k in range(len(poses)):
        seg = c.acc_g[lo[k]:hi[k]]
        assert np.all(c.still[lo[k]:hi[k]])
        se = np.sqrt(poses.sd_g[k] ** 2 / len(seg) + (np.std(seg, axis=0) ** 2) / len(seg)) * 3
        z.append(np.abs(seg.mean(axis=0) - poses.mean_g[k]) / (se + 1e-4))
        assert abs(len(seg) - poses.n[k]) <= 0.1 * len(seg) + 3
    assert np.median(np.concatenate(z)) < 1.0
    # orientation spread: mostly flat, sitting tilts reach tens of degrees
    pitch = np.rad2deg(np.arcsin(np.clip(poses.a_true_g[:, 0], -1, 1)))
    assert np.median(np.abs(pitch)) < 10


def test_the_window_temperatures_do_not_depend_on_the_block_they_are_computed_in(monkeypatch):
    """poses() computes the windows' mean temperatures in blocks (their temporaries stay
    small): any block size gives the table of one pass, bit for bit."""
    cfg = SimConfig().with_effects(["temperature_bias", "temperature_scale"])
    whole = Simulation(cfg, np.random.default_rng(8), days=2.0).poses()
    assert len(whole) > Simulation.TEMPERATURE_BLOCK // 8
    for block in (1, 7, 1000):
        monkeypatch.setattr(Simulation, "TEMPERATURE_BLOCK", block)
        part = Simulation(cfg, np.random.default_rng(8), days=2.0).poses()
        for name in type(whole).__dataclass_fields__:
            a, b = getattr(whole, name), getattr(part, name)
            assert a.dtype == b.dtype and np.array_equal(a, b), (block, name)
    monkeypatch.setattr(Simulation, "TEMPERATURE_BLOCK", 1 << 40)  # one block
    one = Simulation(cfg, np.random.default_rng(8), days=2.0).poses()
    assert np.array_equal(one.temp_true_c, whole.temp_true_c) and np.array_equal(one.mean_g, whole.mean_g)


def test_the_pose_table_does_not_depend_on_the_block_its_windows_are_computed_in(monkeypatch):
    """poses() draws each random quantity whole, in one order, and does the arithmetic on
    the draws in place by blocks of windows (POSE_BLOCK): any block size gives the table of
    one pass, bit for bit, with every sensor effect on (the cross-axis tempco's rows go
    through a matrix product)."""
    cfg = SimConfig().with_effects(["temperature_bias", "temperature_scale", "temperature_cross",
                                    "time_drift_bias", "scale_nonlinearity", "bias_step"])
    monkeypatch.setattr(Simulation, "POSE_BLOCK", 1 << 40)  # one block
    whole = Simulation(cfg, np.random.default_rng(9), days=2.0).poses()
    assert len(whole) > 1000
    for block in (1, 7, 1000, 1 << 15):
        monkeypatch.setattr(Simulation, "POSE_BLOCK", block)
        part = Simulation(cfg, np.random.default_rng(9), days=2.0).poses()
        for name in type(whole).__dataclass_fields__:
            a, b = getattr(whole, name), getattr(part, name)
            assert a.dtype == b.dtype and a.shape == b.shape and np.array_equal(a, b), (block, name)
    # the draws are the stream's: the sds scatter as chi-square, the means about the clean value
    assert np.all(whole.sd_g > 0) and np.all(whole.pressure_kpa >= 0)
    z = (whole.mean_g - sensor_mean(Simulation(cfg, np.random.default_rng(9), days=2.0).truth.sensor,
                                    whole.a_true_g, whole.temp_true_c, whole.t_s + whole.duration_s / 2))
    z /= np.sqrt(whole.noise_var_g2)
    assert abs(float(np.mean(z))) < 0.05 and 0.9 < float(np.std(z)) < 1.1


def test_poses_without_pressure_keep_every_other_column_bit_for_bit():
    """A replay asks for its still windows without the pressure channels (it feeds none):
    they are the windows' generator's last draws, so every other column is the same."""
    import dataclasses

    for seed in (3, 4):
        whole, lean = (Simulation(SimConfig(), np.random.default_rng(seed), days=2.0, seed=seed).poses(pressure=p)
                       for p in (True, False))
        assert lean.pressure_kpa is None and whole.pressure_kpa.shape == (len(whole), 4)
        for f in dataclasses.fields(whole):
            if f.name != "pressure_kpa":
                a, b = getattr(whole, f.name), getattr(lean, f.name)
                assert a.dtype == b.dtype and np.array_equal(a, b) and np.array_equal(np.signbit(a), np.signbit(b)), f.name


def test_a_stream_without_its_truth_sends_the_same_values():
    """A samples-level replay streams what a device sends, without the truth columns: the
    same chunks, rows and values bit for bit; the truth is None, and stays None when such
    chunks are split and joined."""
    sims = [Simulation(SimConfig(), np.random.default_rng(8), days=0.3, seed=8) for _ in range(2)]
    full = list(sims[0].iter_samples(chunk_s=1800))
    lean = list(sims[1].iter_samples(chunk_s=1800, truth=False))
    assert len(full) == len(lean) > 3
    for a, b in zip(full, lean):
        for name in ("t_s", "acc_g", "temp_c", "pressure_kpa"):
            x, y = getattr(a, name), getattr(b, name)
            assert x.dtype == y.dtype and np.array_equal(x, y) and np.array_equal(np.signbit(x), np.signbit(y)), name
        assert b.a_true_g is None and b.index is None and b.still is None and a.index is not None
    head, tail = lean[1].split(float(lean[1].t_s[len(lean[1]) // 2]))
    joined = type(head).concatenate([head, tail])
    assert 0 < len(head) < len(lean[1]) and tail.activity is None and np.array_equal(joined.acc_g, lean[1].acc_g)
    assert joined.temp_true_c is None


def test_the_schedule_table_by_column_is_the_table_by_row():
    """The planner's rows are read by column (each a contiguous array) when the schedule is
    finished: the same values as the table by row; a selection of rows that are the first
    ones is a slice (a view), any other the boolean mask itself."""
    from selfcal.sim import wearer

    b = wearer._Builder(SimConfig(), np.random.default_rng(3))
    b.add_block(np.random.default_rng(4).normal(size=(5, len(wearer._COLUMNS))))
    b.rows.append(tuple(range(len(wearer._COLUMNS))))
    b.add_block(np.random.default_rng(5).normal(size=(3, len(wearer._COLUMNS))))
    b.rows.append(tuple(range(len(wearer._COLUMNS), 2 * len(wearer._COLUMNS))))
    cols = b.columns()
    assert all(c.flags.c_contiguous for c in cols) and np.array_equal(cols, b.table().T)
    assert np.shares_memory(cols, b.columns())  # the builder's buffer itself, not a copy
    assert np.array_equal(wearer._Builder(SimConfig(), np.random.default_rng(3)).columns(),
                          np.empty((len(wearer._COLUMNS), 0)))
    keep = np.array([True, True, True, False, False])
    assert wearer._rows_kept(keep) == slice(0, 3)
    assert wearer._rows_kept(np.ones(4, bool)) == slice(0, 4)
    odd = np.array([True, False, True])
    assert wearer._rows_kept(odd) is odd


def test_a_plan_with_segments_dropped_in_its_middle_keeps_every_other_row_as_it_was():
    """Segments shorter than half a sample (and those past the end) are dropped when a plan
    is finished; the kept rows' columns are compacted in place: each column of the schedule
    is the planned table's column with those rows removed, in order."""
    from selfcal.sim import wearer

    cfg = SimConfig()
    rng = np.random.default_rng(12)
    rows = rng.normal(size=(40, len(wearer._COLUMNS)))
    rows[:, 0] = rng.uniform(1.0, 100.0, 40)  # durations, s
    rows[[3, 17, 18, 30], 0] = 0.01  # shorter than half a sample at 20 Hz: dropped
    rows[:, 1] = 1.0  # an activity code
    b = wearer._Builder(cfg, np.random.default_rng(13))
    b.add_block(rows[:25].copy())
    b.add_block(rows[25:].copy())
    total_s = float(np.sum(rows[:36, 0]))  # the last rows lie past the end
    s = wearer._finish(b, cfg, 20.0, total_s, np.full((2, 3), 20.0))
    t_start = np.r_[0.0, np.cumsum(rows[:, 0])[:-1]]
    i0 = np.rint(t_start * 20.0).astype(np.int64)
    i1 = np.rint(np.minimum(t_start + rows[:, 0], total_s) * 20.0).astype(np.int64)
    keep = (t_start < total_s) & (i1 > i0)
    assert 0 < keep.sum() < 36 and not keep[[3, 17]].any()
    for name, col in (("pitch0", 3), ("roll0", 4), ("pitch1", 5), ("roll1", 6), ("sd_g", 7), ("cycle_s", 8),
                      ("climb", 11)):
        assert np.array_equal(getattr(s, name), rows[keep, col]), name
    assert np.array_equal(s.load, rows[keep][:, 12:16]) and np.array_equal(s.start, i0[keep])
    assert np.array_equal(s.n, (i1 - i0)[keep]) and np.array_equal(s.still_id, rows[keep, 16].astype(np.int64))


# ------------------------------------------------------------------ config and truth
def test_config_validation_and_toml_defaults():
    from selfcal.config import load_config, section

    assert SimConfig.from_section(section(load_config(), "sim")) == SimConfig()
    with pytest.raises(InputError, match=r"\[sim\]\.ble\.rate"):
        SimConfig.from_section({"ble": {"rate": 20}})
    with pytest.raises(InputError, match="packet_loss_rate"):
        SimConfig.from_section({"ble": {"packet_loss_rate": 1.5}})
    with pytest.raises(InputError, match="unknown effect"):
        SimConfig().with_effects(["magnetism"])
    # ranges drawn from uniformly, and durations the planner can alternate: refused by name
    # (numpy's uniform would raise on some of them deep in a plan; numba's does not check)
    for bad, field in (({"posture": {"sit_heel_pitch_deg": [35.0, 10.0]}}, "sit_heel_pitch_deg"),
                       ({"posture": {"sit_toes_pitch_deg": [-1e308, 1e308]}}, "sit_toes_pitch_deg"),
                       ({"posture": {"sit_crossed_roll_deg": [15.0, float("inf")]}}, "sit_crossed_roll_deg"),
                       ({"temperature": {"foot_c": [33.0, 28.0]}}, "foot_c"),
                       ({"posture": {"stand_quiet": {"median_s": 1e-300, "gsd": 1.0, "min_s": 1e-300,
                                                     "max_s": 1e-300}}}, r"stand_quiet\.min_s"),
                       ({"activity": {"sit": {"median_s": 600, "gsd": float("nan"), "min_s": 60,
                                              "max_s": 10800}}}, r"sit\.gsd")):
        with pytest.raises(InputError, match=field):
            SimConfig.from_section(bad)
    assert SimConfig.from_section({"posture": {"sit_heel_pitch_deg": [20.0, 20.0]}}).posture.sit_heel_pitch_deg == (
        20.0, 20.0)


def test_truth_round_trip(tmp_path):
    sim = Simulation(SimConfig().with_effects(["temperature_bias"]), np.random.default_rng(1), days=0.02, seed=1)
    path = tmp_path / "t.json"
    sim.truth.write_json(path)
    back = SimTruth.read_json(path)
    np.testing.assert_array_equal(back.sensor.matrix, sim.truth.sensor.matrix)
    assert back.sensor.enabled == ("temperature_bias",)
    assert back.config == sim.truth.config and back.seed == 1
    d = json.loads(path.read_text())
    assert set(d["params"]) == {"bx", "by", "bz", "sx", "sy", "sz", "nxy", "nxz", "nyz"}
    assert d["effects"]["temperature_bias"]["unit"] == "mg/degC"


# -------------------------------------------------------------------------------- CLI
def test_cli_writes_samples_and_truth(tmp_path, capsys):
    from selfcal.cli import main
    from selfcal.io import read_recording

    out = tmp_path / "day.csv"
    rc = main(["simulate", "--days", "0.01", "--seed", "7", "--out", str(out), "--effects",
               "temperature_bias,time_drift_bias", "--json"])
    assert rc == 0
    summary = json.loads(capsys.readouterr().out)
    rec = read_recording(out)
    assert rec.kind == "samples" and rec.unit == "g" and rec.pressure.shape[1] == 4
    assert len(rec) == summary["rows"] > 0.9 * 0.01 * 86400 * 20
    truth = json.loads((tmp_path / "day.truth.json").read_text())
    assert truth["seed"] == 7 and truth["kind"] == "samples"
    assert truth["effects"]["temperature_bias"]["enabled"] and not truth["effects"]["temperature_scale"]["enabled"]
    # the file holds what the library produces for the same seed
    cfg = SimConfig().with_effects(["temperature_bias", "time_drift_bias"])
    ref = Simulation(cfg, np.random.default_rng(7), days=0.01).samples()
    # exactly: the sensor's 1/256-g steps in 8 decimals (a rounded level is an error that
    # repeats at every window of a posture, not noise)
    np.testing.assert_array_equal(rec.acc, ref.acc_g)

    out2 = tmp_path / "poses.csv"
    assert main(["simulate", "--days", "0.02", "--seed", "7", "--out", str(out2), "--kind", "poses"]) == 0
    rp = read_recording(out2)
    assert rp.kind == "poses" and len(rp) > 10 and rp.n is not None
    assert (tmp_path / "poses.truth.json").exists()
    capsys.readouterr()
    assert main(["simulate", "--days", "0.01", "--seed", "1", "--out", str(out), "--effects", "bogus"]) == 2
    assert "unknown effect" in capsys.readouterr().err


def test_the_efficient_reference_knows_a_simulated_step():
    """bench/consistency.py's CRLB and oracle for a stepped device: the model plus the step
    at its true time, so the oracle's final error is small against the sensor as it now is
    (one offset fitted across a 1-2 mg step would be far off)."""
    from selfcal.scoring import TruthScorer, efficient_reference

    cfg = SimConfig().updated(effects={"bias_step": {"at_day": 2.0}}).with_effects(["bias_step"])
    sim = Simulation(cfg, np.random.default_rng(4), days=4, seed=4)
    truth = {**sim.truth.sensor.to_dict(), "format": "selfcal-sim-truth v1"}
    poses = sim.poses()
    ref = efficient_reference("affine9", truth, poses, 4 * 86400.0)
    assert np.isfinite(ref["crlb_mg"]) and ref["oracle_mg"] < 1.0
    # the calibration that was true before the step is further off the sensor as it now is
    scorer = TruthScorer(truth, "affine9")
    assert scorer.sphere_rms_mg(scorer.truth_u, 4 * 86400.0) > 1.5 * ref["oracle_mg"]


def test_the_planners_scalar_nonneg_is_numpys_maximum_with_zero():
    """The postures are drawn in plain floats; their clamp must give np.maximum's bits."""
    from selfcal.sim.wearer import _nonneg

    values = [-0.0, 0.0, -1.0, 2.0, float("nan"), float("inf"), -float("inf"), 5e-324, -5e-324, -1e-300]
    for v in values:
        want = float(np.maximum(np.array([v] * 33), 0.0)[7])  # the array loop, as the planner used
        got = _nonneg(v)
        assert np.signbit(got) == np.signbit(want) and (got == want or (got != got and want != want)), v


def test_simulated_acceleration_crosses_the_ble_codec_unchanged():
    """The simulated sensor quantises in 12-bit counts at +-8 g (1/256 g), a whole number of
    the BLE codec's 1/4096 g units, as a real insole's firmware sends its counts: so what the
    gateway decodes is bit for bit what the simulator made. With a step that is not (the
    rounded 3.91 mg used before), the codec re-quantised every level by up to 0.12 mg, the
    same way for every window at a posture: a coherent error that moved the demo's insole-02
    (seed 1) to 16.1 mg over the whole sphere against 6.2 mg predicted, where the simulator's
    own stream gives 6.2 mg."""
    from selfcal.gateway import codec

    assert SimConfig().sensor.lsb_mg * codec.ACC_COUNTS_PER_G / 1000.0 == 16.0
    sim = Simulation(worn_config(), np.random.default_rng(5), days=0.1)
    ch = sim.samples()
    n = len(ch.t_s) - len(ch.t_s) % 19
    assert n > 100_000
    decoded = []
    for lo in range(0, n, 19):
        sl = slice(lo, lo + 19)
        packet = codec.decode_packet(codec.encode_packet(lo, ch.acc_g[sl], ch.pressure_kpa[sl], float(ch.temp_c[lo])))
        decoded.append(packet.acc_g)
    acc = np.concatenate(decoded)
    assert np.abs(ch.acc_g[:n]).max() > 1.0  # gait: the whole range, not one posture's levels
    np.testing.assert_array_equal(acc, ch.acc_g[:n])


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_the_gait_attitude_curves_are_numpys_interpolation_bit_for_bit(seed, monkeypatch):
    """The toe-off and heel-strike curves take one floor on the uniform grid instead of two
    of np.interp's binary searches: the same values to the last bit, at the grid's points,
    between them, beyond both ends, and in walking and stairs bouts."""
    from selfcal.sim import motion
    from selfcal.sim.config import GaitConfig

    rng = np.random.default_rng(seed)
    last = len(motion._GRID) - 1
    grid = np.arange(last + 1, dtype=float)
    x = np.concatenate([rng.uniform(-3.0, last + 3.0, 200_000), grid, grid + 1e-9, grid - 1e-9,
                        [0.0, -0.0, float(last), np.nextafter(last, 0), np.nextafter(last, 2 * last), 1e6, -1e6]])
    got = motion._attitude_curves(x)
    for g, curve in zip(got, (motion._TO_CURVE, motion._HS_CURVE)):
        assert np.array_equal(g.view(np.int64), np.interp(x, grid, curve).view(np.int64))
    bouts = [(1500, 1.1, 0.0, False), (900, 1.3, 1.0, True), (700, 1.2, -1.0, True)]
    made = {}
    for impl in ("floor", "interp"):
        if impl == "interp":
            monkeypatch.setattr(motion, "_attitude_curves", lambda gi: tuple(
                np.interp(gi, grid, c) for c in (motion._TO_CURVE, motion._HS_CURVE)))
        made[impl] = [motion.gait_force(n, 20.0, cyc, 1.3, 0.0, climb, 0.05, stairs, GaitConfig(),
                                        np.random.default_rng(seed))[0] for n, cyc, climb, stairs in bouts]
    for a, b in zip(made["floor"], made["interp"]):
        assert np.array_equal(a.view(np.int64), b.view(np.int64))
