"""True specific force of the foot (g, foot frame) for still, moving and gait segments.

Foot frame: x forward toward the toes, y to the left, z up through the sole when the
foot stands flat. World frame for gait: x horizontal in the walking direction, y left,
z up. Attitude: pitch ``theta`` (> 0 toes up) then roll ``phi`` (> 0 left side up);
the specific force of gravity in the foot frame is
``(sin theta, cos theta sin phi, cos theta cos phi)`` g.

Gait template (one stride, phase ``psi`` in [0.2, 1.2), heel strike at psi = 1.0,
each stride's interval starting and ending in mid-stance where the foot is flat):

* forward position ``L * S(u)``, ``S(u) = u - sin(2 pi u) / (2 pi)``, ``u`` over
  psi in [0.40, 0.98] (push-off to terminal swing): acceleration
  ``2 pi L sin(2 pi u) / (0.58 T)^2`` (about +-2.3 g for L = 1.35 m, T = 1.05 s);
* vertical position ``H sin^4(pi u)`` over psi in [0.38, 1.0] (foot clearance), plus
  ``2 h S(u)`` on stairs (one step height h per step, two per stride);
* pitch: flat in mid-stance, toe-off ``toe_off_pitch_deg`` at psi = 0.62, heel strike
  ``heel_strike_pitch_deg`` at psi = 1.0, flat again at psi = 1.14 (PCHIP through knots);
* heel-strike impact: ``A exp(-(t - t_hs) / tau)`` upward (and half of it backward),
  ``A`` about ``impact_g`` per stride;
* mid-stance psi in [0.2, 0.38] and [1.14, 1.2]: foot flat, only ``midstance_sd_g``
  residual motion: a near-still moment of ~0.25 s (0.24 cycles) per stride, shorter than any still
  detector's minimum duration.

Moving segments are computed at ``oversample`` times the output rate and block-averaged
(the sensor's anti-alias average over one sample period).
"""

from __future__ import annotations

import numpy as np
from scipy.interpolate import PchipInterpolator
from scipy.signal import lfilter

from selfcal.sim import draw_numba
from selfcal.sim.config import GaitConfig
from selfcal.sim.draw_numba import standard_normal

G_MPS2 = 9.80665

_PSI_KNOTS = np.array([0.20, 0.38, 0.50, 0.62, 0.72, 0.85, 0.95, 1.00, 1.07, 1.14, 1.20])
# pitch knots as (fraction of toe-off pitch, fraction of heel-strike pitch)
_TO_FRAC = np.array([0, 0, 0.3, 1.0, 0.6, 0, 0, 0, 0, 0, 0])
_HS_FRAC = np.array([0, 0, 0, 0, 0, 0.5, 1.0, 1.0, 0.45, 0, 0])
_GRID = np.linspace(0.2, 1.2, 2001)
_TO_CURVE = PchipInterpolator(_PSI_KNOTS, _TO_FRAC)(_GRID)
_HS_CURVE = PchipInterpolator(_PSI_KNOTS, _HS_FRAC)(_GRID)
#: the curves' slopes between grid points (index units), as ``np.interp`` computes them
_GRID_X = np.arange(len(_GRID), dtype=float)
_TO_SLOPE = (_TO_CURVE[1:] - _TO_CURVE[:-1]) / (_GRID_X[1:] - _GRID_X[:-1])
_HS_SLOPE = (_HS_CURVE[1:] - _HS_CURVE[:-1]) / (_GRID_X[1:] - _GRID_X[:-1])


def _attitude_curves(gi: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """``np.interp(gi, arange(len(_GRID)), curve)`` of the toe-off and heel-strike curves at
    grid positions ``gi`` (m,) (index units, finite), bit for bit, with one floor for
    both instead of two binary searches: on the uniform integer grid the interval of
    ``x`` is ``floor(x)``, and the value ``slope[j] (x - j) + curve[j]`` is numpy's
    formula; outside ``[0, last]`` the end values, at ``last`` the last one."""
    last = len(_GRID) - 1
    j = np.floor(gi)
    np.clip(j, 0.0, last - 1, out=j)
    k = j.astype(np.intp)
    dx = gi - j
    right, left = gi >= last, gi < 0

    def curve_at(curve: np.ndarray, slope: np.ndarray) -> np.ndarray:
        v = slope[k] * dx + curve[k]
        v[right] = curve[last]
        v[left] = curve[0]
        return v

    return curve_at(_TO_CURVE, _TO_SLOPE), curve_at(_HS_CURVE, _HS_SLOPE)


def gravity_foot(pitch_rad: np.ndarray, roll_rad: np.ndarray) -> np.ndarray:
    """Specific force of gravity (1 g) in the foot frame.

    Parameters
    ----------
    pitch_rad, roll_rad : ndarray, shape (n,), rad

    Returns
    -------
    ndarray, shape (n, 3), g
    """
    cp = np.cos(pitch_rad)
    return np.column_stack([np.sin(pitch_rad), cp * np.sin(roll_rad), cp * np.cos(roll_rad)])


def world_to_foot(f_world: np.ndarray, pitch_rad: np.ndarray, roll_rad: np.ndarray) -> np.ndarray:
    """Rotate vectors from the world (walking) frame into the foot frame.

    Parameters
    ----------
    f_world : ndarray, shape (n, 3)
    pitch_rad, roll_rad : ndarray, shape (n,), rad

    Returns
    -------
    ndarray, shape (n, 3), same unit as ``f_world``
    """
    ct, st = np.cos(pitch_rad), np.sin(pitch_rad)
    cr, sr = np.cos(roll_rad), np.sin(roll_rad)
    fx, fy, fz = f_world[:, 0], f_world[:, 1], f_world[:, 2]
    gx = ct * fx + st * fz
    gz = -st * fx + ct * fz
    return np.column_stack([gx, cr * fy + sr * gz, -sr * fy + cr * gz])


def lowpass_noise(rng: np.random.Generator, n: int, rate_hz: float, corner_hz: float, dim: int = 3,
                  accelerate=None) -> np.ndarray:
    """Unit-variance first-order low-pass Gaussian noise.

    ``accelerate``: the draws' numba kernels (:func:`selfcal.sim.draw_numba.for_draws`:
    None takes them once loaded, False never); the same values either way.

    Returns
    -------
    ndarray, shape (n, dim), unit sd
    """
    alpha = float(np.exp(-2 * np.pi * corner_hz / rate_hz))
    gain = float(np.sqrt((1 + alpha) / (1 - alpha)))  # unit variance after the filter
    found = draw_numba.for_draws(rng, n * dim, accelerate)
    if alpha > 1e-6 and found is not None:
        return found.lowpass(rng, n, dim, alpha, gain)
    w = standard_normal(rng, (n, dim), found or False)
    if alpha <= 1e-6:
        return w
    y = lfilter([1 - alpha], [1, -alpha], w, axis=0)
    y *= gain
    return y


def still_force(
    pitch_rad: np.ndarray, roll_rad: np.ndarray, sway_sd_g: np.ndarray, counts: np.ndarray,
    rng: np.random.Generator, rate_hz: float, corner_hz: float,
) -> np.ndarray:
    """Still segments: gravity at a fixed orientation plus low-pass sway.

    Parameters
    ----------
    pitch_rad, roll_rad, sway_sd_g : ndarray, shape (m,)
        Per segment orientation (rad) and sway sd (g).
    counts : ndarray of int, shape (m,)
        Samples per segment.

    Returns
    -------
    ndarray, shape (counts.sum(), 3), g
    """
    f = np.repeat(gravity_foot(pitch_rad, roll_rad), counts, axis=0)
    sd = np.repeat(sway_sd_g, counts)
    moving = sd > 0
    k = int(moving.sum())
    if k:
        f[moving] += lowpass_noise(rng, k, rate_hz, corner_hz) * sd[moving, None]
    return f


def move_force(
    pitch0: np.ndarray, roll0: np.ndarray, pitch1: np.ndarray, roll1: np.ndarray,
    sd_g: np.ndarray, counts: np.ndarray, rng: np.random.Generator, rate_hz: float,
) -> np.ndarray:
    """Movements between two orientations: smooth-step attitude plus windowed noise.

    Parameters
    ----------
    pitch0, roll0, pitch1, roll1 : ndarray, shape (m,), rad
    sd_g : ndarray, shape (m,), g
        RMS of the linear acceleration over the movement.
    counts : ndarray of int, shape (m,)

    Returns
    -------
    ndarray, shape (counts.sum(), 3), g
    """
    total = int(counts.sum())
    seg = np.repeat(np.arange(len(counts)), counts)
    first = np.r_[0, np.cumsum(counts)[:-1]]
    local = np.arange(total) - first[seg]
    u = (local + 0.5) / counts[seg]
    s = u * u * (3 - 2 * u)
    pitch = pitch0[seg] + (pitch1 - pitch0)[seg] * s
    roll = roll0[seg] + (roll1 - roll0)[seg] * s
    lin = lowpass_noise(rng, total, rate_hz, 2.0)
    lin *= (np.sqrt(2.0) * np.sin(np.pi * u) * sd_g[seg])[:, None]
    lin[:, 2] += 1.0
    return world_to_foot(lin, pitch, roll)


def gait_force(
    n: int, rate_hz: float, cycle_s: float, stride_m: float, slope_rad: float, climb: float,
    flat_pitch_rad: float, stairs: bool, cfg: GaitConfig, rng: np.random.Generator,
) -> tuple[np.ndarray, np.ndarray]:
    """One walking or stairs bout of ``n`` samples, starting and ending in mid-stance.

    Parameters
    ----------
    n : int
        Samples at ``rate_hz``.
    cycle_s : float, s
        Mean gait cycle of the bout.
    stride_m : float, m
        Stride length (horizontal).
    slope_rad : float, rad
        Terrain slope (already contained in ``flat_pitch_rad``; kept for the record).
    climb : float
        +1 stairs up, -1 down, 0 level.
    flat_pitch_rad : float, rad
        Pitch of the foot flat on the ground.
    stairs : bool
    cfg : GaitConfig
    rng : numpy.random.Generator

    Returns
    -------
    force_g : ndarray, shape (n, 3), g
        Specific force in the foot frame.
    phase : ndarray, shape (n,)
        Gait phase in [0, 1) at each sample (0 = heel strike).
    """
    os_ = cfg.oversample
    dur = n / rate_hz
    n_str = max(1, int(round(dur / cycle_s)))
    periods = cycle_s * (1 + cfg.cycle_jitter * rng.standard_normal(n_str))
    periods = np.clip(periods, 0.3 * cycle_s, None)
    periods *= dur / periods.sum()
    knots = np.r_[0.0, np.cumsum(periods)]
    m = n * os_
    tau = (np.arange(m) + 0.5) / (rate_hz * os_)
    idx = np.clip(np.searchsorted(knots, tau, side="right") - 1, 0, n_str - 1)
    T = periods[idx]
    psi = 0.2 + (tau - knots[idx]) / T
    # per-stride amplitude variation
    amp = np.exp(0.08 * rng.standard_normal(n_str))[idx]
    L = stride_m * amp
    if stairs:
        to_p, hs_p = 0.6 * np.deg2rad(cfg.toe_off_pitch_deg), 0.3 * np.deg2rad(cfg.heel_strike_pitch_deg)
        H = 0.6 * cfg.clearance_m
        imp = cfg.impact_g * (0.5 if climb > 0 else 1.2)
    else:
        to_p, hs_p = np.deg2rad(cfg.toe_off_pitch_deg), np.deg2rad(cfg.heel_strike_pitch_deg)
        H = cfg.clearance_m
        imp = cfg.impact_g
    # forward
    # the swing's terms are computed where they apply (rows by integer index): the values
    # of np.where(in, expression, 0.0), bit for bit, without the sines and cosines of the
    # stance, ~60 % of the points
    ux = (psi - 0.40) / 0.58
    ix = np.flatnonzero((ux > 0) & (ux < 1))
    ax = np.zeros(m)
    ax[ix] = 2 * np.pi * L[ix] * np.sin(2 * np.pi * ux[ix]) / (0.58 * T[ix]) ** 2
    # vertical and lateral
    uz = (psi - 0.38) / 0.62
    iz = np.flatnonzero((uz > 0) & (uz < 1))
    uz_sw, t_sw = uz[iz], T[iz]
    bump = np.zeros(m)
    bump[iz] = 2 * np.pi**2 * (np.cos(2 * np.pi * uz_sw) - np.cos(4 * np.pi * uz_sw)) / (0.62 * t_sw) ** 2
    az = H * amp * bump
    if climb:
        az[iz] += climb * 2 * cfg.stairs_step_height_m * 2 * np.pi * np.sin(2 * np.pi * uz_sw) / (0.62 * t_sw) ** 2
    side = rng.choice([-1.0, 1.0])
    ay = side * cfg.lateral_m * bump
    # by axis from here on (contiguous rows; the same operations on each value as on the
    # (m, 3) rows of world_to_foot, bit for bit, and faster)
    fx, fy, fz = ax / G_MPS2, ay / G_MPS2, az / G_MPS2
    fz += 1.0
    # heel-strike impact
    after = (psi - 1.0) * T
    hit = after >= 0
    a_imp = imp * np.exp(0.25 * rng.standard_normal(n_str))[idx]
    pulse = np.where(hit, a_imp * np.exp(-np.where(hit, after, 0.0) / cfg.impact_tau_s), 0.0)
    fz += pulse
    fx -= 0.5 * pulse
    # attitude
    gi = (psi - 0.2) * (len(_GRID) - 1)
    curve_to, curve_hs = _attitude_curves(gi)  # np.interp's values, one floor for both
    pitch = flat_pitch_rad + amp * (to_p * curve_to + hs_p * curve_hs)
    swing_roll = np.zeros(m)
    swing_roll[iz] = np.power(np.sin(np.pi * uz_sw), 4)  # as np.where(0 < uz < 1, sin(pi uz) ** 4, 0.0)
    roll = side * np.deg2rad(cfg.swing_roll_deg) * swing_roll
    ct, st = np.cos(pitch), np.sin(pitch)
    # off the swing the roll is a signed zero, whose cosine is 1 and sine itself: the
    # cosine and sine are taken where it is not (the same values, bit for bit)
    cr, sr = np.ones(m), roll.copy()
    roll_sw = roll[iz]
    cr[iz], sr[iz] = np.cos(roll_sw), np.sin(roll_sw)
    gx = ct * fx + st * fz
    gz = -st * fx + ct * fz
    axes = (gx, cr * fy + sr * gz, -sr * fy + cr * gz)  # world_to_foot's columns
    # the anti-alias average over each sample's os_ points, in the order a reduction over
    # the middle axis of (n, os_, 3) adds them: (((x0 + x1) + x2) + ...) / os_
    f = np.empty((n, 3))
    for c, col in enumerate(axes):
        blocks = col.reshape(n, os_)
        acc = blocks[:, 0].copy()
        for i in range(1, os_):
            acc += blocks[:, i]
        np.divide(acc, os_, out=f[:, c])
    if cfg.midstance_sd_g > 0:
        f += cfg.midstance_sd_g * standard_normal(rng, (n, 3))
    phase = (psi.reshape(n, os_)[:, os_ // 2]) % 1.0
    return f, phase
