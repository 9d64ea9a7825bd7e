"""Pose coverage of one device, for the dashboard: its stored still poses and the gravity
directions they leave undetermined.

Computed from what the store already holds, so both backends serve it without a schema
of their own: the calibrator state (``devices.calibrator_state``, the pose store and the
current fit's covariance) and the served version's calibration.

* **Poses.** One entry per pose cell of the calibrator's store: the unit gravity
  direction of the cell's mean reading (sensor frame, uncalibrated), its mean temperature
  (degC; None when its windows had none), its window count, its mean time (device s) and
  its norm residual under the *served* calibration, ``|a_cal| - 1 g`` in mg.
* **Undetermined directions.** On directions spread over the whole sphere, the sd of
  the calibrated norm that the current fit's covariance predicts there (mg; the
  per-direction terms of ``predicted_sphere_rms_mg``). A direction is *undetermined*
  when that sd exceeds ``[scheduler] calibrated_max_sphere_mg`` (2 mg by default): the
  data do not yet pin the norm error along it to what status ``calibrated`` promises on
  average. Before any fit the prior alone answers (~100 mg: every direction is
  undetermined). The prior's sd is given beside it for comparison. (The calibrator's
  rule for a *parameter*, sd below ``determined_ratio`` of the prior's, is looser: on a
  simulated 2-h wear it left no direction undetermined while one predicted 30 mg.)

A calibrator that is not :class:`selfcal.calibrator.OnlineCalibrator` (a test's fake)
has no pose store: the answer says so (``available: false``) instead of failing.
"""

from __future__ import annotations

import json
import math
from typing import Any

import numpy as np

#: Directions spread on the sphere (Fibonacci) on which undetermined directions are looked for.
SPHERE_GRID_DIRECTIONS = 300

STATE_FORMAT = "selfcal-calibrator-state"


def _rounded(values: np.ndarray, digits: int) -> list:
    """A list of floats rounded to ``digits`` (NaN/inf as None), nested like ``values``."""
    arr = np.asarray(values, dtype=float)
    if arr.ndim > 1:
        return [_rounded(row, digits) for row in arr]
    return [round(float(v), digits) if math.isfinite(v) else None for v in arr]


def _unavailable(note: str, served_version: int | None) -> dict[str, Any]:
    return {
        "available": False, "note": note, "version": served_version, "model": None, "residual_basis": None,
        "n_poses": 0, "direction": [], "temp_c": [], "residual_mg": [], "windows": [], "t_s": [],
        "residual_rms_mg": None, "undetermined_above_sd_mg": None,
        "sphere": {"direction": [], "sd_mg": [], "prior_sd_mg": [], "undetermined": []},
    }


def _served_theta(model_cls, served: dict[str, Any] | None, state_model) -> tuple[Any, np.ndarray, str] | None:
    """(model, theta in g units, a description) of the served calibration, or None without params."""
    if not served or not served.get("params"):
        return None
    name = served.get("model") or state_model.name
    model = state_model if name == state_model.name else model_cls(
        name, float(served.get("temp_ref_c", state_model.temp_ref_c)), float(served.get("t_ref_s", state_model.t_ref_s)))
    params = {k: v for k, v in served["params"].items() if v is not None}
    return model, model.from_dict(params), "served"


def pose_coverage(state_json: str | None, served: dict[str, Any] | None,
                  served_version: int | None = None, n_directions: int = SPHERE_GRID_DIRECTIONS,
                  patch_json: str | None = None) -> dict[str, Any]:
    """The device's stored poses and undetermined directions (see the module docstring).

    Parameters
    ----------
    state_json : the device's calibrator state (JSON text), or None before any batch was fed
    patch_json : the checkpoint's latest patch against ``state_json`` (``selfcal.checkpoint``), if any
    served : the served version's calibration (``params`` in g units, ``model``), or None
    served_version : its number (echoed)
    n_directions : directions spread on the sphere for the undetermined ones

    Returns
    -------
    dict with ``available``, ``note``, ``version``, ``model``, ``residual_basis``
    (``served``: the served version's parameters; ``nominal``: no calibration yet),
    ``n_poses`` and per pose ``direction`` (unit, sensor frame), ``temp_c`` (degC),
    ``residual_mg`` (mg), ``windows``, ``t_s`` (device s); ``residual_rms_mg``;
    ``undetermined_above_sd_mg`` (the threshold, mg); ``sphere``: ``direction``, ``sd_mg``
    (predicted sd of the calibrated norm, mg), ``prior_sd_mg`` (the prior's, mg) and
    ``undetermined`` (bool) per direction.
    """
    if not state_json:
        return _unavailable("no calibrator state yet: no batch has been fed", served_version)
    try:
        if patch_json is not None:  # a checkpoint's base and its latest patch
            from selfcal.checkpoint import apply_patch

            state = apply_patch(state_json, patch_json)[0]
        else:
            state = json.loads(state_json)
    except ValueError:  # (InputError is a ValueError: a patch made against another base)
        return _unavailable("the calibrator state is not JSON, or its patch does not apply", served_version)
    if not isinstance(state, dict) or state.get("format") != STATE_FORMAT:
        return _unavailable("this calibrator keeps no pose store (not selfcal's OnlineCalibrator)", served_version)

    from selfcal.calibrator import OnlineCalibrator
    from selfcal.errors import InputError
    from selfcal.fit import datasheet_prior, sphere_directions, sphere_jacobian
    from selfcal.models import ErrorModel

    try:
        cal = OnlineCalibrator.from_json(state)
    except (InputError, KeyError, TypeError, ValueError) as exc:
        return _unavailable(f"cannot read the calibrator state: {exc}", served_version)
    store, model = cal.store, cal.model
    n = len(store)
    if n:
        data = store.pose_data()
        norm = np.linalg.norm(data.mean, axis=1, keepdims=True)
        direction = data.mean / np.where(norm > 0, norm, 1.0)
        temp = store.mean_temp()
        t_mean = data.t_s
        windows = store.window_counts()
    else:
        direction, temp, t_mean, windows = np.zeros((0, 3)), np.zeros(0), np.zeros(0), np.zeros(0)

    basis = "nominal"
    res_model, theta = model, model.nominal()
    try:
        found = _served_theta(ErrorModel, served, model)
    except (InputError, KeyError, TypeError, ValueError):
        found = None
    if found is not None:
        res_model, theta, basis = found
    residual_mg = np.zeros(0)
    if n:
        temp_in = np.where(np.isfinite(temp), temp, res_model.temp_ref_c)  # a cell without temperature: the reference
        residual_mg = res_model.residuals(theta, data.mean, temp_in, t_mean) * 1e3
    finite = residual_mg[np.isfinite(residual_mg)]
    rms = float(np.sqrt(np.mean(finite**2))) if finite.size else None

    # the norm error along each direction: the fit's covariance against the prior's
    prior = datasheet_prior(model, cal.fit_cfg)
    current = cal.current
    theta_cov = np.asarray(current["theta_u"], float) if current else model.nominal()
    cov = np.asarray(current["cov_u"], float) if current else prior.cov
    grid = sphere_directions(n_directions)
    jac = sphere_jacobian(model, theta_cov, None, n_directions)
    sd_mg = np.sqrt(np.maximum(np.einsum("ij,jk,ik->i", jac, cov, jac), 0.0)) * 1e3
    prior_sd_mg = np.sqrt(np.maximum(np.einsum("ij,jk,ik->i", jac, prior.cov, jac), 0.0)) * 1e3
    threshold_mg = float(cal.sched_cfg.calibrated_max_sphere_mg)
    undetermined = sd_mg > threshold_mg

    return {
        "available": True,
        "note": None,
        "version": served_version,
        "model": res_model.name,
        "residual_basis": basis,
        "n_poses": n,
        "direction": _rounded(direction, 5),
        "temp_c": _rounded(temp, 2),
        "residual_mg": _rounded(residual_mg, 3),
        "windows": [int(w) for w in windows],
        "t_s": _rounded(t_mean, 1),
        "residual_rms_mg": None if rms is None else round(rms, 4),
        "undetermined_above_sd_mg": threshold_mg,
        "sphere": {
            "direction": _rounded(grid, 4),
            "sd_mg": _rounded(sd_mg, 3),
            "prior_sd_mg": _rounded(prior_sd_mg, 3),
            "undetermined": [bool(u) for u in undetermined],
        },
    }
