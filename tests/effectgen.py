"""Hidden-effect pose sets for the diagnosis tests (independent of the fit's model forms).

An insole worn for ``days``: still poses on the foot (standing flat, sitting tilted;
in-shoe temperature 28-33 degC) and off the foot (shoe on the floor: flat, on its side,
upside down; ambient 15-25 degC). The sensor is a general affine map (misalignment
included) plus one hidden effect in its *forward* (physical) form:

* temperature_bias   raw += k [mg/degC] * (T - 25) on one axis
* temperature_scale  the axis gain is multiplied by (1 + k [ppm/degC] * (T - 25))
* time_drift_bias    raw += k [mg/day] * t_days on one axis
* scale_nonlinearity raw += k [mg/g^2] * a_axis^2 on one axis (a: true specific force)
* temperature_cross  raw_i += k [ppm/degC] * (T - 25) * a_j: axis i picks up axis j's signal
                     (i != j, either order: a package that bends as it warms)
* bias_step          raw += k [mg] on one axis from a time uniform in the middle half of
                     the span on (a shock or a battery change)
"""

from __future__ import annotations

import numpy as np

EFFECT_RANGES = {  # realistic magnitudes (the ranges), physical units
    "temperature_bias": (0.06, 0.3),      # mg/degC
    "temperature_scale": (75.0, 225.0),   # ppm/degC
    "time_drift_bias": (0.2, 0.6),        # mg/day
    "scale_nonlinearity": (1.5, 4.0),     # mg/g^2
}
NAMES = tuple(EFFECT_RANGES) + (None,)
#: Effects the diagnosis treats as secondary (named only when clearly better than a primary).
SECONDARY_RANGES = {"temperature_cross": (100.0, 300.0)}  # ppm/degC
#: Events: a change at one time (diagnose scans for it).
EVENT_RANGES = {"bias_step": (1.0, 5.0)}  # mg


def _rot(axis, ang):
    c, s = np.cos(ang), np.sin(ang)
    i, j = [k for k in range(3) if k != axis]
    r = np.eye(3)
    r[i, i], r[i, j], r[j, i], r[j, j] = c, -s, s, c
    return r


def insole_directions_and_temps(rng, n):
    """Gravity directions in the sensor frame (n,3) and temperatures (n,) degC."""
    kind = rng.choice(6, size=n, p=[0.35, 0.25, 0.15, 0.12, 0.05, 0.08])
    pitch = np.zeros(n)
    roll = np.zeros(n)
    on_foot = kind <= 1
    m = kind == 0  # standing flat
    pitch[m], roll[m] = rng.normal(0, 3, m.sum()), rng.normal(0, 3, m.sum())
    m = kind == 1  # sitting, foot tilted
    pitch[m], roll[m] = rng.uniform(-45, 25, m.sum()), rng.uniform(-25, 25, m.sum())
    m = kind == 2  # shoe flat on the floor
    pitch[m], roll[m] = rng.normal(0, 2, m.sum()), rng.normal(0, 2, m.sum())
    m = kind == 3  # shoe on its side
    pitch[m], roll[m] = rng.normal(0, 8, m.sum()), rng.choice([-1, 1], m.sum()) * rng.uniform(70, 100, m.sum())
    m = kind == 4  # upside down
    pitch[m], roll[m] = rng.normal(0, 8, m.sum()), 180 + rng.normal(0, 8, m.sum())
    m = kind == 5  # anywhere (tumbled, in a bag)
    pitch[m], roll[m] = rng.uniform(-90, 90, m.sum()), rng.uniform(-180, 180, m.sum())
    p, r = np.deg2rad(pitch), np.deg2rad(roll)
    g = np.column_stack([-np.sin(p), np.cos(p) * np.sin(r), np.cos(p) * np.cos(r)])
    temp = np.where(on_foot, rng.uniform(28, 33, n), rng.uniform(15, 25, n))
    return g, temp


def hidden_effect_case(rng, effect=None, magnitude=None, n_poses=120, days=8.0, sample_sd_g=2.5e-3, noise=True):
    """One seeded case: returns (poses dict in g, truth dict). ``noise=False``: the same case
    without its noise (drawn all the same, so every other value is the seed's)."""
    g, temp = insole_directions_and_temps(rng, n_poses)
    t_s = np.sort(rng.uniform(0, days * 86400, n_poses))
    count = rng.integers(40, 400, n_poses).astype(float)  # 2-20 s at 20 Hz
    scale = 1 + rng.uniform(-0.03, 0.03, 3)
    k = np.tril(rng.uniform(-1, 1, (3, 3)) * np.deg2rad(0.6), -1) + np.eye(3)
    rot = _rot(0, np.deg2rad(rng.uniform(-0.6, 0.6))) @ _rot(1, np.deg2rad(rng.uniform(-0.6, 0.6)))
    sens = np.diag(scale) @ k @ rot  # raw = offset + sens @ a  (sensor's forward matrix)
    offset = rng.uniform(-0.06, 0.06, 3)
    a = g  # still: specific force = gravity direction, 1 g
    lin = a @ sens.T
    axis = int(rng.integers(3))
    sign = float(rng.choice([-1.0, 1.0]))
    if effect is not None and magnitude is None:
        lo, hi = {**EFFECT_RANGES, **SECONDARY_RANGES, **EVENT_RANGES}[effect]
        magnitude = rng.uniform(lo, hi)
    coef = 0.0 if effect is None else sign * magnitude
    raw = lin + offset
    dT = temp - 25.0
    if effect == "temperature_bias":
        raw[:, axis] += 1e-3 * coef * dT
    elif effect == "temperature_scale":
        raw[:, axis] += lin[:, axis] * 1e-6 * coef * dT
    elif effect == "time_drift_bias":
        raw[:, axis] += 1e-3 * coef * t_s / 86400
    elif effect == "scale_nonlinearity":
        raw[:, axis] += 1e-3 * coef * a[:, axis] ** 2
    elif effect == "temperature_cross":
        other = (axis + 1 + int(rng.integers(2))) % 3
        raw[:, axis] += 1e-6 * coef * dT * a[:, other]
    elif effect == "bias_step":
        t_step = rng.uniform(0.25, 0.75) * days * 86400
        raw[:, axis] += 1e-3 * coef * (t_s >= t_step)
    raw += noise * rng.normal(0, 1, raw.shape) * sample_sd_g / np.sqrt(count)[:, None]
    poses = {"mean": raw, "sd": np.full((n_poses, 3), sample_sd_g), "count": count, "t_s": t_s, "temp_c": temp}
    truth = {"effect": effect, "axis": "xyz"[axis], "coef": coef, "magnitude": magnitude,
             "sens": sens, "offset": offset.copy()}  # raw = offset + sens @ a (+ the effect)
    if effect == "bias_step":
        truth["t_step_s"] = t_step
        truth["offset_after"] = offset + 1e-3 * coef * np.eye(3)[axis]
    return poses, truth
