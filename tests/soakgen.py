"""A synthetic thermal-soak generator, independent of the simulator (for tests/test_soak.py).

One soak: a device lying still in a random orientation for 20 s to 2 h while its
temperature relaxes exponentially over a span of 2-15 degC; 2-s still windows at
20-100 Hz. The calibrated window means carry the true temperature terms, white noise
(2 mg per sample, so sd/sqrt(n) per window) and a slowly correlated settling
component (AR(1), 0.15 mg, lag-1 0.6) that the fit is *not* told about.
"""

from __future__ import annotations

import numpy as np


def soak(rng: np.random.Generator, *, tb_g_per_c=None, ts_per_c=None, orientation=None,
         dtemp_c=None, duration_s=None, rate_hz=None, window_s: float = 2.0, resettle_deg: float = 0.0):
    """Returns (temp_c (k,), mean_g (k, 3), var_g2 (k,), truth dict).

    ``resettle_deg``: the device also turns slowly by this angle about a random
    horizontal axis, following the cooling curve (a band settling on a table)."""
    duration = float(duration_s if duration_s is not None else np.exp(rng.uniform(np.log(20.0), np.log(7200.0))))
    rate = float(rate_hz if rate_hz is not None else rng.choice([20.0, 50.0, 100.0]))
    span = float(dtemp_c if dtemp_c is not None else rng.uniform(2.0, 15.0))
    g = np.asarray(orientation, float) if orientation is not None else rng.normal(size=3)
    g = g / np.linalg.norm(g)
    tb = np.zeros(3) if tb_g_per_c is None else np.asarray(tb_g_per_c, float)
    ts = np.zeros(3) if ts_per_c is None else np.asarray(ts_per_c, float)
    k = max(int(duration / window_s), 5)
    t = (np.arange(k) + 0.5) * window_s
    tau = rng.uniform(0.3, 1.5) * duration
    shape = np.exp(-t / tau)
    temp = 25.0 + span * (shape - shape.min()) / (shape.max() - shape.min()) * rng.choice([-1.0, 1.0])
    dt = temp - temp.mean()
    n = window_s * rate
    white = 2e-3 / np.sqrt(n)
    settle = np.zeros((k, 3))
    e = rng.normal(0, 0.15e-3 * np.sqrt(1 - 0.6**2), (k, 3))
    settle[0] = rng.normal(0, 0.15e-3, 3)
    for i in range(1, k):  # a test generator, not a hot path
        settle[i] = 0.6 * settle[i - 1] + e[i]
    gk = np.tile(g, (k, 1))
    if resettle_deg:
        axis = np.cross(g, rng.normal(size=3))
        axis /= np.linalg.norm(axis)
        ang = np.deg2rad(resettle_deg) * (temp - temp[0]) / (temp[-1] - temp[0])
        # Rodrigues: rotate g about the axis (perpendicular to g) by each window's angle
        gk = g * np.cos(ang)[:, None] + np.cross(axis, g) * np.sin(ang)[:, None]
    mean = gk + dt[:, None] * (tb - g * ts) + rng.normal(0, white, (k, 3)) + settle  # selfcal.soak's convention
    return temp, mean, np.full(k, white**2), {"g": g, "tb": tb, "ts": ts, "span": span, "duration": duration}
