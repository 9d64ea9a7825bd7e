"""Sensor temperature: first-order lags between ambient, in-shoe and walking heat.

Per segment the targets are constant, so the temperature has a closed form
(two exponentials), evaluated vectorised at any local time. State at every segment
start is carried by :func:`segment_start_states` (a scalar recurrence over segments).

Model (per segment, local time ``tau`` s from the segment start)::

    h(tau)  = H + (h0 - H) exp(-tau / tau_h)                 walking heat (degC)
    on foot:  dT/dtau = (A + h(tau) - T) / tau_T             A = in-shoe plateau
    off foot: dT/dtau = (A - T) / tau_T                      A = ambient

with ``H`` the day's walking heat while walking (else 0), ``tau_T`` = ``tau_on_s`` on
the foot and ``tau_off_s`` off it, ``tau_h`` = ``tau_walk_s``.
"""

from __future__ import annotations

import numpy as np


def _b_coef(h0: np.ndarray, heat: np.ndarray, tau_t: np.ndarray, tau_h: np.ndarray, on: np.ndarray) -> np.ndarray:
    ratio = tau_h / (tau_h - tau_t)
    return np.where(on, (h0 - heat) * ratio, 0.0)


def temperature_at(
    tau_s: np.ndarray,
    temp0_c: np.ndarray,
    heat0_c: np.ndarray,
    target_c: np.ndarray,
    heat_target_c: np.ndarray,
    tau_t_s: np.ndarray,
    tau_h_s: np.ndarray,
    on_foot: np.ndarray,
) -> tuple[np.ndarray, np.ndarray]:
    """Closed-form temperature and walking heat at local times (all arrays broadcast).

    Parameters
    ----------
    tau_s : ndarray, shape (n,), s
        Time since the segment start.
    temp0_c, heat0_c : ndarray, shape (n,), degC
        Temperature and walking heat at the segment start.
    target_c : ndarray, shape (n,), degC
        Plateau ``A`` (in-shoe on the foot, ambient off it).
    heat_target_c : ndarray, shape (n,), degC
        Walking-heat target ``H`` (0 when not walking).
    tau_t_s, tau_h_s : ndarray, shape (n,), s
        Time constants (``tau_h != tau_t``).
    on_foot : ndarray of bool, shape (n,)

    Returns
    -------
    temp_c : ndarray, shape (n,), degC
    heat_c : ndarray, shape (n,), degC
    """
    eh = np.exp(-tau_s / tau_h_s)
    et = np.exp(-tau_s / tau_t_s)
    heat = heat_target_c + (heat0_c - heat_target_c) * eh
    b = _b_coef(heat0_c, heat_target_c, tau_t_s, tau_h_s, on_foot)
    base = target_c + np.where(on_foot, heat_target_c, 0.0)
    c = temp0_c - base - b
    temp = base + b * eh + c * et
    return temp, heat


def segment_start_states(
    dur_s: np.ndarray,
    target_c: np.ndarray,
    heat_target_c: np.ndarray,
    tau_t_s: np.ndarray,
    tau_h_s: np.ndarray,
    on_foot: np.ndarray,
    temp_init_c: float,
    *,
    kernel="auto",
) -> tuple[np.ndarray, np.ndarray]:
    """Temperature and walking heat at the start of every segment.

    Parameters
    ----------
    dur_s : ndarray, shape (m,), s
        Segment durations.
    target_c, heat_target_c, tau_t_s, tau_h_s, on_foot : ndarray, shape (m,)
        Per-segment model constants (see :func:`temperature_at`).
    temp_init_c : float
        Temperature at time 0.
    kernel : optional
        The planner's numba kernels (:func:`selfcal.sim.plan_numba.kernels`), None for the
        Python recurrence, or ``"auto"`` (default): the kernels if they are loaded already
        (this alone does not pay their first load). The same results either way.

    Returns
    -------
    temp0_c, heat0_c : ndarray, shape (m,), degC
    """
    if kernel == "auto":
        from selfcal.sim import plan_numba

        kernel = plan_numba.kernels(days=0.0)
    if kernel is None:
        return start_states_python(dur_s, target_c, heat_target_c, tau_t_s, tau_h_s, on_foot, temp_init_c)
    eh, et, ratio, base = _recurrence_terms(dur_s, target_c, heat_target_c, tau_t_s, tau_h_s, on_foot)
    return kernel.start_states(eh, et, ratio, base, np.ascontiguousarray(heat_target_c, dtype=float),
                               np.ascontiguousarray(on_foot, dtype=bool), float(temp_init_c),
                               np.empty(len(eh)), np.empty(len(eh)))


def _recurrence_terms(dur_s, target_c, heat_target_c, tau_t_s, tau_h_s, on_foot):
    eh = np.exp(-dur_s / tau_h_s)
    et = np.exp(-dur_s / tau_t_s)
    ratio = tau_h_s / (tau_h_s - tau_t_s)
    base = target_c + np.where(on_foot, heat_target_c, 0.0)
    return eh, et, ratio, base


def start_states_python(dur_s, target_c, heat_target_c, tau_t_s, tau_h_s, on_foot,
                        temp_init_c: float) -> tuple[np.ndarray, np.ndarray]:
    """:func:`segment_start_states` in Python (the reference of its numba kernel)."""
    eh, et, ratio, base = _recurrence_terms(dur_s, target_c, heat_target_c, tau_t_s, tau_h_s, on_foot)
    # the scalar recurrence on Python floats (lists: far faster to index than arrays)
    return recurrence(eh.tolist(), et.tolist(), ratio.tolist(), base.tolist(), heat_target_c.tolist(),
                      on_foot.tolist(), float(temp_init_c), np.empty(len(eh)), np.empty(len(eh)))


def recurrence(eh, et, ratio, base, heat_target, on_foot, temp_init: float, temp0: np.ndarray,
               heat0: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """The temperature and walking heat (degC) at the start of every segment, written into
    ``temp0`` and ``heat0`` ((m,) float64 each, returned), one closed-form step per segment
    from ``temp_init`` (degC): sequences of the per-segment decays ``eh``, ``et``, heat
    ratio, plateau ``base`` (degC), walking heat target (degC) and on-foot flags. Plain
    Python, also compiled as it is by :mod:`selfcal.sim._plan_jit`. The outputs come from
    the caller: numpy's large arrays get transparent huge pages, a kernel's own 4 KiB
    pages (a year's two outputs: ~6 500 page faults more)."""
    m = len(eh)
    t, h = temp_init, 0.0
    for i in range(m):
        temp0[i] = t
        heat0[i] = h
        hs = heat_target[i]
        b = (h - hs) * ratio[i] if on_foot[i] else 0.0
        c = t - base[i] - b
        t = base[i] + b * eh[i] + c * et[i]
        h = hs + (h - hs) * eh[i]
    return temp0, heat0
