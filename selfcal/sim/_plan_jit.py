"""numba kernel of the wearer's planner (:meth:`selfcal.sim.wearer._Builder.worn`).

The planner draws a few thousand postures and durations a simulated day, each a handful
of scalar draws and float operations: in Python that is most of a poses-level replay's
simulator. This is the same code, operation for operation and draw for draw, compiled:
numba's ``Generator`` methods take the same values from the same bit generator as
numpy's (and advance the caller's generator), and the one transcendental function, the
log-normal durations' ``exp``, is numpy's own, called from object mode (numpy's SIMD
``exp`` and the C library's differ in the last bit of ~5 % of values on a CPU with
AVX-512). :mod:`selfcal.sim.wearer` checks the kernel against the Python planner at
first use and falls back to it if any row differs.

Every constant the planner reads comes in ``par`` (float64, the ``P_*`` slots below) and
the semi-Markov chain's tables in ``next_code`` / ``next_cdf`` / ``next_len``; rows go
into the builder's ``(17, cap)`` float64 buffer by column, in
:data:`selfcal.sim.wearer._COLUMNS`' order. Activity
codes are literals here (numba bakes a module's globals into its cached code): SIT 1,
STAND 2, WALK 3, STAIRS 4; motion STILL 0, MOVE 1, GAIT 2; states sit 0, stand 1,
walk 2, stairs 3.
"""

from __future__ import annotations

import math

import numba
import numpy as np

from selfcal.sim.temperature import recurrence

# slots of ``par``: a log-normal duration is (median_s, log(gsd), min_s, max_s)
P_SIT, P_STAND, P_WALK_SHORT, P_WALK_LONG, P_STAIRS = 0, 4, 8, 12, 16
P_STAND_QUIET, P_STAND_SHIFT, P_SIT_QUIET, P_SIT_FIDGET = 20, 24, 28, 32
P_WALK_LONG_FRACTION = 36
P_SHOE_PITCH = 37
P_STAND_TILT_RAD, P_STAND_SHIFT_SD_G, P_STAND_SWAY_G = 38, 39, 40
P_SIT_FACTOR, P_SIT_SWAY_G, P_SIT_FLAT_TILT_RAD = 41, 42, 43
P_SIT_HEEL_PITCH_DEG, P_SIT_TOES_PITCH_DEG, P_SIT_CROSSED_ROLL_DEG = 44, 46, 48  # (lo, hi) each
P_SIT_CROSSED_SWAY_G, P_SIT_FIDGET_SD_G = 50, 51
P_STAIRS_CYCLE_S, P_STAIRS_STRIDE_M, P_CYCLE_S, P_CYCLE_SD_S = 52, 53, 54, 55
P_STRIDE_M, P_STRIDE_SD_M, P_SLOPE_SD_DEG = 56, 57, 58
P_MAX_STILL_PIECE_S = 59  # wearer.MAX_STILL_PIECE_S: a longer still is cut into pieces
N_PAR = 60
N_COLUMNS = 17  # len(wearer._COLUMNS); checked when the kernels are loaded


@numba.njit(cache=True)
def _np_exp(x):
    """numpy's ``exp`` of a float64 array (its SIMD code, not the C library's)."""
    with numba.objmode(y="float64[:]"):
        y = np.exp(x)
    return y


@numba.njit(cache=True)
def _draw_one(par, i, rng):
    """``wearer._draw(d, rng)``: one log-normal duration (s), clipped."""
    z = np.empty(1)
    z[0] = par[i + 1] * rng.standard_normal()
    x = par[i] * _np_exp(z)[0]
    return float(min(max(x, par[i + 2]), par[i + 3]))


@numba.njit(cache=True)
def _draw_many(par, i, rng, k):
    """``wearer._draw(d, rng, k)``: k log-normal durations (s), clipped."""
    z = np.empty(k)
    for j in range(k):
        z[j] = rng.standard_normal()
    x = _np_exp(par[i + 1] * z)
    out = np.empty(k)
    for j in range(k):
        out[j] = min(max(par[i] * x[j], par[i + 2]), par[i + 3])
    return out


@numba.njit(cache=True)
def _pick(cdf, n, rng):
    """``wearer._pick``: one uniform, searched in the first ``n`` entries of ``cdf``."""
    return np.searchsorted(cdf[:n], rng.random(), side="right")


@numba.njit(cache=True)
def _nonneg(v):
    return v if (v > 0.0 or v != v) else 0.0


@numba.njit(cache=True)
def _grow(cols, n):
    """``cols`` (17, cap) with room for column ``n`` (a bigger copy when it is full: rare,
    the builder reserves room for the kernel's rows beforehand in numpy's memory)."""
    if n < cols.shape[1]:
        return cols
    bigger = np.empty((cols.shape[0], 2 * cols.shape[1] + 64))
    bigger[:, :n] = cols[:, :n]
    return bigger


@numba.njit(cache=True, inline="always")
def _put(cols, n, v0, v1, v2, v3, v4, v5, v6, v7, v8, v9, v10, v11, v12, v13, v14, v15, v16):
    """Row ``n`` of the plan, written by column."""
    cols[0, n], cols[1, n], cols[2, n], cols[3, n], cols[4, n], cols[5, n] = v0, v1, v2, v3, v4, v5
    cols[6, n], cols[7, n], cols[8, n], cols[9, n], cols[10, n], cols[11, n] = v6, v7, v8, v9, v10, v11
    cols[12, n], cols[13, n], cols[14, n], cols[15, n], cols[16, n] = v12, v13, v14, v15, v16


@numba.njit(cache=True)
def worn(rng, total, par, sit_cdf, next_code, next_cdf, next_len, t, orient, load, next_still, cols, n):
    """The semi-Markov chain of sit / stand / walk / stairs for ``total`` s, as
    ``_Builder.worn`` plans it.

    ``t`` (s), ``orient`` (2,) rad and ``load`` (4,) are the builder's state and
    ``next_still`` its next still id; ``sit_cdf`` is the sitting postures' cumulative
    distribution, ``next_code[s, :next_len[s]]`` / ``next_cdf[s]`` the states that follow
    state ``s`` and their cumulative distribution. The rows are written by column into
    ``cols`` (17, cap) float64 from column ``n`` on (the builder's buffer, allocated by
    numpy: its large arrays get transparent huge pages, a kernel's own allocations 4 KiB
    pages, ~7x the page faults). Returns ``(cols, n, t, next_still)``: ``cols`` itself, or
    a bigger copy if it ran out of room, and the rows filled; ``orient`` and ``load`` are
    updated in place.
    """
    end = t + total
    state = 1  # stand
    climb = 1.0
    while t < end - 1e-9:
        left = end - t
        if state == 0 or state == 1:  # sit, stand: alternating movements and quiet
            if state == 0:
                bout = min(_draw_one(par, P_SIT, rng), left)
                iq, im = P_SIT_QUIET, P_SIT_FIDGET
            else:
                bout = min(_draw_one(par, P_STAND, rng), left)
                iq, im = P_STAND_QUIET, P_STAND_SHIFT
            k = int(bout / (par[iq] + par[im])) * 2 + 8
            q = _draw_many(par, iq, rng, k)
            m = _draw_many(par, im, rng, k)
            used = 0.0
            new_p, new_r, sway = 0.0, 0.0, 0.0
            new_load = np.zeros(4)
            for j in range(k):
                if used >= bout:
                    break
                for kind in range(2):  # 0: a movement to a new posture, 1: quiet in it
                    if kind == 0:
                        d = min(m[j], bout - used)
                    else:
                        d = min(q[j], bout - used)
                    used += d
                    if kind == 0:
                        if state == 1:  # stand_posture
                            t0 = rng.standard_normal()
                            t1 = rng.standard_normal()
                            c = par[P_STAND_TILT_RAD]
                            w = 0.15 * rng.standard_normal()
                            share = rng.uniform(0.8, 1.2)
                            new_load[0] = share * (1 + w)
                            new_load[1] = share * 1.0
                            new_load[2] = share * (1 - w)
                            new_load[3] = share * (1 - w)
                            new_p, new_r = par[P_SHOE_PITCH] + c * t0, c * t1
                            sway = par[P_STAND_SWAY_G]
                            sd = par[P_STAND_SHIFT_SD_G]
                            act = 2.0
                        else:  # sit_posture
                            kk = _pick(sit_cdf, sit_cdf.size, rng)
                            f = par[P_SIT_FACTOR]
                            sway = par[P_SIT_SWAY_G]
                            if kk == 0:
                                t0 = rng.standard_normal()
                                t1 = rng.standard_normal()
                                c = par[P_SIT_FLAT_TILT_RAD]
                                new_p, new_r = par[P_SHOE_PITCH] + c * t0, c * t1
                                z = 1 + 0.2 * rng.standard_normal()
                                new_load[0] = (f * 1.2) * z
                                new_load[1] = (f * 1.0) * z
                                new_load[2] = (f * 0.9) * z
                                new_load[3] = (f * 0.6) * z
                            elif kk == 1:
                                new_p = math.radians(rng.uniform(par[P_SIT_HEEL_PITCH_DEG], par[P_SIT_HEEL_PITCH_DEG + 1]))
                                new_r = math.radians(5 * rng.standard_normal())
                                new_load[0], new_load[1], new_load[2], new_load[3] = f * 2.0, f * 0.2, f * 0.0, f * 0.0
                            elif kk == 2:
                                new_p = math.radians(rng.uniform(par[P_SIT_TOES_PITCH_DEG], par[P_SIT_TOES_PITCH_DEG + 1]))
                                new_r = math.radians(5 * rng.standard_normal())
                                new_load[0], new_load[1], new_load[2], new_load[3] = f * 0.0, f * 0.2, f * 1.8, f * 1.5
                            else:
                                u = math.radians(rng.uniform(par[P_SIT_CROSSED_ROLL_DEG], par[P_SIT_CROSSED_ROLL_DEG + 1]))
                                new_r = u * (-1.0 if rng.integers(0, 2) == 0 else 1.0)
                                new_p = math.radians(rng.uniform(-40.0, 0.0))
                                new_load[0], new_load[1], new_load[2], new_load[3] = 0.0, 0.0, 0.0, 0.0
                                sway = par[P_SIT_CROSSED_SWAY_G]
                            for i in range(4):
                                new_load[i] = _nonneg(new_load[i])
                            sd = par[P_SIT_FIDGET_SD_G]
                            act = 1.0
                        # move: from the current orientation to the new posture, the load kept
                        cols = _grow(cols, n)
                        _put(cols, n, d, act, 1.0, orient[0], orient[1], new_p, new_r, sd, 0.0, 0.0, 0.0, 0.0,
                             load[0], load[1], load[2], load[3], -1.0)
                        n += 1
                        t += d
                        orient[0], orient[1] = new_p, new_r
                    else:
                        # still: a new still period (``_Builder.still`` continues the last
                        # row's period when it is a still in the same orientation; here the
                        # last row is always the move into this posture)
                        sid = float(next_still)
                        next_still += 1
                        rest = d
                        while rest > 0:
                            piece = min(rest, par[P_MAX_STILL_PIECE_S])
                            cols = _grow(cols, n)
                            _put(cols, n, piece, act, 0.0, new_p, new_r, new_p, new_r, sway, 0.0, 0.0, 0.0, 0.0,
                                 new_load[0], new_load[1], new_load[2], new_load[3], sid)
                            n += 1
                            rest -= piece
                        t += d
                        orient[0], orient[1] = new_p, new_r
                        for i in range(4):
                            load[i] = new_load[i]
                    if used >= bout:
                        break
        else:  # walk, stairs: a gait bout
            if state == 2:
                idist = P_WALK_LONG if rng.uniform(0.0, 1.0) < par[P_WALK_LONG_FRACTION] else P_WALK_SHORT
                act = 3.0
                c_climb = 0.0
            else:
                climb = -climb if rng.uniform(0.0, 1.0) < 0.8 else climb  # mostly up then down
                idist = P_STAIRS
                act = 4.0
                c_climb = climb
            d = min(_draw_one(par, idist, rng), left)
            if state == 3:
                cycle = par[P_STAIRS_CYCLE_S] * (1 + 0.05 * rng.standard_normal())
                stride = par[P_STAIRS_STRIDE_M]
                slope = 0.0
            else:
                cycle = par[P_CYCLE_S] + par[P_CYCLE_SD_S] * rng.standard_normal()
                stride = par[P_STRIDE_M] + par[P_STRIDE_SD_M] * rng.standard_normal()
                slope = np.deg2rad(par[P_SLOPE_SD_DEG] * rng.standard_normal())
            cycle = min(max(cycle, 0.7), 2.2)
            stride = max(stride, 0.3)
            flat = par[P_SHOE_PITCH] + slope
            cols = _grow(cols, n)
            _put(cols, n, d, act, 2.0, flat, 0.0, flat, 0.0, 0.0, cycle, stride, slope, c_climb,
                 np.nan, 0.0, 0.0, 0.0, -1.0)
            n += 1
            t += d
            orient[0], orient[1] = flat, 0.0
            for i in range(4):
                load[i] = 1.0
        state = next_code[state, _pick(next_cdf[state], next_len[state], rng)]
    return cols, n, t, next_still


#: ``temperature.segment_start_states``' recurrence (:func:`selfcal.sim.temperature.recurrence`,
#: the same function, compiled): the temperature and walking heat (degC) at the start of
#: every segment, (m,) each.
start_states = numba.njit(cache=True)(recurrence)
