"""Small still-pose generators for tests (not the simulator: no wearer, no time)."""

from __future__ import annotations

import numpy as np

from selfcal.fit import PoseData
from selfcal.models import ErrorModel


def random_truth(rng: np.random.Generator, model: ErrorModel | None = None) -> np.ndarray:
    """Consumer-MEMS-like affine9 truth in g units: bias +-60 mg, scale +-3 %, axes +-0.6 deg."""
    model = model or ErrorModel("affine9")
    th = model.nominal()
    th[0:3] = rng.uniform(-0.06, 0.06, 3)
    th[3:6] = 1.0 + rng.uniform(-0.03, 0.03, 3)
    if model.base == "affine9":
        th[6:9] = np.deg2rad(rng.uniform(-0.6, 0.6, 3))
    return th


def spread_directions(rng: np.random.Generator, n: int) -> np.ndarray:
    """n unit gravity directions spread over the whole sphere (random), (n, 3)."""
    d = rng.normal(size=(n, 3))
    return d / np.linalg.norm(d, axis=1, keepdims=True)


def tilted(rng, axis_dirs: np.ndarray, tilt_deg: float) -> np.ndarray:
    """Directions (n,3) perturbed by random tilts of up to tilt_deg."""
    d = axis_dirs + rng.normal(0, np.deg2rad(tilt_deg) / 2, axis_dirs.shape)
    return d / np.linalg.norm(d, axis=1, keepdims=True)


def insole_like_directions(rng, n_axis: int = 6, n_other: int = 18) -> np.ndarray:
    """The insole paper's pose mix: a few near axis-aligned poses (O_cor) plus others."""
    faces = np.vstack([np.eye(3), -np.eye(3)])
    ax = tilted(rng, faces[rng.permutation(6)[: n_axis] if n_axis <= 6 else rng.integers(0, 6, n_axis)], 3.0)
    return np.vstack([ax, spread_directions(rng, n_other)])


def flat_directions(rng, n: int, tilt_deg: float = 5.0) -> np.ndarray:
    """Near-flat insole poses: z up, small random tilts, (n, 3)."""
    return tilted(rng, np.tile([0.0, 0.0, 1.0], (n, 1)), tilt_deg)


def poses_from_truth(rng, model: ErrorModel, theta, directions, sample_sd_g=2e-3, count=40, temp_c=None, t_s=None) -> PoseData:
    """Raw pose means whose true specific force is ``directions`` (unit, g).

    The raw reading is the inverse of the model's linear part (effects of ``model``
    are inverted by a fixed-point iteration), plus the noise of a mean of ``count``
    samples of per-axis sd ``sample_sd_g``.
    """
    matrix, offset = model.linear(theta)
    inv = np.linalg.inv(matrix)
    raw = directions @ inv.T + offset
    if model.effects:
        for _ in range(30):  # fixed point: raw <- raw + M^-1 (a_true - a(raw))
            a = model.apply(theta, raw, temp_c, t_s)
            raw = raw + (directions - a) @ inv.T
    raw = raw + rng.normal(0, sample_sd_g / np.sqrt(count), raw.shape)
    n = len(directions)
    return PoseData(raw, np.full((n, 3), sample_sd_g), np.full(n, count), t_s, temp_c)


def sample_stream(rng, model: ErrorModel, theta, directions, still_s=4.0, move_s=1.5, rate_hz=20.0,
                  sample_sd_g=2e-3, t0_s=0.0, temp_c=None):
    """A raw 20 Hz stream: a still of ``still_s`` in each direction, separated by motion.

    Returns ``t_s (n,)``, ``raw (n, 3)`` (model's raw unit), ``temp (n,)`` or None.
    """
    matrix, offset = model.linear(theta)
    inv = np.linalg.inv(matrix)
    n_still = int(round(still_s * rate_hz))
    n_move = int(round(move_s * rate_hz))
    parts = []
    for d in directions:
        still = np.tile(d, (n_still, 1))
        move = d + rng.normal(0, 0.4, (n_move, 3))  # vigorous motion: several-g peaks
        parts += [still, move]
    a = np.vstack(parts)
    raw = a @ inv.T + offset + rng.normal(0, sample_sd_g, a.shape)
    t = t0_s + np.arange(len(a)) / rate_hz
    temp = None if temp_c is None else np.full(len(a), float(temp_c))
    return t, raw, temp


def sphere_rms_mg(model: ErrorModel, theta_est, theta_true, n=2000, seed=0) -> float:
    """RMS of ||a_cal|| - 1 (mg) over directions spread on the whole sphere (truth known)."""
    d = spread_directions(np.random.default_rng(seed), n)
    matrix, offset = model.linear(theta_true)
    raw = d @ np.linalg.inv(matrix).T + offset
    a = model.apply(theta_est, raw)
    return float(np.sqrt(np.mean((np.linalg.norm(a, axis=1) - 1) ** 2)) * 1e3)
