"""bench/diagnose_power_bound.py's MAX6 figure: the calibrated null holds its false-alarm
rate on effect-free designs, and a strong effect is named by its largest statistic."""

from __future__ import annotations

import sys
from pathlib import Path

import numpy as np
import pytest

ROOT = Path(__file__).resolve().parents[1]


def _bound():
    sys.path[:0] = [str(ROOT / "bench"), str(ROOT / "tests")]
    try:
        import diagnose_power_bound
    finally:
        del sys.path[:2]
    return diagnose_power_bound


def _case(effect: str, strength: float, seed: int):
    b = _bound()
    return (b, *b.base_fit_of_case(effect, strength, seed, 240))


@pytest.mark.parametrize("seed", [11, 12, 13])
def test_the_calibrated_null_holds_its_false_alarm_rate(seed):
    # the design of a weak case; with mu = 0 every exceedance is a false alarm
    b, fit, mean, data, sigma, mu = _case("temperature_bias", 0.06, seed)
    alphas = [0.05, 0.2]
    rates = b.max_lr_rates(fit, mean, data, sigma, np.zeros_like(mu), None, alphas, 20_000, seed)
    for a, r in zip(alphas, rates):
        # binomial sd of the two Monte-Carlo estimates (null quantile and rate), 20 000 draws each
        assert abs(r - a) < 5 * np.sqrt(2 * a * (1 - a) / 20_000), (a, r)


@pytest.mark.parametrize("effect", ["temperature_bias", "time_drift_bias", "scale_nonlinearity"])
def test_a_strong_effect_is_named_by_its_largest_statistic(effect):
    b, fit, mean, data, sigma, mu = _case(effect, 0.5, 7)
    assert float(mu @ mu) > 100  # strong: the base model cannot absorb it
    named = b.max_lr_rates(fit, mean, data, sigma, mu, effect, [0.05], 2000, 7)[0]
    other = b.max_lr_rates(fit, mean, data, sigma, mu, "temperature_cross", [0.05], 2000, 7)[0]
    assert named > 0.95 and other < 0.05
