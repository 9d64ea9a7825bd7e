"""Published calibration versions scored against a simulation's truth.

``selfcal simulate --out SIM.csv`` writes the truth beside the recording
(``SIM.truth.json``, :func:`truth_path`). Every version the online calibrator publishes
over that recording (``selfcal calibrate SIM.csv --history H.jsonl``, ``selfcal replay
--recording SIM.csv``) is scored against it (:class:`TruthScorer`):

* ``z``: the parameter errors in reported sds, ``(est - true) / std``, every parameter;
* ``true_mg``: the true whole-sphere calibrated-norm RMS error (2000 directions, the
  true sensor at the reference temperature, at the version's time), beside the
  version's own ``predicted_sphere_rms_mg`` (``predicted_mg``).

Per run (:func:`run_figures`): versions, versions per week, time to the first
``calibrated``, the final error against ``max(0.5 mg, 2 x CRLB)``, where the CRLB
(:func:`crlb_sphere_mg`) is the Cramér-Rao whole-sphere error of the run's still
windows (each independent, with its own noise along gravity and the 0.3 mg floor) plus
the datasheet prior, propagated to the sphere exactly as ``predicted_sphere_rms_mg`` is.
Over the calibrated versions of one run or many (:func:`consistency_figures`): the
share of parameter errors within 2 sd, the largest, the share of versions whose true
error is within ``2.5 x predicted + 0.05 mg``, and the jumps (a calibrated version
whose true error exceeds 1.5 x the previous one's + 0.5 mg).

Used by ``selfcal replay --recording`` and ``bench/consistency.py`` (which adds the
acceptance checks).
"""

from __future__ import annotations

import json
import os
from pathlib import Path
from typing import Iterable

import numpy as np

from selfcal.errors import InputError
from selfcal.fit import FitConfig, datasheet_prior, predicted_sphere_rms_mg, sphere_directions
from selfcal.models import ErrorModel

#: ``format`` of the truth files ``selfcal simulate`` writes.
TRUTH_FORMAT = "selfcal-sim-truth v1"
#: A version keeps its sphere promise when true <= RATIO x predicted + SLACK_MG.
PROMISE_RATIO, PROMISE_SLACK_MG = 2.5, 0.05
#: A jump: a calibrated version whose true error exceeds JUMP_RATIO x the previous + JUMP_MG.
JUMP_RATIO, JUMP_MG = 1.5, 0.5
#: The final error's target: max(FINAL_FLOOR_MG, FINAL_CRLB_FACTOR x CRLB).
FINAL_FLOOR_MG, FINAL_CRLB_FACTOR = 0.5, 2.0


def truth_path(recording: str | os.PathLike) -> Path:
    """Where ``selfcal simulate`` puts the truth of ``recording`` (``x.csv`` -> ``x.truth.json``)."""
    p = Path(recording)
    stem = p.name[:-4] if p.name.lower().endswith(".csv") else p.name
    return p.with_name(stem + ".truth.json")


def load_truth(path: str | os.PathLike) -> dict:
    """Read a truth file written by ``selfcal simulate``; InputError naming what is wrong."""
    name = os.fspath(path)
    try:
        text = Path(path).read_text(encoding="utf-8")
    except FileNotFoundError as exc:
        raise InputError(f"{name}: no such truth file") from exc
    except IsADirectoryError as exc:
        raise InputError(f"{name}: is a directory, not a truth file") from exc
    except (OSError, UnicodeDecodeError) as exc:
        raise InputError(f"{name}: cannot read the truth file ({getattr(exc, 'strerror', None) or exc})") from exc
    try:
        truth = json.loads(text)
    except json.JSONDecodeError as exc:
        raise InputError(f"{name}:{exc.lineno}:{exc.colno}: not JSON ({exc.msg}); a truth file is the "
                         f"'.truth.json' that selfcal simulate writes") from exc
    if not isinstance(truth, dict) or truth.get("format") != TRUTH_FORMAT:
        raise InputError(f"{name}: not a selfcal truth file (expected format {TRUTH_FORMAT!r})")
    missing = [k for k in ("matrix", "offset", "params", "effects", "effect_params", "temp_ref_c") if k not in truth]
    if missing:
        raise InputError(f"{name}: truth file without {missing}")
    return truth


def version_row(calibration: dict) -> dict:
    """The truth-free part of a published version's score: version, time, status, prediction."""
    return {"version": calibration["version"], "t_s": calibration["t_s"], "status": calibration["status"],
            "predicted_mg": calibration["predicted_sphere_rms_mg"]}


class TruthScorer:
    """Scores published versions (calibration JSON in g) against a truth dict.

    ``model_name`` is the model of the CRLB and of :attr:`truth_u`; each version is scored
    under its own ``model`` (online model selection may change it between versions)."""

    def __init__(self, truth: dict, model_name: str, n_dirs: int = 2000):
        from selfcal.sim.sensor import SensorTruth

        self.truth = truth
        self.sensor = SensorTruth.from_dict(truth)
        self._models: dict[str, tuple[ErrorModel, np.ndarray]] = {}
        self.model, self.truth_u = self._of(model_name)
        self.dirs = sphere_directions(n_dirs)

    @staticmethod
    def _truth_in(model: ErrorModel, known: dict[str, float]) -> np.ndarray:
        """The truth ``known`` (parameter name -> value) as ``model``'s vector (its names only)."""
        names = set(model.param_names)
        return model.from_dict({k: v for k, v in known.items() if k in names})

    def _of(self, model_name: str) -> tuple[ErrorModel, np.ndarray]:
        """The model of that name (the truth's reference temperature and time) and the truth in it."""
        if model_name not in self._models:
            model = ErrorModel(model_name, self.truth["temp_ref_c"], float(self.truth.get("time_origin_s", 0.0)))
            known = {**self.truth["params"], **self.truth["effect_params"]}
            self._models[model_name] = (model, self._truth_in(model, known))
        return self._models[model_name]

    def sphere_rms_mg(self, theta_u: np.ndarray, t_s: float, model: ErrorModel | None = None) -> float:
        """True calibrated-norm RMS error (mg) over the sphere, at the reference temperature and ``t_s``."""
        from selfcal.sim.sensor import sensor_mean

        model = model or self.model
        temp = np.full(len(self.dirs), self.sensor.temp_ref_c)
        tt = np.full(len(self.dirs), float(t_s))
        raw = sensor_mean(self.sensor, self.dirs, temp, tt)
        a = model.apply(theta_u, raw, temp, tt)
        return float(np.sqrt(np.mean((np.linalg.norm(a, axis=1) - 1) ** 2)) * 1e3)

    def score(self, calibration: dict) -> dict:
        """One published version: :func:`version_row` plus ``true_mg`` and ``z`` (per parameter of its model)."""
        model, truth_u = self._of(calibration.get("model", self.model.name))
        t_s = float(calibration["t_s"])
        if t_s >= self.sensor.step_at_s:  # after a bias step the truth is the sensor as it now is
            truth_u = self._truth_in(model, {**self.sensor.params_at(t_s), **self.truth["effect_params"]})
        theta = model.from_dict(calibration["params"])
        std = np.array([calibration["std"][n] for n in model.param_names])
        row = version_row(calibration)
        return {"version": row["version"], "t_s": row["t_s"], "status": row["status"],
                "true_mg": self.sphere_rms_mg(theta, calibration["t_s"], model), "predicted_mg": row["predicted_mg"],
                "z": ((theta - truth_u) / std).tolist()}

    def score_all(self, calibrations: Iterable[dict]) -> list[dict]:
        """:meth:`score` of every version, in order."""
        return [self.score(c) for c in calibrations]


def fisher_information(model: ErrorModel, truth_u: np.ndarray, rec, cfg: FitConfig | None = None) -> np.ndarray:
    """Fisher information (p, p) at the truth of a poses recording (or a block of one), without prior.

    Each still window is independent, with its own noise along gravity and the fit's
    ``sigma_floor_g``; the information of a file is the sum over its blocks.
    """
    from selfcal.poses import PoseConfig, window_noise_var

    cfg = cfg or FitConfig()
    a = model.apply(truth_u, rec.acc, rec.temp_c, rec.t_s)
    u = a / np.linalg.norm(a, axis=1, keepdims=True)
    rate = float(rec.meta.get("rate_hz", 20.0))
    sd = rec.sd if rec.sd is not None else np.full_like(rec.acc, cfg.default_sample_sd_g)
    var = window_noise_var(u, sd, rec.n, rate, PoseConfig()) + cfg.sigma_floor_g**2
    _, jac = model.residual_jac(truth_u, rec.acc, rec.temp_c, rec.t_s)
    jw = jac / np.sqrt(var)[:, None]
    return jw.T @ jw


def crlb_from_information(model: ErrorModel, truth_u: np.ndarray, info: np.ndarray, t_s: float,
                          cfg: FitConfig | None = None) -> float:
    """Cramér-Rao whole-sphere error (mg) of ``info`` plus the datasheet prior, at time ``t_s``."""
    prior = datasheet_prior(model, cfg or FitConfig())
    cov = np.linalg.inv(info + prior.precision())
    return predicted_sphere_rms_mg(model, truth_u, cov, t_s)


def crlb_sphere_mg(model: ErrorModel, truth_u: np.ndarray, rec, t_s: float) -> float:
    """Cramér-Rao whole-sphere error (mg) of a poses recording, with the datasheet prior."""
    return crlb_from_information(model, truth_u, fisher_information(model, truth_u, rec), t_s)


def poses_file_information(path, model: ErrorModel, truth_u: np.ndarray,
                           block_rows: int = 100_000) -> tuple[np.ndarray, int, float] | None:
    """:func:`fisher_information` of a poses file, streamed in blocks: ``(info, n_poses, last t_s)``.

    None for a samples table (its still windows are the detector's, not the file's rows).
    """
    from selfcal.io import iter_recording

    info = np.zeros((model.n_params, model.n_params))
    n, last_t = 0, float("nan")
    blocks = iter_recording(path, block_rows)
    try:
        for rec in blocks:
            if rec.kind != "poses":
                return None
            if len(rec) == 0:
                continue
            info += fisher_information(model, truth_u, rec)
            n += len(rec)
            last_t = float(rec.t_s[-1])
    finally:
        blocks.close()
    return info, n, last_t


def efficient_reference(model_name: str, truth: dict, poses, t_end_s: float) -> dict:
    """What an efficient estimator achieves on a simulation's still windows.

    ``poses`` is the simulator's :class:`selfcal.sim.simulator.PoseTable` (the windows a
    poses recording holds, with ``noise_var_g2``, the true variance of each window mean).
    Returns ``crlb_mg``: the Cramér-Rao whole-sphere error of those windows with their true
    noise and the datasheet prior; ``oracle_mg``: the true whole-sphere error of the MAP fit
    (datasheet prior) weighted by that true noise, started at the truth; both at ``t_end_s``.
    The oracle knows what no calibrator can (each window's true noise), so its error is the
    floor an online estimator is measured against: even it exceeds ``2 x crlb_mg`` on a few
    per cent of weeks (README). When the truth has a bias step, both also know its time:
    they use ``model_name`` plus ``bias_step`` at that time (the offset before it and the
    jump), so the reference is the sensor as it is at ``t_end_s``, not one offset fitted
    across the step.
    """
    from selfcal.fit import NoiseModel, PoseData, fit_poses

    scorer = TruthScorer(truth, model_name)
    model, truth_u = scorer.model, scorer.truth_u
    step_at = scorer.sensor.step_at_s
    if np.isfinite(step_at) and model.takes("bias_step"):
        from selfcal.sim.sensor import EFFECT_MODEL_PARAMS

        model = ErrorModel(f"{model_name}+bias_step", model.temp_ref_c, model.t_ref_s, float(step_at))
        factor, names = EFFECT_MODEL_PARAMS["bias_step"]
        step = dict(zip(names, factor * scorer.sensor.effects["bias_step"]))
        truth_u = scorer._truth_in(model, {**truth["params"], **truth["effect_params"], **step})
    t_s = np.asarray(poses.t_s, float) + 0.5 * np.asarray(poses.duration_s, float)
    data = PoseData(poses.mean_g, np.sqrt(poses.noise_var_g2), np.ones(len(t_s)), t_s, poses.temp_c)
    cfg = FitConfig(sigma_floor_g=0.0)
    sigma = NoiseModel.from_poses(data.mean, data.sd, data.count, cfg, model, data.temp_c, t_s).sigma(truth_u)
    _, jac = model.residual_jac(truth_u, data.mean, data.temp_c, t_s)
    jw = jac / sigma[:, None]
    crlb = crlb_from_information(model, truth_u, jw.T @ jw, t_end_s, cfg)
    fit = fit_poses(model, data, prior=datasheet_prior(model, cfg), theta0_u=truth_u, cfg=cfg)
    return {"crlb_mg": crlb, "oracle_mg": scorer.sphere_rms_mg(fit.theta_u, t_end_s, model)}


def _calibrated(rows: list[dict]) -> list[dict]:
    return [v for v in rows if v["status"] == "calibrated"]


def run_figures(rows: list[dict], days: float | None = None, crlb_mg: float | None = None) -> dict:
    """One run's figures from its scored versions (or truth-free :func:`version_row` s).

    ``days``: the run's length (versions per week); ``crlb_mg``: its CRLB (the final target).
    Figures that need what was not given are None.
    """
    cal = _calibrated(rows)
    final = rows[-1] if rows else None
    final_true = final.get("true_mg") if final else None
    target = None if crlb_mg is None else max(FINAL_FLOOR_MG, FINAL_CRLB_FACTOR * crlb_mg)
    return {
        "versions": len(rows),
        "versions_per_week": len(rows) / (days / 7.0) if days else None,
        "calibrated_versions": len(cal),
        "first_calibrated_h": cal[0]["t_s"] / 3600 if cal else None,
        "final_status": final["status"] if final else None,
        "final_true_mg": final_true,
        "final_predicted_mg": final["predicted_mg"] if final else None,
        "crlb_sphere_mg": crlb_mg,
        "final_target_mg": target,
        "final_ok": None if target is None else bool(final_true is not None and final_true <= target),
    }


def consistency_figures(runs: Iterable[list[dict]]) -> dict:
    """Over the calibrated versions of one or more runs (lists of scored versions), pooled."""
    zs, ratio_ok, jumps, pairs = [], [], 0, 0
    for rows in runs:
        cal = _calibrated(rows)
        for v in cal:
            zs.extend(np.abs(v["z"]))
            ratio_ok.append(v["true_mg"] <= PROMISE_RATIO * v["predicted_mg"] + PROMISE_SLACK_MG)
        for a, b in zip(cal, cal[1:]):
            pairs += 1
            jumps += b["true_mg"] > JUMP_RATIO * a["true_mg"] + JUMP_MG
    z = np.asarray(zs)
    return {
        "within_2sd": float(np.mean(z <= 2)) if z.size else None,
        "max_abs_z": float(z.max()) if z.size else None,
        "sphere_ratio_ok": float(np.mean(ratio_ok)) if ratio_ok else None,
        "jumps": int(jumps), "pairs": int(pairs), "jump_fraction": jumps / pairs if pairs else 0.0,
    }
