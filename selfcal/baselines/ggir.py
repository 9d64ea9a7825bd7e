"""GGIR auto-calibration (van Hees et al. 2014) and its data rules; optional actipy run.

``ggir_autocal`` follows the iterative closest-point loop of GGIR's ``g.calibrate``
(R, wadpac/GGIR, ``R/g.calibrate.R``, "Zhou Fang's code"), re-read for this port:

* ``curr = (input + offset) * scale + (T - mean T) * tempoffset`` (per axis);
* ``closestpoint = curr / ||curr||``;
* per axis ``k``: weighted regression ``closestpoint[:, k] ~ 1 + curr[:, k] + T'`` (R
  ``lm.wfit``) giving ``offsetch, scalech, toffch``; ``curr[:, k]`` = fitted values;
* ``offset += offsetch / (scale * scalech)``; ``tempoffset = tempoffset * scalech + toffch``;
  ``scale *= scalech``;
* ``res = 3 * mean(weights * (curr - closestpoint)^2 / sum(weights))``;
  ``weights = min(1 / ||curr - closestpoint||, 1/0.01)``;
* stop when ``|res_i - res_(i-1)| < 1e-10``, at most 1000 iterations.

Data rules: a 10-s window is still if its sd is below 13 mg on all three axes (and
``|mean| < 2 g`` per axis, against clipping); recalibration is attempted only if on
every axis some still window reads below -0.3 g and some above +0.3 g. GGIR keeps
the new calibration only if the mean absolute norm error ``cal.error.end`` drops
below ``cal.error.start`` and below 0.01 g (and enough hours were read — not
applicable to a pose table).
"""

from __future__ import annotations

import warnings

import numpy as np

from ._common import BaselineResult, check_poses, prescale_poses

__all__ = ["ggir_autocal", "ggir_still_mask", "ggir_sphere_coverage", "ggir_actipy"]


def ggir_still_mask(mean_g, sd_g, sd_crit_g: float = 0.013, clip_g: float = 2.0) -> np.ndarray:
    """GGIR's non-movement rule for 10-s windows.

    Parameters
    ----------
    mean_g : array_like, shape (n, 3), g
        Window means.
    sd_g : array_like, shape (n, 3), g
        Window standard deviations.
    sd_crit_g : float, g, default 0.013
        ``sdcriter``: every axis' sd must be below it.
    clip_g : float, g, default 2.0
        ``|mean|`` must be below it on every axis (GGIR: "to reduce chance of
        including clipping periods").

    Returns
    -------
    ndarray, shape (n,), bool
    """
    mean_g = np.asarray(mean_g, dtype=float)
    sd_g = np.asarray(sd_g, dtype=float)
    return np.all(sd_g < sd_crit_g, axis=1) & np.all(np.abs(mean_g) < clip_g, axis=1)


def ggir_sphere_coverage(mean_g, sphere_crit_g: float = 0.3) -> tuple[bool, np.ndarray]:
    """GGIR's "sphere populated" rule.

    Parameters
    ----------
    mean_g : array_like, shape (n, 3), g
        Means of the still windows.
    sphere_crit_g : float, g, default 0.3
        ``spherecrit``.

    Returns
    -------
    ok : bool
        True if every axis has a window below ``-sphere_crit_g`` *and* one above
        ``+sphere_crit_g``; else GGIR reports "recalibration not done because not
        enough points on all sides of the sphere".
    per_axis : ndarray, shape (3,), bool
    """
    mean_g = np.asarray(mean_g, dtype=float).reshape(-1, 3)
    if len(mean_g) == 0:
        return False, np.zeros(3, dtype=bool)
    per_axis = (mean_g.min(axis=0) < -sphere_crit_g) & (mean_g.max(axis=0) > sphere_crit_g)
    return bool(per_axis.all()), per_axis


def _wls(X: np.ndarray, y: np.ndarray, w: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    sw = np.sqrt(w)
    coef, *_ = np.linalg.lstsq(X * sw[:, None], y * sw, rcond=None)
    return coef, X @ coef


def ggir_autocal(
    mean,
    sd=None,
    n_samples=None,
    t_s=None,
    temp_c=None,
    *,
    use_temp: bool = True,
    sd_crit_g: float = 0.013,
    sphere_crit_g: float = 0.3,
    max_iter: int = 1000,
    tol: float = 1e-10,
    temp_sanity_max_c: float | None = 40.0,
    prescale: bool | str = "auto",
) -> BaselineResult:
    """GGIR ``g.calibrate`` on a table of still windows.

    Parameters
    ----------
    mean : array_like, shape (n, 3), raw unit
        Window means (GGIR: 10-s windows).
    sd : array_like, shape (n, 3), raw unit, optional
        Window sd; if given, GGIR's stillness rule (:func:`ggir_still_mask`) selects
        the windows used. Without it all windows are taken as still.
    n_samples, t_s : array_like, optional
        Accepted for the common interface and ignored.
    temp_c : array_like, shape (n,), degC, optional
        Window mean temperature; enables the temperature offset (``use_temp``).
    use_temp : bool, default True
    sd_crit_g, sphere_crit_g : float, g
        GGIR's 13 mg stillness and 0.3 g coverage criteria.
    max_iter : int, default 1000
    tol : float, default 1e-10
    temp_sanity_max_c : float or None, default 40
        GGIR drops the temperature if the mean of its first 10 values exceeds 40 degC
        ("temperature is too high", a GENEActiv artefact). ``None`` disables it.
    prescale : {"auto", True, False}
        GGIR expects g. Other units are pre-scaled to ~g (sphere fit) first and the
        result mapped back, so offsets and the sd rule act in g.

    Returns
    -------
    BaselineResult
        ``matrix = diag(scale)``, ``offset = -offset_ggir``, ``temp_coef = tempoffset``
        (g/degC, *added after scaling*, as GGIR's code does), ``temp_ref_c = mean T``.
        ``extra``: ``scale``, ``offset_ggir``, ``tempoffset`` (GGIR's own convention),
        ``cal_error_start``, ``cal_error_end`` (g), ``qc`` (GGIR's QC message),
        ``recalibrated`` (GGIR would keep it), ``use_temp``, ``npoints``, ``res``.
        When recalibration is not attempted (no still windows, poor coverage),
        ``converged`` is False and the calibration is the identity (in g).

    Notes
    -----
    GGIR's ``cal = (raw + offset) * scale + (T - mean T) * tempoffset``; the brief of
    this module wrote ``(raw + offset + tempoffset (T - mean T)) * scale`` — the two
    differ by a factor ``scale`` (~1) in ``tempoffset``; the code is followed.
    """
    m, s, _, _, tc = check_poses(mean, sd, n_samples, t_s, temp_c, min_poses=1, method="ggir_autocal")
    ps = prescale_poses(m, prescale)
    u = ps.forward(m)
    sd_u = None if s is None else s / ps.radius
    use_t = bool(use_temp and tc is not None and np.all(np.isfinite(tc)))
    qc_temp = ""
    if use_t and temp_sanity_max_c is not None and np.mean(tc[:10]) > temp_sanity_max_c:
        use_t, qc_temp = False, "temperature is too high"
    keep = np.all(np.abs(u) < 2.0, axis=1) if sd_u is None else ggir_still_mask(u, sd_u, sd_crit_g)
    pinfo = dict(applied=ps.applied, centre=ps.centre, radius=ps.radius)

    def not_done(qc, start=np.nan):
        matrix, offset = ps.back(np.eye(3), np.zeros(3))
        return BaselineResult(
            method="ggir_autocal", matrix=matrix, offset=offset, n_iter=0, converged=False,
            message=qc, extra=dict(qc=qc, recalibrated=False, cal_error_start=start, cal_error_end=np.nan,
                                   npoints=int(keep.sum()), use_temp=use_t, still=keep, prescale=pinfo))

    if not keep.any():
        return not_done("recalibration not done because no non-movement data available")
    inp = u[keep]
    npoints = len(inp)
    cal_error_start = float(np.mean(np.abs(np.linalg.norm(inp, axis=1) - 1.0)))
    ok, _ = ggir_sphere_coverage(inp, sphere_crit_g)
    if not ok:
        return not_done("recalibration not done because not enough points on all sides of the sphere",
                        cal_error_start)
    if use_t:
        temp = tc[keep]
        meantemp = float(np.mean(temp))
        it_temp = temp - meantemp
    else:
        meantemp = 0.0
        it_temp = np.zeros(npoints)
    offset = np.zeros(3)
    scale = np.ones(3)
    tempoffset = np.zeros(3)
    weights = np.ones(npoints)
    res = [np.inf]
    converged = False
    it = 0
    for it in range(1, max_iter + 1):
        curr = (inp + offset) * scale + it_temp[:, None] * tempoffset
        closest = curr / np.linalg.norm(curr, axis=1, keepdims=True)
        offsetch = np.zeros(3)
        scalech = np.ones(3)
        toffch = np.zeros(3)
        for k in range(3):
            cols = [np.ones(npoints), curr[:, k]] + ([it_temp] if use_t else [])
            coef, fitted = _wls(np.column_stack(cols), closest[:, k], weights)
            offsetch[k], scalech[k] = coef[0], coef[1]
            if use_t:
                toffch[k] = coef[2]
            curr[:, k] = fitted
        offset = offset + offsetch / (scale * scalech)
        if use_t:
            tempoffset = tempoffset * scalech + toffch
        scale = scale * scalech
        res.append(3.0 * np.mean(weights[:, None] * (curr - closest) ** 2 / weights.sum()))
        weights = np.minimum(1.0 / np.linalg.norm(curr - closest, axis=1), 1.0 / 0.01)
        if abs(res[-1] - res[-2]) < tol:
            converged = True
            break
    cal = (inp + offset) * scale + it_temp[:, None] * tempoffset
    cal_error_end = float(np.mean(np.abs(np.linalg.norm(cal, axis=1) - 1.0)))
    recal = cal_error_end < cal_error_start and cal_error_end < 0.01
    if recal:
        qc = "recalibration done, no problems detected" if use_t or tc is None else \
            "recalibration done, but temperature values not used"
    elif cal_error_end > cal_error_start:
        qc = "recalibration not done because recalibration does not decrease error"
    else:
        qc = ("recalibration attempted with all available data, but possibly not good enough: "
              "Check calibration error variable to varify this")
    if qc_temp:
        qc = f"{qc_temp}; {qc}"
    matrix, off = ps.back(np.diag(scale), -offset)
    return BaselineResult(
        method="ggir_autocal", matrix=matrix, offset=off, n_iter=it, converged=converged,
        message=f"{qc} (cal.error {cal_error_start * 1000:.2f} -> {cal_error_end * 1000:.2f} mg, {it} iterations)",
        extra=dict(scale=scale, offset_ggir=offset, tempoffset=tempoffset, cal_error_start=cal_error_start,
                   cal_error_end=cal_error_end, qc=qc, recalibrated=bool(recal), use_temp=use_t,
                   npoints=npoints, res=np.array(res[1:]), still=keep, prescale=pinfo),
        temp_coef=tempoffset.copy() if use_t else None,
        temp_ref_c=meantemp,
    )


def ggir_actipy(
    mean,
    sd=None,
    n_samples=None,
    t_s=None,
    temp_c=None,
    *,
    stdtol_g: float = 0.015,
    calib_cube: float = 0.3,
    calib_min_samples: int = 9,
    prescale: bool | str = "auto",
) -> BaselineResult:
    """actipy's ``calibrate_gravity`` (van Hees et al. 2014, as the UK Biobank pipeline does it).

    Parameters
    ----------
    mean : array_like, shape (n, 3), raw unit
        Still-window means. Each becomes one 10-s window of 10 constant samples at
        1 Hz in a synthetic DataFrame (so actipy's own window statistics give back
        exactly these means, with sd 0).
    sd : array_like, shape (n, 3), raw unit, optional
        If given, windows with any sd >= ``stdtol_g`` are dropped first (actipy's
        stationarity rule, applied here because constant samples carry no sd).
    n_samples, t_s : array_like, optional
        Accepted for the common interface and ignored.
    temp_c : array_like, shape (n,), degC, optional
        Added as the ``temperature`` column (actipy then fits ``slopeT``).
    stdtol_g : float, g, default 0.015
        actipy's ``stdtol`` (GGIR uses 0.013).
    calib_cube : float, g, default 0.3
    calib_min_samples : int, default 9
        actipy's default is 50 ten-second windows, meant for multi-day recordings; a
        pose table is already a curated set of windows.
    prescale : {"auto", True, False}

    Returns
    -------
    BaselineResult
        ``matrix = diag(slope)``, ``offset = -intercept/slope``, ``temp_coef = slopeT``
        (g/degC, ``temp_ref_c = 0``: actipy uses absolute temperature). If actipy
        declines (``CalibOK == 0``) or skips because the initial error is already
        below 10 mg, the identity is returned with ``converged`` accordingly.

    Raises
    ------
    ImportError
        If ``actipy`` (and pandas, statsmodels) is not installed.

    Notes
    -----
    Differences from GGIR that actipy documents in its code: MAE instead of RMSE,
    weights ``max(1 - e/q99.5(e), 0)`` instead of ``min(1/e, 100)``, stop when the
    relative improvement is < 1e-4, keep the best iterate, no temperature centring.
    """
    import pandas as pd  # lazy: optional dependency
    from actipy import processing as ap

    m, s, _, _, tc = check_poses(mean, sd, n_samples, t_s, temp_c, min_poses=1, method="ggir_actipy")
    ps = prescale_poses(m, prescale)
    u = ps.forward(m)
    keep = np.ones(len(u), dtype=bool) if s is None else np.all(s / ps.radius < stdtol_g, axis=1)
    uk = u[keep]
    nwin = len(uk)
    reps = 10
    t = pd.Timestamp("2000-01-01") + pd.to_timedelta(np.arange(nwin * reps), unit="s")
    df = pd.DataFrame(np.repeat(uk, reps, axis=0), columns=["x", "y", "z"], index=t)
    if tc is not None:
        df["temperature"] = np.repeat(tc[keep], reps)
    with warnings.catch_warnings(record=True) as wlist:
        warnings.simplefilter("always")
        _, info = ap.calibrate_gravity(df, calib_cube=calib_cube, calib_min_samples=calib_min_samples,
                                       stdtol=stdtol_g, return_coeffs=True)
    msgs = "; ".join(str(w.message) for w in wlist)
    ok = bool(info.get("CalibOK", 0))
    if ok and "CalibxSlope" in info:
        slope = np.array([info[f"Calib{a}Slope"] for a in "xyz"])
        icpt = np.array([info[f"Calib{a}Intercept"] for a in "xyz"])
        slope_t = np.array([info[f"Calib{a}SlopeT"] for a in "xyz"]) if tc is not None else None
        matrix, offset = ps.back(np.diag(slope), -icpt / slope)
        msg = "actipy calibrate_gravity: CalibOK"
    else:
        matrix, offset = ps.back(np.eye(3), np.zeros(3))
        slope_t = None
        msg = ("actipy skipped: initial error already below 10 mg" if ok
               else "actipy calibrate_gravity declined (CalibOK=0)")
    if msgs:
        msg += f" [{msgs}]"
    return BaselineResult(
        method="ggir_actipy", matrix=matrix, offset=offset, n_iter=int(info.get("CalibNumIters", 0)),
        converged=ok, message=msg,
        extra=dict(info=dict(info), n_windows=nwin,
                   prescale=dict(applied=ps.applied, centre=ps.centre, radius=ps.radius)),
        temp_coef=slope_t, temp_ref_c=0.0,
    )
