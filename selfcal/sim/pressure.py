"""Four insole pressure channels (kPa): heel, midfoot, 1st metatarsal head, toe.

Driven by the same segments as the motion: each still or moving segment carries a load
vector relative to the wearer's standing load (standing ~1 with a heel/forefoot shift,
sitting ~0.3, a hanging foot or the shoe off the foot 0); gait segments follow the roll-
over of the foot: heel peak just after heel strike, midfoot, 1st metatarsal at push-off,
toe at toe-off, nothing in swing (peaks ``walk_peak_factor`` x the standing load).
"""

from __future__ import annotations

import numpy as np

from selfcal.sim.config import PressureConfig
from selfcal.sim.draw_numba import standard_normal
from selfcal.sim.motion import lowpass_noise

#: Gait phase (0 = heel strike) of each channel's peak and its width (sd, cycle units).
_GAIT_CENTRE = np.array([0.08, 0.22, 0.45, 0.55])
_GAIT_WIDTH = np.array([0.07, 0.09, 0.08, 0.05])
_GAIT_SCALE = np.array([1.0, 0.6, 1.0, 0.8])
_SWING_PHASE = 0.64


def gait_pressure_profile(phase: np.ndarray) -> np.ndarray:
    """Relative load (1 = standing load) of each channel over the gait cycle.

    Parameters
    ----------
    phase : ndarray, shape (n,)
        Gait phase in [0, 1), 0 = heel strike.

    Returns
    -------
    ndarray, shape (n, 4)
    """
    return gait_pressure_profile_by_channel(phase).T


def gait_pressure_profile_by_channel(phase: np.ndarray) -> np.ndarray:
    """:func:`gait_pressure_profile` by channel: shape (4, n), the same values bit for bit
    (each channel on a contiguous row: an (n, 4) broadcast runs an inner loop of 4 a row)."""
    prof = np.empty((4, len(phase)))
    for c in range(4):
        d = (phase - _GAIT_CENTRE[c]) / _GAIT_WIDTH[c]
        np.multiply(_GAIT_SCALE[c], np.exp(-0.5 * d * d), out=prof[c])
    prof[:, phase >= _SWING_PHASE] = 0.0
    return prof


def pressure_by_channel(
    load: np.ndarray,
    gait_phase: np.ndarray,
    moving: np.ndarray,
    stand_kpa: np.ndarray,
    cfg: PressureConfig,
    rng: np.random.Generator,
    rate_hz: float,
) -> np.ndarray:
    """Pressure samples for a chunk, by channel.

    Parameters
    ----------
    load : ndarray, shape (4, n)
        Per-sample load relative to standing (NaN on gait samples), by channel; the
        result is computed in it (overwritten).
    gait_phase : ndarray, shape (n,)
        Gait phase on gait samples, NaN elsewhere.
    moving : ndarray of bool, shape (n,)
        Samples of MOVE segments (loads vary strongly).
    stand_kpa : ndarray, shape (4,), kPa
        The wearer's standing load per channel.
    cfg : PressureConfig
    rng : numpy.random.Generator
    rate_hz : float

    Returns
    -------
    ndarray, shape (4, n), kPa, >= 0 (``.T`` gives the samples' rows)

    Each channel is a contiguous row: on (n, 4) rows a broadcast or a row selection runs
    an inner loop of 4 a row, several times slower. The draws keep their (n, 4) shapes.
    """
    rel = load
    n = rel.shape[1]
    gait = np.isfinite(gait_phase)
    gi = np.flatnonzero(gait)
    if len(gi):
        prof = gait_pressure_profile_by_channel(gait_phase[gi])
        for c in range(4):
            rel[c, gi] = cfg.walk_peak_factor * prof[c]
    li = np.flatnonzero((rel[0] > 0) | (rel[1] > 0) | (rel[2] > 0) | (rel[3] > 0))  # any loaded channel
    k = len(li)
    if k and cfg.sway_rel > 0:
        var = lowpass_noise(rng, k, rate_hz, 0.3, dim=4)
        amp = np.where(moving[li], 0.3, cfg.sway_rel)
        amp = np.where(gait[li], 0.1, amp)
        for c in range(4):
            factor = amp * var[:, c]
            factor += 1.0
            np.maximum(factor, 0.0, out=factor)
            rel[c, li] *= factor
    p = rel
    p *= stand_kpa[:, None]
    p += cfg.offset_kpa
    if cfg.noise_kpa > 0:
        noise = standard_normal(rng, (n, 4))
        noise *= cfg.noise_kpa
        p += noise.T
    return np.maximum(p, 0.0, out=p)
