"""Thermal soaks: coverage of the reported sd, 'none' on effect-free soaks, and what one
orientation cannot determine (synthetic generator in tests/soakgen.py, fixed seeds)."""

from __future__ import annotations

import numpy as np
import pytest

from soakgen import soak

from selfcal.soak import SoakConfig, find_soaks, fit_soak


@pytest.mark.parametrize("seed", [1, 2])
def test_bias_tempcos_within_2_sd_in_90_percent_of_200_soaks(seed):
    rng = np.random.default_rng(seed)
    z = []
    for _ in range(200):
        tb = rng.normal(0, 1e-3, 3)  # the datasheet's 1 mg/degC
        temp, mean, var, truth = soak(rng, tb_g_per_c=tb)
        fit = fit_soak(temp, mean, var, model="temperature_bias")
        assert fit.determined.all(), fit.to_dict()  # one soak determines all three bias tempcos
        z += list((fit.coef - truth["tb"]) / fit.std)
    z = np.abs(np.array(z))
    assert np.mean(z <= 2.0) >= 0.90, np.mean(z <= 2.0)
    assert np.mean(z <= 2.0) <= 0.995  # not hiding behind inflated sds either


@pytest.mark.parametrize("seed", [3, 4])
def test_effect_free_soaks_are_named_none_in_95_percent(seed):
    rng = np.random.default_rng(seed)
    named = [fit_soak(*soak(rng)[:3], model="temperature_bias").effect for _ in range(200)]
    assert np.mean([e == "none" for e in named]) >= 0.95


def test_a_real_effect_is_named():
    rng = np.random.default_rng(5)
    named = [fit_soak(*soak(rng, tb_g_per_c=[0.0, 0.0, 1e-3], dtemp_c=8.0, duration_s=1800)[:3]).effect
             for _ in range(50)]
    assert np.mean([e == "temperature_bias" for e in named]) >= 0.95


def test_what_one_orientation_cannot_determine_is_said():
    rng = np.random.default_rng(6)
    temp, mean, var, _ = soak(rng, orientation=[0.01, -0.02, 1.0], ts_per_c=[0, 0, 300e-6], dtemp_c=10.0,
                              duration_s=3600)
    scale = fit_soak(temp, mean, var, model="temperature_scale")
    d = scale.to_dict()
    assert d["determined"] == ["tsz"] and set(d["undetermined"]) == {"tsx", "tsy"}  # lying flat: only z
    both = fit_soak(temp, mean, var, model="temperature_bias+scale")
    assert len(both.undetermined_directions) >= 3  # 6 terms, 3 observable combinations
    assert any("3 combinations" in n for n in both.notes)
    tiny = fit_soak(np.linspace(25.0, 25.001, 10), mean[:10], var[:10])  # no temperature change
    assert tiny.effect == "none" and not tiny.determined.any()
    assert any("not determinable" in n for n in tiny.notes)


def test_find_soaks_splits_on_orientation_gaps_and_needs_a_temperature_change():
    rng = np.random.default_rng(7)
    t1, m1, _, _ = soak(rng, orientation=[0, 0, 1], dtemp_c=5.0, duration_s=200)
    t2, m2, _, _ = soak(rng, orientation=[1, 0, 0], dtemp_c=5.0, duration_s=200)
    flat_temp = np.full(50, 25.0)
    m3 = np.tile([0.0, 1.0, 0.0], (50, 1))
    temp = np.concatenate([t1, t2, flat_temp])
    mean = np.vstack([m1, m2, m3])
    t_s = np.arange(len(temp)) * 2.0
    runs = find_soaks(t_s, mean, temp, SoakConfig())
    assert [(r.start, r.stop) for r in runs] == [(0, len(t1)), (len(t1), len(t1) + len(t2))]
    t_gap = t_s.copy()
    t_gap[len(t1) // 2:] += 1000.0  # a gap cuts the first soak in two
    assert len(find_soaks(t_gap, mean, temp)) == 3
