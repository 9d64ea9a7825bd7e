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
    d = (phase[:, None] - _GAIT_CENTRE) / _GAIT_WIDTH
    prof = _GAIT_SCALE * np.exp(-0.5 * d * d)
    prof[phase >= _SWING_PHASE] = 0.0
    return prof


def pressure_kpa(
    load: np.ndarray,
    gait_phase: np.ndarray,
    moving: np.ndarray,
    stand_kpa: np.ndarray,
    cfg: PressureConfig,
    rng: np.random.Generator,
    rate_hz: float,
) -> np.ndarray:
    """Pressure samples for a chunk.

    Parameters
    ----------
    load : ndarray, shape (n, 4)
        Per-sample load relative to standing (NaN on gait samples).
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
    ndarray, shape (n, 4), kPa, >= 0
    """
    n = len(load)
    rel = load.copy()
    gait = np.isfinite(gait_phase)
    # rows by integer index, not by boolean mask: the same values, several times faster on (n, 4)
    gi = np.flatnonzero(gait)
    if len(gi):
        rel[gi] = cfg.walk_peak_factor * gait_pressure_profile(gait_phase[gi])
    li = np.flatnonzero((rel[:, 0] > 0) | (rel[:, 1] > 0) | (rel[:, 2] > 0) | (rel[:, 3] > 0))  # any(axis=1), faster
    k = len(li)
    if k and cfg.sway_rel > 0:
        var = lowpass_noise(rng, k, rate_hz, 0.3, dim=4)
        amp = np.where(moving[li], 0.3, cfg.sway_rel)
        amp = np.where(gait[li], 0.1, amp)
        factor = amp[:, None] * var
        factor += 1.0
        np.maximum(factor, 0.0, out=factor)
        rel[li] *= factor
    p = rel
    p *= stand_kpa
    p += cfg.offset_kpa
    if cfg.noise_kpa > 0:
        noise = rng.standard_normal((n, 4))
        noise *= cfg.noise_kpa
        p += noise
    return np.maximum(p, 0.0, out=p)
